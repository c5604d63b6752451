"""The simulated oblique block through import-eo, pairs, matching and known-pose triangulation,
checked against the simulation's truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.simulate.oblique import ObliqueOptions, simulate_matching, simulate_oblique_block
from data_paths import CITYGML

CITY = CITYGML / "berlin" / "3910_5819.gml"


def _origin(path: Path) -> np.ndarray:
    if path.suffix == ".json":
        return np.asarray(json.loads(path.read_text())["origin"], float)
    return np.array([float(v) for v in path.read_text().splitlines()[1].split()])


@pytest.mark.slow
def test_oblique_block_chain(tmp_path):
    ws = tmp_path / "ws"
    options = ObliqueOptions(citymodel=str(CITY), strips=2, strip_length=100.0, seed=3)
    stats = simulate_oblique_block(options, ws)
    assert stats["images"] == 30
    assert cli_main(["import-eo", "--database", str(ws / "database.db"), "--eo",
                     str(ws / "eo.txt"), "--rig", str(ws / "rig.json"), "--eo_crs",
                     "EPSG:25833", "--output_path", str(tmp_path / "eo")]) == 0
    eo = pycolmap.Reconstruction(str(tmp_path / "eo" / "sparse"))
    truth = pycolmap.Reconstruction(str(ws / "truth"))
    shift = _origin(tmp_path / "eo" / "origin.json") - _origin(ws / "truth" / "origin.txt")
    true_centres = {i.name: np.asarray(i.projection_center()) for i in truth.images.values()}
    errors = np.array([np.asarray(i.projection_center()) + shift - true_centres[i.name]
                       for i in eo.images.values()])
    # the EO noise (5/5/10 cm antenna, 0.005 deg attitude) and nothing else
    assert np.all(np.abs(errors) < 4 * np.array([0.05, 0.05, 0.10]) + 0.01)

    pairs = tmp_path / "pairs.txt"
    assert cli_main(["pairs", "--input_path", str(tmp_path / "eo" / "sparse"), "--citymodel",
                     str(CITY), "--output", str(pairs)]) == 0
    names = sorted(true_centres)
    exhaustive = tmp_path / "exhaustive.txt"
    exhaustive.write_text("".join(f"{a} {b}\n" for k, a in enumerate(names)
                                  for b in names[k + 1:]))
    images_with_points = {}
    for name, pair_file in (("footprint", pairs), ("exhaustive", exhaustive)):
        database = tmp_path / f"{name}.db"
        database.write_bytes((ws / "database.db").read_bytes())
        result = simulate_matching(ws, pair_file, database)
        assert result.verified_pairs > 0
        out = tmp_path / f"sparse_{name}"
        assert cli_main(["triangulate", "--database", str(database), "--input_path",
                         str(tmp_path / "eo" / "sparse"), "--output_path", str(out)]) == 0
        rec = pycolmap.Reconstruction(str(out))
        images_with_points[name] = sum(i.num_points3D >= 20 for i in rec.images.values())
        # poses held
        for image in rec.images.values():
            assert np.allclose(image.projection_center(),
                               eo.find_image_with_name(image.name).projection_center())
        # tie points near the true surface points they were simulated from
        obs = np.load(ws / "truth" / "observations.npz")
        key = {(int(i), int(k)): int(p) for p, i, k in zip(obs["point"], obs["image"],
                                                           obs["keypoint"])}
        err = np.array([np.asarray(p.xyz) + shift - obs["xyz"][key[(
            p.track.elements[0].image_id - 1, p.track.elements[0].point2D_idx)]]
            for p in rec.points3D.values()])
        assert np.all(np.median(np.abs(err), 0) < [0.12, 0.12, 0.3])
    assert len(pairs.read_text().splitlines()) * 2 <= len(exhaustive.read_text().splitlines())
    assert images_with_points["footprint"] == images_with_points["exhaustive"]
