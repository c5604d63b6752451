"""Seeded fuzzing of every file the CLI reads: damaged copies of real inputs, run through the CLI.

A case is (run seed, case index) -> one input kind, one real base file and 1-3 kinds of damage
(truncation, flipped bits, deleted or duplicated runs, numbers replaced by nan, inf, 1e308, ''
or '1.2.3', junk bytes, lines swapped; for binary files also overwritten counts and ids). The
damaged copy is written next to undamaged copies of the other inputs and the CLI's own entry,
`colmap_citymodel.cli.main(argv)`, runs in a worker process:

- city models (CityGML 1.0/2.0/3.0, CityJSON, CityJSONSeq): `model-info FILE`, and the
  synthetic street's model.gml also through `refine` (CRS from the file's head, GNSS box);
- GNSS text files, EXIF image directories, options TOML, transform files and COLMAP models
  (binary and text): `refine ...` with the other inputs intact; the adjustment itself is
  replaced by a stop once every input has been read (`inputs read`), since it costs seconds per
  case and is not what is fuzzed here;
- COLMAP models also through `evaluate ...`, run to the end.

A case passes when it ends with exit 0 (or `inputs read`) or with exit 2 and exactly one line
`error: ...` on stderr that names the damaged file (or its directory), and prints no Python
warning a user would see. Tracebacks, crashes of the worker and cases over the time limit
(hangs: the worker is killed and restarted) fail.

Reproduce one case: `python tests/fuzz_inputs.py --seed S --case I --keep DIR` writes the
damaged inputs to DIR and prints the command line.
"""

from __future__ import annotations

import argparse
import io
import json
import math
import multiprocessing
import os
import random
import re
import shutil
import struct
import sys
import tempfile
import time
import traceback
import warnings
from collections import Counter
from contextlib import nullcontext, redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from pathlib import Path

from data_paths import CITYGML, CITYJSON, LUND

CASE_TIMEOUT = 10.0  # seconds a case may take (worker side) before it counts as a hang

# ---------------------------------------------------------------------------------------------
# Damage


NUMBER = re.compile(rb"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")
NUMBER_SUBSTITUTES = (
    b"nan", b"NaN", b"-nan", b"inf", b"-inf", b"Infinity", b"-Infinity", b"1e308", b"-1e308",
    b"1e309", b"", b"1.2.3", b"0", b"-0", b"1e-320", b"99999999999999999999", b"0x1F", b"1,5",
    b"+", b"-", b"e5", b"1e", b" ", b"\xef\xbc\x91", b"4294967296", b"-1",
    b"18446744073709551615", b"1e8", b"-2147483649", b"9" * 400,
)
JUNK = (
    b"\x00", b"\xff\xfe", b"\xc3", b"<", b">", b"\"", b"{", b"}", b"[", b"]", b"#", b"&", b"\n",
    b"\r\n", b"\t", b"<!--", b"]]>", b"&amp;", b"&#0;", b"\xe2\x80\x8b", b",", b":", b"=",
    b"<x>", b"</gml:posList>", b"null", b"[[", b"\\", b"'",
)
SPECIAL_FIELDS = (
    struct.pack("<Q", 0), struct.pack("<Q", 1), struct.pack("<Q", 2**31),
    struct.pack("<Q", 2**63 - 1), struct.pack("<Q", 2**64 - 1), struct.pack("<Q", 10**9),
    struct.pack("<I", 2**32 - 1), struct.pack("<I", 0), struct.pack("<i", -1),
    struct.pack("<I", 7), struct.pack("<d", math.nan), struct.pack("<d", math.inf),
    struct.pack("<d", -math.inf), struct.pack("<d", 1e308), struct.pack("<d", -1e308),
    struct.pack("<d", 0.0), struct.pack("<d", 5e-324),
)


def _pos(rng: random.Random, data: bytes, region: int | None = None) -> int:
    n = len(data) if region is None else min(len(data), region)
    return rng.randrange(n + 1)


