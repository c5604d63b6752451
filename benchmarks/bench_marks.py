"""Ground control and check marks on the synthetic street: does refine use control marks
beside GNSS and the model, name a wrong one, place a block without GNSS, and state the check
marks' accuracy as an independent triangulation finds it?

The street of the tests (simulate.synthetic, seed 7: 72 images along 48 m, a LOD2 model, GNSS
with a constant bias of 4.0 m (3.0, -2.0, 1.7) plus a slowly varying 0.5 m, stated sigma 3, 3,
5 m). Ten marks from the truth, spread along the street (simulate.synthetic.street_marks: true
surface points seen in at least 8 images), measured with 0.7 px noise: odd ones control, even
ones check, written as gcp_list.txt files (EPSG:25832) and read back as a user's would be.

Cases: GNSS + model + control marks; the same with one control mark's coordinates 2 m off
(1.2 m E, 1.6 m N); with two control marks' names swapped; control marks and model without
GNSS; GNSS and model without control marks. Per case: the camera centres' RMS against the
truth, the check marks' RMS 3D as refine reports it and as an independent triangulation from
the refined cameras gives it (block.marks.triangulate_mark), the check test, the control marks
left out, the verdict, the marks' and GNSS's share of the information on E, N, U, seconds.

    .venv/bin/python benchmarks/bench_marks.py      # writes benchmarks/results/marks.md
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from colmap_citymodel.block.marks import (measurements_in, read_gcp_list, triangulate_mark,
                                          write_gcp_list)
from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.simulate.synthetic import (StreetSceneOptions, centre_errors,
                                                 make_street_scene, street_marks)
from colmap_citymodel.workflow import refine

RESULTS = Path(__file__).resolve().parent / "results"
CASES = {
    "GNSS 4 m off + model + 5 control marks": {"gnss": True, "marks": True},
    "the same, one control mark 2 m off": {"gnss": True, "marks": True, "off": "M3"},
    "the same, two control marks' names swapped": {"gnss": True, "marks": True,
                                                   "swap": ("M5", "M7")},
    "model + 5 control marks, no GNSS": {"gnss": False, "marks": True},
    "GNSS 4 m off + model, no marks": {"gnss": True, "marks": False},
}


def rows(marks, off=None, swap=None):
    """gcp_list rows of `marks`; `off`: a mark 2 m off; `swap`: two marks' coordinates
    exchanged."""
    position = {name: xyz for name, xyz, _ in marks}
    out = []
    for name, xyz, observations in marks:
        if name == off:
            xyz = xyz + np.array([1.2, 1.6, 0.0])
        if swap and name in swap:
            xyz = position[swap[1 - swap.index(name)]]
        out += [(xyz, image, x, y, name) for image, x, y in observations]
    return out


def independent_rms(result, check, origin) -> float:
    """The check marks' RMS 3D (m) from the refined cameras by block.marks' triangulation."""
    rec = result.reconstruction
    errors = [triangulate_mark(rec, measurements_in(rec, m)[0])[0] + origin - m.position
              for m in check.marks]
    return float(np.linalg.norm(np.sqrt(np.mean(np.square(errors), axis=0))))


def run_case(scene, marks, case: dict, directory: Path) -> dict:
    control_rows = rows(marks[0::2], case.get("off"), case.get("swap"))
    write_gcp_list(directory / "gcp_list.txt", "EPSG:25832", control_rows)
    write_gcp_list(directory / "check.txt", "EPSG:25832", rows(marks[1::2]))
    control = read_gcp_list(directory / "gcp_list.txt", scene.store.crs)
    check = read_gcp_list(directory / "check.txt", scene.store.crs)
    start = time.perf_counter()
    result = refine(scene.sfm, scene.store, scene.gnss() if case["gnss"] else None,
                    RefineOptions(), progress=False,
                    marks=control if case["marks"] else None, check_marks=check)
    seconds = time.perf_counter() - start
    accuracy = result.checkpoints.accuracy
    shares = {axis: result.observability[axis].get("shares", {}) for axis in "ENU"}
    return {"cameras_rms_m": float(np.sqrt(np.mean(centre_errors(result.reconstruction,
                                                                   scene.truth) ** 2))),
            "check_rms_3d_m": accuracy["rmse_3d_m"],
            "independent_rms_3d_m": independent_rms(result, check, scene.store.origin),
            "check_test": accuracy["test"], "verdict": result.quality.verdict,
            "left_out": sorted((result.control_marks or {}).get("blunders", {})),
            "shares": shares, "seconds": seconds}


def table(results: dict) -> str:
    lines = ["| case | cameras RMS (m) | check marks RMS 3D (m) | independent triangulation "
             "(m) | check test | control marks left out | gcp / GNSS share of E, N, U "
             "| verdict | s |", "|---|---|---|---|---|---|---|---|---|"]
    for name, r in results.items():
        shares = " / ".join(
            f"{100 * np.mean([r['shares'][a].get(s, 0.0) for a in 'ENU']):.1f} %"
            for s in ("gcp", "gnss")) if any(r["shares"].values()) else "-"
        lines.append(f"| {name} | {r['cameras_rms_m']:.4f} | {r['check_rms_3d_m']:.4f} | "
                     f"{r['independent_rms_3d_m']:.4f} | "
                     f"{'passed' if r['check_test']['passed'] else 'failed'} "
                     f"({r['check_test']['statistic']:.1f} on {r['check_test']['dof']}) | "
                     f"{', '.join(r['left_out']) or 'none'} | {shares} | {r['verdict']} | "
                     f"{r['seconds']:.0f} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=list(CASES), help="case names to run")
    parser.add_argument("--table_only", action="store_true",
                        help="write marks.md from the results in marks.json")
    args = parser.parse_args()
    if args.table_only:
        results = json.loads((RESULTS / "marks.json").read_text())
        (RESULTS / "marks.md").write_text(table(results))
        return
    logging.getLogger("colmap_citymodel").setLevel(logging.WARNING)
    scene = make_street_scene(StreetSceneOptions(seed=7, gnss_bias=(3.0, -2.0, 1.7)),
                              crs=user_crs("EPSG:25832"))
    marks = street_marks(scene, 10, 0.7, seed=1, min_views=8)
    results = {}
    for name in args.cases:
        with tempfile.TemporaryDirectory() as directory:
            results[name] = run_case(scene, marks, CASES[name], Path(directory))
        print(name, json.dumps(results[name], default=str)[:300])
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "marks.json").write_text(json.dumps(results, indent=2, default=str))
    (RESULTS / "marks.md").write_text(table(results))
    print(table(results))


if __name__ == "__main__":
    main()
