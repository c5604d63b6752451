"""Streaming read of a large CityGML file: throughput and peak memory against the store's size.

Builds a synthetic city (>= 200 MB; `--quick` ~20 MB) by tiling the 35 real Berlin buildings of
`tests/data/citygml/berlin/3910_5819.gml` on a grid with shifted coordinates and new gml:ids
(xlinks renamed with them), writes it to a temporary file, then reads it in a fresh subprocess
(so nothing of the generation is in its memory) and prints

    read_mb_per_s     file size / wall time of read_city_model (parse + build_store)
    read_mb_per_cpu_s the same per CPU second (robust when other jobs share the machine)
    parse_mb_per_s    file size / wall time of the streaming parse alone (read_citygml)
    parse_peak_rss_mb peak resident memory of that parse (RawCityModel) minus the memory before
    peak_rss_mb       peak resident memory during the read minus the resident memory before it
    store_mb          nbytes of the store's numpy arrays + its faces' arrays (rings, and the
                      string columns: semantic/building/part codes, gml:id bytes + offsets)
    store_py_mb       the same plus the Python objects of the faces (Face, lists, id strings)
    peak_over_store   peak_rss_mb / store_mb   (target < 2)
    peak_over_store_py peak_rss_mb / store_py_mb

Peak RSS is measured in the child via /proc/self/status (VmHWM reset through
/proc/self/clear_refs before the read; resource.getrusage as fallback).

    python benchmarks/bench_read_citygml.py [--quick] [--size_mb 200] [--keep] [--file CITY.gml]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

SOURCE = Path(__file__).resolve().parents[1] / "tests" / "data" / "citygml" / "berlin" / "3910_5819.gml"

_COORDS = re.compile(r"(<gml:(?:posList|pos|lowerCorner|upperCorner)\b[^>]*>)([^<]*)(<)")
_IDS = re.compile(r'(gml:id="|xlink:href="#)([^"]+)(")')


def _template(text: str):
    """Split a member's text into static pieces and coordinate arrays (N,3)."""
    pieces, arrays = [], []
    last = 0
    for m in _COORDS.finditer(text):
        pieces.append(text[last:m.end(1)])
        arrays.append(np.array(m.group(2).split(), dtype=np.float64).reshape(-1, 3))
        last = m.start(3)
    pieces.append(text[last:])
    return pieces, arrays


def _fmt(a: np.ndarray) -> str:
    return " ".join(map(repr, a.ravel().tolist()))


def make_city(path: Path, size_mb: float) -> dict:
    text = SOURCE.read_text(encoding="utf-8")
    start = text.index("<cityObjectMember>")
    end = text.rindex("</cityObjectMember>") + len("</cityObjectMember>")
    header, body, footer = text[:start], text[start:end], text[end:]
    # drop the model envelope (it would not cover the tiled city)
    header = re.sub(r"<gml:boundedBy>.*?</gml:boundedBy>", "", header, flags=re.S)
    pieces, arrays = _template(body)
    lo = np.min([a.min(0) for a in arrays], axis=0)
    hi = np.max([a.max(0) for a in arrays], axis=0)
    step = np.ceil((hi - lo)[:2] / 100.0) * 100.0 + 100.0
    per_copy = len(body.encode())
    copies = max(1, int(np.ceil(size_mb * 1e6 / per_copy)))
    side = int(np.ceil(np.sqrt(copies * step[1] / step[0])))
    with open(path, "w", encoding="utf-8") as f:
        f.write(header)
        for k in range(copies):
            i, j = k % side, k // side
            shift = np.array([i * step[0], j * step[1], 0.0])
            out = []
            for piece, arr in zip(pieces, arrays + [None]):
                out.append(piece)
                if arr is not None:
                    out.append(_fmt(arr + shift))
            member = "".join(out)
            f.write(_IDS.sub(lambda m, k=k: f"{m.group(1)}{m.group(2)}_c{k}{m.group(3)}", member))
        f.write(footer)
    return {"copies": copies, "buildings": 35 * copies, "polygons": 1207 * copies}


