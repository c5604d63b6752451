"""Sliding-window workflow speed and memory against the length of the sequence.

Synthetic streets (simulate.synthetic: three cameras per station, 2 m between stations, GNSS
with a bias of about 2 m for every image, the SfM input bent by a smooth drift of 1 % of the
street's length at its far end) of 250, 500 and 1,000 images, each refined with
`[workflow] mode = "sliding_window"` (the source's windows: 100 images, 33 new per window) in
a fresh subprocess, so that every size's peak resident memory is its own. Per size: seconds
of the windows alone, of the whole refine (the global GNSS-only adjustment before and the
final global hybrid adjustment after the windows included), seconds per image of each, peak
RSS (MB) of the whole run, resident memory when the windows start and its peak while they run
(sampled every 0.05 s: the global adjustments of the whole block set the run's peak, the
windows hold 100 images each), and camera centres against the truth (RMS 3D, m).

The baseline is the 250-image sequence of the same run: `window_time_ratio_1000` is the
windows' seconds per image at 1,000 images over that at 250 (1 = linear growth). Prints last
the lines `seconds_per_image_250`, `seconds_per_image_500`, `seconds_per_image_1000` (whole
refine), `window_seconds_per_image_250`, `window_seconds_per_image_1000`,
`window_time_ratio_1000`, `peak_rss_mb_250`, `peak_rss_mb_1000` and
`window_rss_growth_mb_<size>` (peak in the windows minus resident memory at their start).

    .venv/bin/python benchmarks/bench_sequential.py [--sizes 250 500 1000] [--results FILE]
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


class ResidentMemory:
    """Samples this process's resident memory (VmRSS, MB) every `interval` seconds in a
    thread, so that the peak of one phase can be told from the peak of the whole run."""

    def __init__(self, interval: float = 0.05):
        import threading

        self.interval, self.samples = interval, []  # (perf_counter, MB)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def now_mb() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * resource.getpagesize() / 2**20

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append((time.perf_counter(), self.now_mb()))
            self._stop.wait(self.interval)

    def __enter__(self) -> "ResidentMemory":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def peak(self, start: float, end: float) -> float:
        inside = [mb for t, mb in self.samples if start <= t <= end]
        return max(inside) if inside else float("nan")


def child(num_images: int) -> dict:
    """One sequence in this process: build, refine with the sliding window, measure."""
    import numpy as np

    import colmap_citymodel  # noqa: F401  (sets up the package logger first)
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.simulate.synthetic import (
        StreetSceneOptions,
        centre_errors,
        make_street_scene,
    )
    from colmap_citymodel.workflow import refine

    logging.getLogger("colmap_citymodel").setLevel(logging.WARNING)
    start = time.perf_counter()
    scene = make_street_scene(StreetSceneOptions(num_stations=num_images // 3, seed=5))
    build = time.perf_counter() - start
    rss_scene = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    options = RefineOptions()
    options.precision.covariances = "off"
    options.workflow.mode = "sliding_window"
    # the windows' own phase: from the first window to the last (the global adjustments of the
    # whole block before and after them set the process's peak)
    import colmap_citymodel.adjust.sliding_window as windows_module

    phase = {}
    run_windows = windows_module.sliding_window

    def timed_windows(*args, **kwargs):
        phase["start"], phase["rss_at_start"] = time.perf_counter(), ResidentMemory.now_mb()
        try:
            return run_windows(*args, **kwargs)
        finally:
            phase["end"] = time.perf_counter()

    windows_module.sliding_window = timed_windows
    start = time.perf_counter()
    with ResidentMemory() as memory:
        result = refine(scene.sfm, scene.store, scene.gnss(), options, progress=False)
    seconds = time.perf_counter() - start
    windows_module.sliding_window = run_windows
    errors = centre_errors(result.reconstruction, scene.truth)
    windows = result.sliding_window
    images = result.reconstruction.num_reg_images()
    return {"num_images": images, "num_points3D": result.reconstruction.num_points3D(),
            "num_windows": windows["num_windows"], "build_seconds": build,
            "refine_seconds": seconds, "window_seconds": windows["seconds"],
            "seconds_per_image": seconds / images,
            "window_seconds_per_image": windows["seconds"] / images,
            "stage_seconds": result.seconds,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
            "peak_rss_mb_after_scene": rss_scene,
            "rss_mb_at_windows_start": phase["rss_at_start"],
            "peak_rss_mb_windows": memory.peak(phase["start"], phase["end"]),
            "camera_rms_3d_m": float(np.sqrt(np.mean(errors ** 2))),
            "verdict": result.quality.verdict}


def measure(num_images: int) -> dict:
    out = subprocess.run([sys.executable, __file__, "--child", str(num_images)],
                         capture_output=True, text=True, cwd=ROOT)
    if out.returncode:
        raise RuntimeError(f"{num_images} images: {out.stderr[-2000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def table(runs: dict) -> str:
    lines = ["| images | points | windows | windows s | refine s | windows s/image | "
             "refine s/image | peak RSS MB | RSS MB at windows' start | peak RSS MB in windows | "
             "camera RMS 3D m | verdict |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in runs.values():
        lines.append(f"| {r['num_images']} | {r['num_points3D']} | {r['num_windows']} | "
                     f"{r['window_seconds']:.0f} | {r['refine_seconds']:.0f} | "
                     f"{r['window_seconds_per_image']:.3f} | {r['seconds_per_image']:.3f} | "
                     f"{r['peak_rss_mb']:.0f} | {r['rss_mb_at_windows_start']:.0f} | "
                     f"{r['peak_rss_mb_windows']:.0f} | {r['camera_rms_3d_m']:.3f} | "
                     f"{r['verdict']} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", type=int, nargs="+", default=[250, 500, 1000])
    parser.add_argument("--results", type=Path, default=None,
                        help="write the table (markdown) and the figures (.json beside it)")
    parser.add_argument("--child", type=int, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        print(json.dumps(child(args.child)))
        return
    runs = {}
    for size in args.sizes:
        print(f"{size} images: ...", flush=True)
        runs[size] = measure(size)
        r = runs[size]
        print(f"  {r['num_images']} images, {r['num_windows']} windows: windows "
              f"{r['window_seconds']:.0f} s, refine {r['refine_seconds']:.0f} s, peak RSS "
              f"{r['peak_rss_mb']:.0f} MB, cameras {r['camera_rms_3d_m']:.3f} m", flush=True)
    text = table(runs)
    print(text)
    if args.results:
        args.results.write_text(
            "# Sliding-window workflow: time and memory against the sequence length\n\n"
            "Produced by\n\n    .venv/bin/python benchmarks/bench_sequential.py --results "
            f"{args.results}\n\nSynthetic streets, windows of 100 images with 33 new each, "
            "then the global adjustment; the SfM input bent by 1 % of the street's length at "
            "its far end; each size in its own process (2-core machine shared with other "
            "jobs: compare sizes of the same run).\n\n" + text)
        args.results.with_suffix(".json").write_text(json.dumps(runs, indent=2))
    base = runs.get(250) or runs[min(runs)]
    for size, r in runs.items():
        print(f"seconds_per_image_{size} {r['seconds_per_image']:.4f}")
    for size, r in runs.items():
        print(f"window_seconds_per_image_{size} {r['window_seconds_per_image']:.4f}")
    for size, r in runs.items():
        if r is not base:
            print(f"window_time_ratio_{size} "
                  f"{r['window_seconds_per_image'] / base['window_seconds_per_image']:.3f}")
    for size, r in runs.items():
        print(f"peak_rss_mb_{size} {r['peak_rss_mb']:.1f}")
    for size, r in runs.items():
        print(f"window_rss_growth_mb_{size} "
              f"{r['peak_rss_mb_windows'] - r['rss_mb_at_windows_start']:.1f}")


if __name__ == "__main__":
    main()
