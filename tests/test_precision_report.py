"""Precision after refine on the synthetic street, and the files written next to report.json."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest

from colmap_citymodel.errors import InputError
from colmap_citymodel.options import PrecisionOptions, RefineOptions
from colmap_citymodel.precision import PrecisionResult, wants_covariances
from colmap_citymodel.workflow import refine
from colmap_citymodel.synthetic_scene import StreetSceneOptions, make_street_scene
from colmap_citymodel.write_output import write_refined


@pytest.fixture(scope="module")
def scene():
    return make_street_scene(StreetSceneOptions(seed=7))


@pytest.fixture(scope="module")
def refined(scene):
    return refine(scene.sfm, scene.store, scene.gnss(), RefineOptions(), progress=False)


@pytest.fixture(scope="module")
def written(refined, tmp_path_factory):
    return write_refined(refined, tmp_path_factory.mktemp("precision") / "refined")


def _read_ply(path):
    raw = path.read_bytes()
    end = raw.index(b"end_header\n") + len(b"end_header\n")
    header = raw[:end].decode().splitlines()
    types = {"double": "<f8", "uchar": "u1", "float": "<f4"}
    fields = [(line.split()[2], types[line.split()[1]]) for line in header
              if line.startswith("property")]
    count = int(next(line for line in header if line.startswith("element vertex")).split()[2])
    return np.frombuffer(raw[end:], dtype=fields, count=count)


def test_variance_factors_per_group_after_refine(refined):
    p = refined.precision
    assert p is not None and p.has_covariances
    v = p.variance
    assert v.method == "hat_matrix"
    # Same s0 as refine's own last solve report (n - u from the trace of the hat matrix).
    assert v.sigma0_squared == pytest.approx(refined.iterations[-1].final.sigma0_squared,
                                             rel=1e-6)
    s0 = v.sigma0_by_group
    # Image noise 0.5 px against the stated 1 px.
    assert 0.45 < s0["image"] < 0.55
    # Tie points sit ~4 cm off the planes (relief) against the stated sigma_dTP = 0.2 m.
    assert 0.1 < s0["dTP"] < 0.35
    # The model vertices are exact: their groups take almost no redundancy and residual.
    assert v.redundancy_by_group["VT"] < 0.2 * v.count["VT"]
    # Stated sigmas are pessimistic here, so the global test must reject.
    assert not v.test.accepted and v.test.statistic < v.test.lower


def test_covariances_after_refine(refined, scene):
    p = refined.precision
    rec = refined.reconstruction
    assert len(p.image_ids) == rec.num_reg_images()
    assert len(p.point_ids) == rec.num_points3D()
    sigma = p.image_sigmas
    assert np.all((sigma[:, :3] > 1e-4) & (sigma[:, :3] < 0.1))  # millimetres to centimetres
    # Marginal point sigmas include the poses' uncertainty: never below the conditional ones.
    assert np.all(p.point_sigmas >= p.point_sigmas_conditional - 1e-9)
    assert np.median(p.point_sigmas) > np.median(p.point_sigmas_conditional)
    # Points seen by more images are better determined (Mulder 5.2).
    track = np.array([rec.point3D(int(i)).track.length() for i in p.point_ids])
    norm = np.linalg.norm(p.point_sigmas, axis=1)
    assert np.median(norm[track >= 8]) < np.median(norm[track <= 3])


def test_report_files(refined, written):
    report = json.loads((written / "report.json").read_text())
    assert report["sigma0"] == pytest.approx(refined.precision.variance.sigma0)
    assert set(report["sigma0_by_group"]) == {"image", "gnss", "dTP", "dVT", "VT"}
    test = report["global_test"]
    assert {"statistic", "redundancy", "p_value", "accepted"} <= set(test)
    assert test["accepted"] is False
    assert report["precision"]["covariances"] is True
    assert "A posteriori precision" in (written / "report.md").read_text()

    with open(written / "image_precision.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == refined.reconstruction.num_reg_images()
    first = rows[0]
    image_id = int(first["image_id"])
    centre = refined.reconstruction.image(image_id).projection_center() + refined.origin
    np.testing.assert_allclose([float(first[k]) for k in ("X0", "Y0", "Z0")], centre, atol=1e-3)
    k = int(np.flatnonzero(refined.precision.image_ids == image_id)[0])
    assert float(first["sigma_Z0_m"]) == pytest.approx(refined.precision.image_sigmas[k, 2],
                                                       abs=1e-5)

    points = _read_ply(written / "point_precision.ply")
    assert len(points) == refined.reconstruction.num_points3D()
    np.testing.assert_allclose(points["sigma_z"], refined.precision.point_sigmas[:, 2],
                               rtol=1e-6)
    assert np.all(points["sigma_x"] >= points["sigma_x_conditional"] - 1e-7)
    assert abs(points["x"].mean() - refined.origin[0]) < 200  # CRS coordinates

    page = (written / "report.html").read_text()
    assert page.startswith("<!DOCTYPE html>")
    assert page.count("src='data:image/png;base64,") == 3
    assert "Global test" in page
    plots = sorted((written / "plots").glob("*.png"))
    assert len(plots) == 3
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in plots)


def test_report_without_covariances(refined, tmp_path):
    quick = dataclasses.replace(refined, precision=PrecisionResult(
        variance=refined.precision.variance))
    out = write_refined(quick, tmp_path / "quick")
    report = json.loads((out / "report.json").read_text())
    assert report["global_test"]["accepted"] is False
    assert report["precision"]["covariances"] is False
    assert not (out / "image_precision.csv").exists()
    assert not (out / "point_precision.ply").exists()
    assert "Covariances were not computed" in (out / "report.md").read_text()
    assert (out / "report.html").read_text().count("data:image/png") == 1  # plane histograms


def test_covariance_switch(tmp_path):
    limit = PrecisionOptions().max_images_auto
    assert wants_covariances(PrecisionOptions(), limit - 1)
    assert not wants_covariances(PrecisionOptions(), limit)
    assert wants_covariances(PrecisionOptions(covariances="on"), 10_000)
    assert not wants_covariances(PrecisionOptions(covariances="off"), 3)
    with pytest.raises(InputError, match="on, off or auto"):
        wants_covariances(PrecisionOptions(covariances="maybe"), 3)
    toml = tmp_path / "options.toml"
    toml.write_text('[precision]\ncovariances = "off"\nmax_images_auto = 100\n')
    options = RefineOptions.from_toml(toml)
    assert options.precision.covariances == "off" and options.precision.max_images_auto == 100