# ---------------------------------------------------------------------------------------------
# child: the measured read
# ---------------------------------------------------------------------------------------------


def _status_kb(key: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def _reset_peak() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def store_nbytes(store) -> tuple[int, int, int]:
    """(nbytes of the store's numpy arrays incl. the faces' ring index arrays and string columns,
    that + the Python objects that stay with the store: per-face lists/Face objects, id strings,
    the string columns' share of the first)."""
    arrays = [store.origin, store.vertices, store.centroids, store.rotations, store.areas,
              store.rms_out_of_plane, store.nonplanar]
    n = sum(a.nbytes for a in arrays)
    faces = store.faces
    seen: set[int] = set()
    columns = 0

    def strings(values) -> int:
        k = 0
        for s in values:
            if id(s) not in seen:
                seen.add(id(s))
                k += sys.getsizeof(s)
        return k

    if hasattr(faces, "ring_vertex"):  # flat ring arrays (FaceList)
        n += faces.ring_vertex.nbytes + faces.ring_ptr.nbytes + faces.face_ring.nbytes + faces.lod.nbytes
        py = sys.getsizeof(faces)
        for values in (faces.semantic, faces.building_id, faces.part_id, faces.gml_id):
            if isinstance(values, list):  # per-face str objects in a list
                py += sys.getsizeof(values) + strings(values)
            else:  # string columns: codes / UTF-8 bytes + offsets (arrays), distinct strings
                n += values.nbytes()
                columns += values.nbytes()
                py += sys.getsizeof(values) + strings(getattr(values, "categories", ()))
        return n, n + py, columns
    py = n  # a list of Face objects with their own index arrays
    for face in faces:
        n += face.exterior.nbytes + sum(h.nbytes for h in face.holes)
        py += sys.getsizeof(face) + (sys.getsizeof(face.__dict__) if hasattr(face, "__dict__") else 0)
        py += sys.getsizeof(face.exterior) + sys.getsizeof(face.holes) + sum(sys.getsizeof(h) for h in face.holes)
        py += strings((face.gml_id, face.building_id, face.part_id, face.semantic))
    return n, py, 0


def child(path: str, mode: str) -> None:
    import gc

    from colmap_citymodel.citymodel.read import read_city_model
    from colmap_citymodel.citymodel.read_citygml import read_citygml

    # warm up: imports, pyproj database, lxml
    read_city_model(SOURCE)
    gc.collect()
    base = _status_kb("VmRSS")
    reset = _reset_peak()
    base_hwm = _status_kb("VmHWM") if reset else None
    import resource

    t0 = time.perf_counter()
    c0 = time.process_time()
    if mode == "parse":
        raw = read_citygml(path)
        result = {"polygons": len(raw.polygons), "buildings": len(raw.building_ids)}
    else:
        store = read_city_model(path)
        result = {"faces": store.num_faces, "buildings": store.num_buildings, "vertices": len(store.vertices)}
    seconds = time.perf_counter() - t0
    cpu_seconds = time.process_time() - c0
    peak = _status_kb("VmHWM") if reset else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    result.update(seconds=seconds, cpu_seconds=cpu_seconds, base_rss_kb=base, peak_rss_kb=peak, peak_reset=reset, base_hwm_kb=base_hwm)
    if mode != "parse":
        result["store_bytes"], result["store_py_bytes"], result["store_column_bytes"] = store_nbytes(store)
    print("RESULT " + json.dumps(result))


def run_child(path: Path, mode: str) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = str(Path(__file__).resolve().parents[1]) + os.pathsep + env.get("PYTHONPATH", "")
    run = subprocess.run(
        [sys.executable, __file__, "--child", str(path), "--mode", mode],
        capture_output=True, text=True, env=env,
    )
    if run.returncode != 0:
        sys.stderr.write(run.stderr)
        raise SystemExit(f"child failed ({mode})")
    line = next(line for line in run.stdout.splitlines() if line.startswith("RESULT "))
    return json.loads(line[len("RESULT "):])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="~20 MB instead of 200 MB")
    parser.add_argument("--size_mb", type=float, default=None, help="file size to generate (MB)")
    parser.add_argument("--keep", action="store_true", help="keep the generated file")
    parser.add_argument("--file", default=None, help="read this (earlier generated) file instead of generating one")
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--mode", default="full", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child:
        child(args.child, args.mode)
        return
    if not SOURCE.is_file():
        raise SystemExit(f"source file not found: {SOURCE}")
    size_mb = args.size_mb or (20.0 if args.quick else 205.0)
    if args.file:
        path = Path(args.file)
        tmp = None
    else:
        tmp = Path(tempfile.mkdtemp(prefix="bench_citygml_"))
        path = tmp / "synthetic_city.gml"
    try:
        if tmp is not None:
            t0 = time.perf_counter()
            info = make_city(path, size_mb)
            print(f"generated {path.stat().st_size / 1e6:.1f} MB ({info['copies']} copies, "
                  f"{info['buildings']} buildings, {info['polygons']} polygons) in "
                  f"{time.perf_counter() - t0:.1f} s: {path}")
        file_mb = path.stat().st_size / 1e6
        parse = run_child(path, "parse")
        full = run_child(path, "full")
        peak_parse = (parse["peak_rss_kb"] - parse["base_rss_kb"]) / 1024
        peak = (full["peak_rss_kb"] - full["base_rss_kb"]) / 1024
        store_mb = full["store_bytes"] / 2**20
        store_py_mb = full["store_py_bytes"] / 2**20
        print(f"file_mb {file_mb:.1f}")
        print(f"buildings {full['buildings']} faces {full['faces']} vertices {full['vertices']}")
        print(f"parse_s {parse['seconds']:.2f}")
        print(f"parse_mb_per_s {file_mb / parse['seconds']:.1f}")
        print(f"parse_mb_per_cpu_s {file_mb / parse['cpu_seconds']:.1f}")
        print(f"parse_peak_rss_mb {peak_parse:.1f}")
        print(f"read_s {full['seconds']:.2f}")
        print(f"read_mb_per_s {file_mb / full['seconds']:.1f}")
        print(f"read_mb_per_cpu_s {file_mb / full['cpu_seconds']:.1f}")
        print(f"peak_rss_mb {peak:.1f}")
        print(f"store_mb {store_mb:.1f}")
        print(f"store_py_mb {store_py_mb:.1f}")
        columns_mb = full.get("store_column_bytes", 0) / 2**20
        print(f"store_string_columns_mb {columns_mb:.1f} (semantic/building/part codes, gml:id "
              f"bytes + offsets; included in store_mb)")
        print(f"peak_over_store {peak / store_mb:.2f}")
        print(f"peak_over_store_py {peak / store_py_mb:.2f}")
        print(f"peak_over_store_without_string_columns {peak / (store_mb - columns_mb):.2f}")
        print(f"parse_peak_over_store {peak_parse / store_mb:.2f}")
        print(f"parse_peak_over_store_py {peak_parse / store_py_mb:.2f}")
        print(f"load_average {os.getloadavg()[0]:.1f} (2 cores: wall-clock rates suffer above ~2)")
        # the reader targets, full path (read_city_model = parse + build_store); the store size of
        # the target is store_mb (numpy array bytes, the stricter definition); *_py includes the
        # Python objects (lists, id strings) the store keeps
        rate = file_mb / full["seconds"]
        print(f"target read_mb_per_s >= 20: {rate:.1f} {'MET' if rate >= 20 else 'NOT MET'}"
              f" (per CPU second {file_mb / full['cpu_seconds']:.1f})")
        print(f"target peak_over_store < 2: {peak / store_mb:.2f} "
              f"{'MET' if peak / store_mb < 2 else 'NOT MET'} (store_py: {peak / store_py_mb:.2f})")
        if not full["peak_reset"]:
            print("note: peak RSS could not be reset; peak includes the warm-up")
    finally:
        if tmp is None:
            pass
        elif args.keep:
            print(f"kept {path}")
        else:
            path.unlink(missing_ok=True)
            tmp.rmdir()


if __name__ == "__main__":
    main()