def _run_length(rng: random.Random, n: int) -> int:
    """Mostly short runs, sometimes long ones."""
    top = max(1, min(n, rng.choice((4, 16, 64, 512, 4096, n // 3 + 1))))
    return rng.randint(1, top)


def truncate(data: bytes, rng: random.Random, region=None) -> bytes:
    return data[:_pos(rng, data)]


def flip(data: bytes, rng: random.Random, region=None) -> bytes:
    if not data:
        return data
    b = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        i = min(_pos(rng, data, region), len(b) - 1)
        b[i] = b[i] ^ (1 << rng.randrange(8)) if rng.random() < 0.6 else rng.randrange(256)
    return bytes(b)


def delete_run(data: bytes, rng: random.Random, region=None) -> bytes:
    if not data:
        return data
    i = _pos(rng, data, region)
    return data[:i] + data[i + _run_length(rng, len(data)):]


def duplicate_run(data: bytes, rng: random.Random, region=None) -> bytes:
    if not data:
        return data
    i = _pos(rng, data, region)
    run = data[i:i + _run_length(rng, len(data))]
    j = _pos(rng, data, region)
    return data[:j] + run + data[j:]


def junk(data: bytes, rng: random.Random, region=None) -> bytes:
    i = _pos(rng, data, region)
    piece = rng.choice(JUNK) if rng.random() < 0.8 else bytes(
        rng.randrange(256) for _ in range(rng.randint(1, 32)))
    return data[:i] + piece + data[i:]


def replace_numbers(data: bytes, rng: random.Random, region=None) -> bytes:
    """One number, or several, or every number of one line, replaced by a bad one."""
    spans = [m.span() for m in NUMBER.finditer(data)]
    if not spans:
        return junk(data, rng, region)
    mode = rng.random()
    if mode < 0.6:
        chosen = [rng.choice(spans)]
    elif mode < 0.85:
        chosen = rng.sample(spans, min(len(spans), rng.randint(2, 20)))
    else:  # every number of one line
        a, _ = rng.choice(spans)
        start = data.rfind(b"\n", 0, a) + 1
        end = data.find(b"\n", a)
        end = len(data) if end < 0 else end
        chosen = [s for s in spans if start <= s[0] < end]
    value = rng.choice(NUMBER_SUBSTITUTES)
    out, last = [], 0
    for a, b in sorted(set(chosen)):
        out += [data[last:a], value if rng.random() < 0.8 else rng.choice(NUMBER_SUBSTITUTES)]
        last = b
    out.append(data[last:])
    return b"".join(out)


def shuffle_lines(data: bytes, rng: random.Random, region=None) -> bytes:
    lines = data.split(b"\n")
    if len(lines) < 2:
        return data
    i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
    op = rng.random()
    if op < 0.4:
        lines[i], lines[j] = lines[j], lines[i]
    elif op < 0.7:
        del lines[i]
    else:
        lines.insert(j, lines[i])
    return b"\n".join(lines)


def empty(data: bytes, rng: random.Random, region=None) -> bytes:
    return b"" if rng.random() < 0.7 else rng.choice((b"\n", b" ", b"\x00", b"{}", b"<a/>"))


def overwrite_field(data: bytes, rng: random.Random, region=None) -> bytes:
    """A binary field replaced by a count, id or double that is out of range or not finite."""
    if not data:
        return data
    value = rng.choice(SPECIAL_FIELDS)
    i = _pos(rng, data, region)
    if rng.random() < 0.5:
        i -= i % 4
    return data[:i] + value + data[i + len(value):]


def append_junk(data: bytes, rng: random.Random, region=None) -> bytes:
    return data + bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))


TEXT_DAMAGE = ((replace_numbers, 5), (truncate, 2), (flip, 2), (delete_run, 2),
               (duplicate_run, 2), (junk, 2), (shuffle_lines, 2), (empty, 0.3))
BINARY_DAMAGE = ((overwrite_field, 5), (truncate, 3), (flip, 3), (delete_run, 2),
                 (duplicate_run, 2), (append_junk, 1), (empty, 0.3))


def _pick(rng: random.Random, weighted):
    items, weights = zip(*weighted)
    return rng.choices(items, weights)[0]


def damage(data: bytes, rng: random.Random, binary: bool = False, region: int | None = None
           ) -> tuple[bytes, list[str]]:
    """`data` with 1-3 kinds of damage; returns (damaged bytes, names of the damage)."""
    table = BINARY_DAMAGE if binary else TEXT_DAMAGE
    names = []
    for _ in range(rng.choice((1, 1, 1, 2, 2, 3))):
        op = _pick(rng, table)
        data = op(data, rng, region)
        names.append(op.__name__)
    return data, names


# ---------------------------------------------------------------------------------------------
# Corpus: the undamaged inputs


@dataclass
class Corpus:
    root: Path
    citygml: list[tuple[Path, list[str]]]  # file, extra model-info arguments
    cityjson: list[tuple[Path, list[str]]]
    workspace: Path  # sparse/0 (bin), text/0 (txt), model.gml, gnss*.txt, options, transforms
    lund: Path  # a few EXIF images, odd-EXIF variants and a box model around them


# model-info arguments a base file needs to read cleanly (see tests/data/README.md)
EXTRA_ARGS = {
    "no_crs_house_part.gml": ["--crs", "EPSG:3946"],
    "53394517_bldg_6697_op_CityGML2.gml": ["--target_crs", "EPSG:6677"],
    "DH_01_subs.city.json": ["--crs", "EPSG:7415"],
    "rotterdam_subset.json": ["--crs", "EPSG:7415"],
}


def _cityjson_seq(source: Path, target: Path) -> None:
    """A CityJSONSeq file (header line + one CityJSONFeature per building) from a CityJSON file."""
    doc = json.loads(source.read_text())
    header = {k: v for k, v in doc.items() if k not in ("CityObjects", "vertices", "appearance")}
    objects, vertices = doc["CityObjects"], doc["vertices"]
    lines = [json.dumps(header)]
    for oid, obj in objects.items():
        if obj.get("parents"):
            continue
        members = [oid] + list(obj.get("children", []))
        used: dict[int, int] = {}

        def remap(b):
            if isinstance(b, list):
                return [remap(x) for x in b]
            return used.setdefault(b, len(used))

        feature_objects = {}
        for m in members:
            o = dict(objects[m])
            o["geometry"] = [dict(g, boundaries=remap(g["boundaries"])) for g in o.get("geometry", [])]
            feature_objects[m] = o
        verts = [vertices[i] for i in sorted(used, key=used.get)]
        lines.append(json.dumps({"type": "CityJSONFeature", "id": oid,
                                 "CityObjects": feature_objects, "vertices": verts}))
    target.write_text("\n".join(lines) + "\n")


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    return "[" + ", ".join(_toml_value(x) for x in v) + "]"


def _options_toml(options: dict) -> str:
    out = []
    for section, entries in options.items():
        out.append(f"[{section}]")
        out += [f"{k} = {_toml_value(v)}" for k, v in entries.items() if v is not None]
        out.append("")
    return "\n".join(out)


def _box_citygml(centre_xy, crs: str, n: int = 3) -> str:
    """A CityGML 2.0 model of n box buildings (walls and roof) east of `centre_xy`."""
    members = []
    for k in range(n):
        x0, y0 = centre_xy[0] + 30.0 * k - 30.0, centre_xy[1] - 10.0
        x1, y1, z0, z1 = x0 + 20.0, y0 + 15.0, 0.0, 25.0
        corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
        polys = []
        for i in range(4):
            (ax, ay), (bx, by) = corners[i], corners[(i + 1) % 4]
            ring = [(ax, ay, z0), (bx, by, z0), (bx, by, z1), (ax, ay, z1), (ax, ay, z0)]
            polys.append(("WallSurface", ring))
        polys.append(("RoofSurface", [(x, y, z1) for x, y in corners + corners[:1]]))
        surfaces = []
        for j, (cls, ring) in enumerate(polys):
            pos = " ".join(f"{c:.3f}" for p in ring for c in p)
            surfaces.append(
                f"<bldg:boundedBy><bldg:{cls}><bldg:lod2MultiSurface><gml:MultiSurface>"
                f"<gml:surfaceMember><gml:Polygon gml:id=\"b{k}_p{j}\"><gml:exterior><gml:LinearRing>"
                f"<gml:posList srsDimension=\"3\">{pos}</gml:posList></gml:LinearRing></gml:exterior>"
                f"</gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod2MultiSurface>"
                f"</bldg:{cls}></bldg:boundedBy>")
        members.append(f"<cityObjectMember><bldg:Building gml:id=\"b{k}\">{''.join(surfaces)}"
                       "</bldg:Building></cityObjectMember>")
    return (
        '<?xml version="1.0" encoding="UTF-8"?>\n'
        '<CityModel xmlns="http://www.opengis.net/citygml/2.0" '
        'xmlns:bldg="http://www.opengis.net/citygml/building/2.0" '
        'xmlns:gml="http://www.opengis.net/gml">\n'
        f'<gml:boundedBy><gml:Envelope srsName="{crs}" srsDimension="3">'
        f"<gml:lowerCorner>{centre_xy[0] - 100:.3f} {centre_xy[1] - 100:.3f} 0</gml:lowerCorner>"
        f"<gml:upperCorner>{centre_xy[0] + 100:.3f} {centre_xy[1] + 100:.3f} 30</gml:upperCorner>"
        "</gml:Envelope></gml:boundedBy>\n" + "\n".join(members) + "\n</CityModel>\n"
    )


ODD_EXIF = ("no_exif", "no_gps", "lat_out_of_range", "zero_denominator", "short_values",
            "no_altitude", "huge_altitude", "zero_position", "south_west", "bad_refs", "huge_dop")


def jpeg_with_size(data: bytes, width: int, height: int) -> bytes:
    """A JPEG whose frame header (SOF0/SOF2) states another image size."""
    i = max(data.find(b"\xff\xc0"), data.find(b"\xff\xc2"))
    if i < 0:
        return data
    return data[:i + 5] + struct.pack(">HH", height, width) + data[i + 9:]


def _odd_exif(source: Path, target: Path, variant: str) -> None:
    """A copy of a JPEG whose EXIF lacks GPS or holds odd GPS values."""
    from PIL import ExifTags, Image, TiffImagePlugin

    with Image.open(source) as image:
        exif = image.getexif()
        small = image.resize((160, 120))
    gps = exif.get_ifd(ExifTags.IFD.GPSInfo)
    R = TiffImagePlugin.IFDRational
    if variant == "no_exif":
        small.save(target, "JPEG", quality=80)
        return
    if variant == "no_gps":
        del exif[ExifTags.IFD.GPSInfo]
    elif variant == "lat_out_of_range":
        gps[2] = (R(95), R(0), R(0))
    elif variant == "zero_denominator":
        gps[2] = (R(1, 0), R(0, 0), R(0))
        gps[6] = R(5, 0)
    elif variant == "short_values":
        gps[2] = (R(55),)
        gps[4] = (R(13), R(11))
    elif variant == "huge_altitude":
        gps[6] = R(4 * 10**9)
    elif variant == "no_altitude":
        gps.pop(6, None)
    elif variant == "zero_position":
        gps[2] = (R(0), R(0), R(0))
        gps[4] = (R(0), R(0), R(0))
    elif variant == "south_west":
        gps[1], gps[3] = "S", "W"
    elif variant == "bad_refs":
        gps[1], gps[3], gps[5] = "?", "\x00", 7
    elif variant == "huge_dop":
        gps[11] = R(10**9)
    small.save(target, "JPEG", quality=80, exif=exif)


def build_workspace(ws: Path, num_stations: int = 8) -> Path:
    """A small synthetic street as a user has it, in `ws`: sparse/0 (COLMAP binary), text/0
    (the same model as text), model.gml (EPSG:25832), gnss.txt (EPSG:25832), gnss_wgs84.txt
    (EPSG:4979), options.toml (every option), transform.txt / .json / _matrix.json, and check
    points (checkpoints.txt, checkpoint_obs.txt) for `evaluate`. 8 stations (24 images) read
    fast but are too short a baseline for refine's georegistration; 16 run it through."""
    import pyproj

    from colmap_citymodel.citymodel.crs import user_crs
    from colmap_citymodel.citymodel.write_citygml import raw_from_store, write_citygml
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.simulate.synthetic import (
        StreetSceneOptions,
        make_street_scene,
    )

    (ws / "sparse" / "0").mkdir(parents=True, exist_ok=True)
    (ws / "text" / "0").mkdir(parents=True, exist_ok=True)
    scene = make_street_scene(StreetSceneOptions(seed=11, num_stations=num_stations, point_spacing=2.0),
                              crs=user_crs("EPSG:25832"))
    scene.sfm.write_binary(str(ws / "sparse" / "0"))
    scene.sfm.write_text(str(ws / "text" / "0"))
    write_citygml(ws / "model.gml", raw_from_store(scene.store))
    lines = ["# image_name X Y Z sX sY sZ"] + [
        f"{n} {x:.4f} {y:.4f} {z:.4f} 3 3 5"
        for n, (x, y, z) in zip(scene.gnss_names, scene.gnss_positions_crs)]
    (ws / "gnss.txt").write_text("\n".join(lines) + "\n")
    to_geo = pyproj.Transformer.from_crs("EPSG:25832", "EPSG:4979")
    lat, lon, h = to_geo.transform(*scene.gnss_positions_crs.T)
    (ws / "gnss_wgs84.txt").write_text("".join(
        f"{n} {a:.9f} {b:.9f} {c:.3f}\n" for n, a, b, c in zip(scene.gnss_names, lat, lon, h)))
    (ws / "options.toml").write_text(_options_toml(RefineOptions().todict()))
    centre = scene.gnss_positions_crs.mean(axis=0)
    c, s = math.cos(0.3), math.sin(0.3)
    matrix = [[1.1 * c, -1.1 * s, 0, centre[0]], [1.1 * s, 1.1 * c, 0, centre[1]],
              [0, 0, 1.1, centre[2]], [0, 0, 0, 1]]
    (ws / "transform.txt").write_text(
        "# input frame -> EPSG:25832\n" + "".join(" ".join(f"{v:.6f}" for v in row) + "\n"
                                                   for row in matrix))
    (ws / "transform.json").write_text(json.dumps(
        {"scale": 1.1, "rotation": [math.cos(0.15), 0.0, 0.0, math.sin(0.15)],
         "translation": list(map(float, centre))}))
    (ws / "transform_matrix.json").write_text(json.dumps({"matrix": matrix}))
    # check points: truth points of long tracks and their observations in the SfM images
    truth_ids = [pid for pid, p in sorted(scene.truth.points3D.items()) if p.track.length() >= 4][:6]
    cps, obs = [], []
    for pid in truth_ids:
        xyz = scene.truth.point3D(pid).xyz + scene.store.origin
        cps.append(f"cp{pid} {xyz[0]:.4f} {xyz[1]:.4f} {xyz[2]:.4f}")
        for el in scene.sfm.point3D(pid).track.elements:
            image = scene.sfm.image(el.image_id)
            x, y = image.points2D[el.point2D_idx].xy
            obs.append(f"{image.name} cp{pid} {x:.3f} {y:.3f}")
    (ws / "checkpoints.txt").write_text("\n".join(cps) + "\n")
    (ws / "checkpoint_obs.txt").write_text("\n".join(obs) + "\n")
    return ws


def build_corpus(root: Path, num_stations: int = 8) -> Corpus:
    """Write the undamaged inputs under `root`: the list of real city model files (and a
    CityJSONSeq made from one), the synthetic workspace (build_workspace) and a Lund EXIF
    directory (four real photos, odd-EXIF variants) with a box model around it."""
    import numpy as np
    import pyproj

    root.mkdir(parents=True, exist_ok=True)
    citygml = [(p, EXTRA_ARGS.get(p.name, []))
               for p in sorted(CITYGML.rglob("*.gml"))]
    cityjson = [(p, EXTRA_ARGS.get(p.name, []))
                for p in sorted(CITYJSON.glob("*.json"))]
    seq = root / "3dbag_b2.city.jsonl"
    _cityjson_seq(CITYJSON / "3dbag_b2.city.json", seq)
    cityjson.append((seq, []))
    ws = build_workspace(root / "workspace", num_stations)

    lund = root / "lund"
    (lund / "images").mkdir(parents=True, exist_ok=True)
    photos = sorted(LUND.glob("*.jpg"))[:4]
    for p in photos:
        shutil.copyfile(p, lund / "images" / p.name)
    (lund / "odd").mkdir(exist_ok=True)
    for variant in ODD_EXIF:
        _odd_exif(photos[0], lund / "odd" / f"{variant}.jpg", variant)
    to_sweref = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:3006", always_xy=True)
    cathedral = np.array(to_sweref.transform(13.1935, 55.6975))
    (lund / "boxes.gml").write_text(_box_citygml(cathedral, "EPSG:3006"))
    return Corpus(root, citygml, cityjson, ws, lund)


# ---------------------------------------------------------------------------------------------
# Cases


@dataclass
class Case:
    index: int
    kind: str
    argv: list[str]
    damaged: list[Path]  # the damaged files (or directories)
    names: list[str]  # strings a clean error message must contain one of
    description: str
    refine: bool = False  # argv is a refine: stops with "inputs read" before the adjustment
    directory: Path | None = None


KINDS = (("citygml", 27), ("cityjson", 12), ("citymodel_refine", 5), ("gnss", 10), ("exif", 7),
         ("options", 7), ("transform", 7), ("colmap_bin", 15), ("colmap_txt", 10))


def _link_tree(source: Path, target: Path) -> None:
    """Copy a directory tree as hard links (the readers only read)."""
    target.mkdir(parents=True, exist_ok=True)
    for p in source.iterdir():
        if p.is_dir():
            _link_tree(p, target / p.name)
        else:
            try:
                os.link(p, target / p.name)
            except OSError:
                shutil.copyfile(p, target / p.name)


def _write_damaged(source: Path, target: Path, rng: random.Random, binary=False, region=None):
    data, names = damage(source.read_bytes(), rng, binary=binary, region=region)
    if target.exists():
        target.unlink()  # may be a hard link to the undamaged file
    target.write_bytes(data)
    return names


def _refine_argv(corpus: Corpus, out: Path, **overrides) -> list[str]:
    ws = corpus.workspace
    args = {"--input_path": ws / "sparse" / "0", "--citymodel": ws / "model.gml",
            "--output_path": out, "--gnss": ws / "gnss.txt", "--gnss_crs": "EPSG:25832"}
    args.update(overrides)
    argv = ["refine", "--no_progress"]
    for key, value in args.items():
        if value is not None:
            argv += [key, str(value)]
    return argv


def make_case(corpus: Corpus, seed: int, index: int, workdir: Path, *, kind: str | None = None,
              undamaged: bool = False) -> Case:
    """Case `index` of the run `seed`: its damaged files are written under `workdir`."""
    rng = random.Random(f"{seed}:{index}")
    kind = kind or _pick(rng, KINDS)
    d = workdir / f"case_{index:05d}"
    if d.exists():
        shutil.rmtree(d)
    d.mkdir(parents=True)
    ws = corpus.workspace
    out = d / "out"

    def damaged_copy(source: Path, target: Path, binary=False, region=None) -> str:
        if undamaged:
            if source != target:
                shutil.copyfile(source, target)
            return "undamaged"
        return "+".join(_write_damaged(source, target, rng, binary, region))

    if kind in ("citygml", "cityjson"):
        base, extra = rng.choice(corpus.citygml if kind == "citygml" else corpus.cityjson)
        # keep the suffix (.gml, .json, .jsonl): the reader is chosen by it
        target = d / base.name
        how = damaged_copy(base, target)
        argv = ["model-info", str(target)] + extra
        return Case(index, kind, argv, [target], [str(target)], f"{base.name}: {how}", directory=d)
    if kind == "citymodel_refine":
        target = d / "model.gml"
        how = damaged_copy(ws / "model.gml", target)
        argv = _refine_argv(corpus, out, **{"--citymodel": target})
        return Case(index, kind, argv, [target], [str(target)], f"model.gml: {how}", True, d)
    if kind == "gnss":
        base, crs = rng.choice([(ws / "gnss.txt", "EPSG:25832"), (ws / "gnss_wgs84.txt", "EPSG:4979")])
        target = d / base.name
        how = damaged_copy(base, target)
        argv = _refine_argv(corpus, out, **{"--gnss": target, "--gnss_crs": crs})
        return Case(index, kind, argv, [target], [str(target)], f"{base.name}: {how}", True, d)
    if kind == "options":
        target = d / "options.toml"
        how = damaged_copy(ws / "options.toml", target)
        argv = _refine_argv(corpus, out, **{"--options": target})
        return Case(index, kind, argv, [target], [str(target)], f"options.toml: {how}", True, d)
    if kind == "transform":
        base = rng.choice([ws / "transform.txt", ws / "transform.json", ws / "transform_matrix.json"])
        target = d / base.name
        how = damaged_copy(base, target)
        argv = _refine_argv(corpus, out, **{"--initial_transform": target, "--gnss": None,
                                            "--gnss_crs": None})
        return Case(index, kind, argv, [target], [str(target)], f"{base.name}: {how}", True, d)
    if kind == "exif":
        images = d / "images"
        _link_tree(corpus.lund / "images", images)
        odd = sorted((corpus.lund / "odd").iterdir())
        for p in rng.sample(odd, rng.randint(0, 3)):
            shutil.copyfile(p, images / p.name)
        files = sorted(images.iterdir())
        hows = []
        if not undamaged:
            r = rng.random()
            if r < 0.04:  # no image at all
                for p in files:
                    p.unlink()
                (images / "notes.txt").write_text("no images here\n")
                hows.append("no images")
            elif r < 0.08:  # not a JPEG under a .jpg name
                (images / "fake.jpg").write_bytes(rng.choice((b"", b"GIF89a", b"\xff\xd8\xff")))
                hows.append("fake.jpg")
            elif r < 0.12:  # a frame header of a huge (or zero) image size
                p = rng.choice(files)
                size = rng.choice(((65000, 65000), (0, 0), (1, 65535)))
                data = p.read_bytes()
                p.unlink()  # a hard link to the corpus
                p.write_bytes(jpeg_with_size(data, *size))
                hows.append(f"{p.name}: {size[0]} x {size[1]} pixels")
            else:
                for p in rng.sample(files, rng.randint(1, 2)):
                    # most EXIF lives in the first few kilobytes
                    region = rng.choice((None, 2048, 16384))
                    hows.append(f"{p.name}: " + damaged_copy(p, p, binary=True, region=region))
        argv = _refine_argv(corpus, out, **{"--citymodel": corpus.lund / "boxes.gml",
                                            "--gnss": None, "--gnss_crs": None, "--exif": images})
        return Case(index, kind, argv, [images], [str(images)], "; ".join(hows) or "undamaged",
                    True, d)
    # COLMAP models
    binary = kind == "colmap_bin"
    ext = "bin" if binary else "txt"
    model = d / "model"
    _link_tree(ws / ("sparse" if binary else "text") / "0", model)
    names = ["cameras", "images", "points3D", "frames", "rigs"]
    name = rng.choices(names, (2, 3, 3, 2, 1))[0]
    target = model / f"{name}.{ext}"
    r = 1.0 if undamaged else rng.random()
    if r < 0.03:
        target.unlink()
        how = f"{target.name} deleted"
    elif r < 0.06:
        other = model / f"{rng.choice([n for n in names if n != name])}.{ext}"
        target.unlink()
        shutil.copyfile(other, target)
        how = f"{target.name} replaced by {other.name}"
    elif r < 0.08:
        other_ext = "txt" if binary else "bin"
        target.unlink()
        shutil.copyfile(ws / ("text" if binary else "sparse") / "0" / f"{name}.{other_ext}", target)
        how = f"{target.name} holds the .{other_ext} format"
    else:
        how = f"{target.name}: " + damaged_copy(target, target, binary=binary)
    evaluate = rng.random() < 0.4
    if evaluate:
        argv = ["evaluate", "--input_path", str(model), "--checkpoints", str(ws / "checkpoints.txt"),
                "--observations", str(ws / "checkpoint_obs.txt")]
    else:
        argv = _refine_argv(corpus, out, **{"--input_path": model})
    return Case(index, kind + ("_evaluate" if evaluate else ""), argv, [target], [str(model)], how,
                not evaluate, d)


# ---------------------------------------------------------------------------------------------
# Running: a worker process calls cli.main(argv); the parent enforces the time limit


class InputsRead(Exception):
    """Raised in place of the adjustment once `refine` has read every input."""


def _stop_before_adjustment(*args, **kwargs):
    raise InputsRead()


def _worker(conn) -> None:
    import logging
    import resource

    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    try:  # a damaged count must not make the worker eat the machine's memory
        limit = 6 << 30
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    except (ValueError, OSError):
        pass
    from colmap_citymodel import cli, workflow

    logging.getLogger("colmap_citymodel").setLevel(logging.CRITICAL)
    workflow.refine = _stop_before_adjustment
    conn.send("ready")
    while True:
        argv = conn.recv()
        if argv is None:
            break
        out, err = io.StringIO(), io.StringIO()
        status, tb = None, None
        start = time.perf_counter()
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            with redirect_stdout(out), redirect_stderr(err):
                try:
                    status = cli.main(argv)
                except InputsRead:
                    status = "inputs read"
                except SystemExit as error:
                    status = f"SystemExit {error.code}"
                except BaseException:  # noqa: BLE001 - everything else is what we look for
                    tb = traceback.format_exc()
        # warnings Python shows by default (not the deprecation and resource ones it hides)
        hidden = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)
        conn.send({"status": status, "stderr": err.getvalue(), "traceback": tb,
                   "seconds": time.perf_counter() - start,
                   "warnings": [f"{w.category.__name__}: {w.message}" for w in caught],
                   "shown_warnings": [f"{w.category.__name__}: {w.message}" for w in caught
                                      if not issubclass(w.category, hidden)]})


class Runner:
    """One worker process; restarted after a hang or a crash."""

    def __init__(self, timeout: float = CASE_TIMEOUT, target=None):
        self.timeout = timeout
        self.target = target or _worker
        self.ctx = multiprocessing.get_context("spawn")
        self.process = None
        self.restarts = 0

    def _start(self) -> None:
        self.conn, child = self.ctx.Pipe()
        self.process = self.ctx.Process(target=self.target, args=(child,), daemon=True)
        self.process.start()
        child.close()
        if not self.conn.poll(120):
            raise RuntimeError("fuzz worker did not start")
        self.conn.recv()

    def _stop(self) -> None:
        if self.process is not None:
            self.process.kill()
            self.process.join()
            self.conn.close()
            self.process = None

    def run(self, argv: list[str]) -> dict:
        if self.process is None:
            self._start()
        start = time.perf_counter()
        self.conn.send(argv)
        if self.conn.poll(self.timeout):
            try:
                return self.conn.recv()
            except EOFError:
                pass
            self.process.join(5)
            code = self.process.exitcode
            self._stop()
            self.restarts += 1
            return {"status": "crash", "exitcode": code, "seconds": time.perf_counter() - start}
        self._stop()
        self.restarts += 1
        return {"status": "hang", "seconds": time.perf_counter() - start}

    def close(self) -> None:
        if self.process is not None:
            try:
                self.conn.send(None)
                self.process.join(10)
            finally:
                self._stop()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _selftest_worker(conn) -> None:
    """A stand-in worker for testing the Runner: argv ["hang"] never answers, ["crash"] ends the
    process, anything else answers with exit status 0."""
    conn.send("ready")
    while True:
        argv = conn.recv()
        if argv is None:
            break
        if argv == ["hang"]:
            time.sleep(3600)
        if argv == ["crash"]:
            os._exit(7)
        conn.send({"status": 0, "stderr": "", "traceback": None, "seconds": 0.0})


def classify(case: Case, result: dict) -> tuple[str, str | None]:
    """(outcome, problem): outcome 'exit 0', 'inputs read', 'exit 2', 'traceback', 'hang',
    'crash', ...; problem None when the case ended cleanly, else what is wrong."""
    status = result["status"]
    if result.get("traceback"):
        last = result["traceback"].strip().splitlines()[-1]
        return "traceback", f"traceback: {last}"
    if status in ("hang", "crash"):
        extra = f" (exit code {result.get('exitcode')})" if status == "crash" else ""
        return status, f"{status}{extra} after {result['seconds']:.1f} s"
    outcome = status if status == "inputs read" else f"exit {status}"
    if status not in (0, 2, "inputs read"):
        return outcome, f"exit status {status}: {result['stderr'].strip()[:300]}"
    if result.get("shown_warnings"):
        return outcome, f"prints a Python warning: {result['shown_warnings'][0][:200]}"
    if status != 2:
        return outcome, None
    lines = result["stderr"].strip().splitlines()
    if len(lines) != 1 or not lines[0].startswith("error: "):
        return outcome, f"not one 'error:' line: {result['stderr'][:500]!r}"
    if not any(name in lines[0] for name in case.names):
        return outcome, f"the message does not name {case.names[0]}: {lines[0][:300]}"
    return outcome, None


@dataclass
class Report:
    seed: int
    cases: int = 0
    outcomes: Counter = field(default_factory=Counter)
    by_kind: dict = field(default_factory=dict)
    problems: list = field(default_factory=list)
    messages: Counter = field(default_factory=Counter)
    warnings: Counter = field(default_factory=Counter)
    seconds: float = 0.0
    slowest: list = field(default_factory=list)
    restarts: int = 0

    def summary(self) -> str:
        lines = [f"seed {self.seed}: {self.cases} cases in {self.seconds:.0f} s, "
                 f"{len(self.problems)} problems, {self.restarts} worker restarts",
                 "outcomes: " + ", ".join(f"{k} {v}" for k, v in self.outcomes.most_common())]
        for kind, counts in sorted(self.by_kind.items()):
            lines.append(f"  {kind}: " + ", ".join(f"{k} {v}" for k, v in counts.most_common()))
        lines.append("slowest: " + ", ".join(f"#{i} {k} {s:.2f} s" for s, i, k in self.slowest))
        if self.warnings:
            lines.append("python warnings: " + "; ".join(
                f"{k} ({v})" for k, v in self.warnings.most_common(8)))
        lines.append("most common messages: " + "; ".join(
            f"{k} ({v})" for k, v in self.messages.most_common(12)))
        for p in self.problems[:40]:
            lines.append(f"  PROBLEM case {p['case']} {p['kind']} [{p['damage']}]: {p['problem']}")
        return "\n".join(lines)


def _message_shape(stderr: str) -> str:
    """The error message with paths and numbers blanked, to count kinds of messages."""
    text = stderr.strip().splitlines()[0] if stderr.strip() else ""
    text = re.sub(r"/\S+", "<path>", text)
    text = re.sub(r"'[^']*'|\"[^\"]*\"", "<q>", text)
    return re.sub(r"[-+]?\d[\d.eE+-]*", "N", text)[:90]


def run_fuzz(corpus: Corpus, seed: int, count: int, workdir: Path, *, start: int = 0,
             timeout: float = CASE_TIMEOUT, keep_failures: Path | None = None,
             progress=None, runner: Runner | None = None) -> Report:
    """Run cases start..start+count-1 of `seed` (in `runner`, else a new one); damaged inputs of
    failing cases are kept under `keep_failures` (when given)."""
    report = Report(seed)
    t0 = time.perf_counter()
    slow = []
    restarts = runner.restarts if runner is not None else 0
    with (Runner(timeout) if runner is None else nullcontext(runner)) as runner:
        for index in range(start, start + count):
            case = make_case(corpus, seed, index, workdir)
            result = runner.run(case.argv)
            outcome, problem = classify(case, result)
            report.cases += 1
            report.outcomes[outcome] += 1
            report.by_kind.setdefault(case.kind, Counter())[outcome] += 1
            if outcome == "exit 2":
                report.messages[_message_shape(result["stderr"])] += 1
            for w in result.get("warnings", []):
                report.warnings[w[:120]] += 1
            slow.append((result["seconds"], index, case.kind))
            if problem:
                report.problems.append({"case": index, "kind": case.kind, "damage": case.description,
                                        "problem": problem, "argv": case.argv,
                                        "traceback": result.get("traceback")})
                if keep_failures is not None:
                    shutil.copytree(case.directory, keep_failures / case.directory.name,
                                    dirs_exist_ok=True)
            shutil.rmtree(case.directory, ignore_errors=True)
            if progress is not None and (index - start + 1) % 500 == 0:
                progress(f"{index - start + 1}/{count} cases, {len(report.problems)} problems, "
                         f"{time.perf_counter() - t0:.0f} s")
        report.restarts = runner.restarts - restarts
    report.seconds = time.perf_counter() - t0
    report.slowest = sorted(slow, reverse=True)[:5]
    return report


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description="run or reproduce fuzz cases")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--case", type=int, default=None, help="reproduce this one case")
    parser.add_argument("--count", type=int, default=200)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--keep", type=Path, default=None, help="directory for damaged inputs")
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="fuzz_") as tmp:
        tmp = Path(tmp)
        corpus = build_corpus((args.keep or tmp) / "corpus")
        if args.case is not None:
            case = make_case(corpus, args.seed, args.case, args.keep or tmp)
            print(f"{case.kind}: {case.description}")
            print("colmap-citymodel " + " ".join(case.argv))
            with Runner() as runner:
                result = runner.run(case.argv)
            print(classify(case, result))
            print(result.get("traceback") or result.get("stderr", ""))
            return 0
        report = run_fuzz(corpus, args.seed, args.count, tmp / "cases", start=args.start,
                          keep_failures=args.keep, progress=print)
        print(report.summary())
        return 1 if report.problems else 0


if __name__ == "__main__":
    sys.exit(main())
