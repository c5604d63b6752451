"""Footprints and footprint pairs: a nadir and a tilted camera over flat ground against the closed
form, a roof in the way, pairs along a strip, and the pairs command on an imported block."""

from __future__ import annotations

import json
import math

import numpy as np
import pycolmap
import pytest
from shapely import affinity
from shapely.geometry import Polygon, box

from colmap_citymodel.block.eo import FLIP, rotation_opk
from colmap_citymodel.block.footprints import FootprintOptions, GroundSurface, footprint, footprints, overlapping_pairs
from colmap_citymodel.cli import main as cli_main
from data_paths import CITYGML

F, W, H = 5000.0, 4000, 3000
BERLIN = CITYGML / "berlin" / "3920_5820.gml"


def _image(centre, omega=0.0, phi=0.0, kappa=0.0, name="a.jpg", camera_id=1):
    rotation = FLIP @ rotation_opk(omega, phi, kappa).T
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ np.asarray(centre, float))
    camera = pycolmap.Camera(model="PINHOLE", width=W, height=H, params=[F, F, W / 2, H / 2],
                             camera_id=camera_id)
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(camera)
    image = pycolmap.Image(name=name, camera_id=camera_id, image_id=1)
    rec.add_image_with_trivial_frame(image, pose)
    return rec.image(1), rec.camera(camera_id)


def _same(a: Polygon, b: Polygon) -> float:
    return a.symmetric_difference(b).area / b.area


def test_nadir_footprint_is_the_closed_form_rectangle():
    centre, ground, kappa = np.array([10.0, 20.0, 500.0]), 100.0, 30.0
    image, camera = _image(centre, kappa=kappa)
    got = footprint(image, camera, GroundSurface(ground))
    distance = centre[2] - ground
    half_x, half_y = distance * (W / 2) / F, distance * (H / 2) / F  # 160 m, 120 m
    expected = affinity.rotate(box(-half_x, -half_y, half_x, half_y), kappa, origin=(0, 0))
    expected = affinity.translate(expected, *centre[:2])
    assert got.area == pytest.approx(4 * half_x * half_y, rel=1e-6)
    assert _same(got, expected) < 1e-6


def test_tilted_footprint_near_and_far_edge():
    """omega = 45 deg: the camera looks north; near and far edges at d tan(45 -/+ alpha)."""
    centre, tilt = np.array([0.0, 0.0, 600.0]), 45.0
    image, camera = _image(centre, omega=tilt)
    got = footprint(image, camera, GroundSurface(0.0), FootprintOptions(border_points=8))
    alpha = math.degrees(math.atan((H / 2) / F))
    near = centre[2] * math.tan(math.radians(tilt - alpha))
    far = centre[2] * math.tan(math.radians(tilt + alpha))
    assert got.bounds[1] == pytest.approx(near, rel=1e-6)
    assert got.bounds[3] == pytest.approx(far, rel=1e-6)
    # the far corners: slant distance to the far edge times the half width over f
    slant = centre[2] / math.cos(math.radians(tilt + alpha))
    half_far = slant * math.cos(math.radians(alpha)) * (W / 2) / F
    assert got.bounds[2] == pytest.approx(half_far, rel=1e-6)


def test_a_roof_in_the_way_shrinks_the_footprint():
    roof = 300.0
    vertices = np.array([[-1e3, -1e3, roof], [1e3, -1e3, roof], [1e3, 1e3, roof],
                         [-1e3, 1e3, roof]])
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    image, camera = _image([0.0, 0.0, 500.0])
    got = footprint(image, camera, GroundSurface(0.0, vertices, triangles))
    half_x, half_y = 200.0 * (W / 2) / F, 200.0 * (H / 2) / F
    assert _same(got, box(-half_x, -half_y, half_x, half_y)) < 1e-5  # float32 rays


def test_pairs_along_a_strip():
    """Nadir footprints 320 m wide along x, 100 m apart: neighbours overlap 220/320 and 120/320
    of a footprint, the third one 20/320, below the 0.2 share."""
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=W, height=H,
                                                    params=[F, F, W / 2, H / 2], camera_id=1))
    n = 8
    for k in range(n):
        rotation = FLIP @ rotation_opk(0, 0, 0).T
        centre = np.array([100.0 * k, 0.0, 400.0])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centre)
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{k}.jpg", camera_id=1, image_id=k + 1), pose)
    plans = footprints(rec, GroundSurface(0.0))
    pairs = overlapping_pairs(plans, 0.2)
    assert len(pairs) == (n - 1) + (n - 2)
    shares = {(a, b): s for a, b, s in pairs}
    assert shares[("0.jpg", "1.jpg")] == pytest.approx(220 / 320, rel=1e-6)
    assert shares[("0.jpg", "2.jpg")] == pytest.approx(120 / 320, rel=1e-6)


def test_pairs_command_on_an_imported_block(tmp_path):
    """Two strips of five-head exposures over Berlin: the pairs command with the city model
    writes a pair list naming database images, far fewer than exhaustive."""
    heads = [("N", [0, 0, 0]), ("F", [45, 0, 0]), ("B", [-45, 0, 0]), ("L", [0, -45, 0]),
             ("R", [0, 45, 0])]
    camera = {"model": "PINHOLE", "width": W, "height": H, "params": [F, F, W / 2, H / 2]}
    rig = {"heads": [{"name": n, "image_name": f"{n}_{{exposure}}.jpg", "boresight": b,
                      "camera": camera} for n, b in heads]}
    (tmp_path / "rig.json").write_text(json.dumps(rig))
    lines = []
    for strip in range(2):
        for k in range(10):
            lines.append(f"s{strip}e{k} {392000 + 150 * k} {5820300 + 250 * strip} 600 0 0 0")
    (tmp_path / "eo.txt").write_text("\n".join(lines) + "\n")
    database = tmp_path / "database.db"
    pycolmap.Database.open(str(database)).close()
    assert cli_main(["import-eo", "--database", str(database), "--eo", str(tmp_path / "eo.txt"),
                     "--rig", str(tmp_path / "rig.json"), "--eo_crs", "EPSG:25833",
                     "--output_path", str(tmp_path / "eo")]) == 0
    out = tmp_path / "pairs.txt"
    assert cli_main(["pairs", "--input_path", str(tmp_path / "eo" / "sparse"), "--database",
                     str(database), "--citymodel", str(BERLIN), "--output", str(out)]) == 0
    pairs = [line.split() for line in out.read_text().splitlines()]
    names = {f"{n}_s{s}e{k}.jpg" for n, _ in heads for s in range(2) for k in range(10)}
    assert pairs and all(len(p) == 2 and p[0] in names and p[1] in names for p in pairs)
    assert len(pairs) * 3 <= 100 * 99 // 2
    # forward (north) and backward (south) images of one exposure look 1200 m apart: never a
    # pair; the east-looking L image and the west-looking R one 8 exposures (1200 m) further
    # on see the same ground
    pair_set = {tuple(sorted(p)) for p in pairs}
    assert ("B_s0e0.jpg", "F_s0e0.jpg") not in pair_set
    assert tuple(sorted(("L_s0e0.jpg", "R_s0e8.jpg"))) in pair_set
