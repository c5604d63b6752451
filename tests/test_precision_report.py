"""Precision after refine on the synthetic street, and the files written next to report.json."""

from __future__ import annotations

import csv
import dataclasses
import json

import numpy as np
import pytest

from colmap_citymodel.errors import InputError
from colmap_citymodel.options import PrecisionOptions, RefineOptions
from colmap_citymodel.output.write import write_refined
from colmap_citymodel.precision.estimate import PrecisionResult, wants_covariances
from colmap_citymodel.workflow import refine


@pytest.fixture(scope="module")
def scene(street_scene):
    return street_scene


@pytest.fixture(scope="module")
def refined(street_refined):
    return street_refined


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
    # With the faces' offsets and tilts and GNSS's common bias as unknowns: their priors too.
    assert set(report["sigma0_by_group"]) == {"image", "gnss", "dTP", "dVT", "VT", "gen",
                                              "offset"}
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
    # The plane histograms (the 3D view's script may name PNG data URLs too).
    assert (out / "report.html").read_text().count("src='data:image/png;base64,") == 1


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


# -- check points through refine (Delta/sigma in report.json) ----------------------------

def _street_checkpoints(scene, num: int = 12, seed: int = 0):
    """Check points at true tie point positions (model CRS), observed anew with 1 px noise."""
    rng = np.random.default_rng(seed)
    truth = scene.truth
    ids = rng.choice([i for i in truth.point3D_ids() if truth.point3D(i).track.length() >= 5],
                     num, replace=False)
    known, observations = {}, []
    for k, point_id in enumerate(ids):
        xyz = truth.point3D(int(point_id)).xyz
        known[f"CP{k}"] = xyz + scene.store.origin
        for element in truth.point3D(int(point_id)).track.elements:
            image = truth.image(element.image_id)
            uv = np.asarray(image.camera.img_from_cam((image.cam_from_world() * xyz)[None]))
            uv = uv.reshape(2) + rng.normal(0.0, 1.0, 2)
            observations.append((image.name, f"CP{k}", float(uv[0]), float(uv[1])))
    return known, observations


@pytest.fixture(scope="module")
def refined_with_checkpoints(scene):
    known, observations = _street_checkpoints(scene)
    options = RefineOptions()
    # Every tie point alike: the classical sigmas beside the generalisation-aware ones.
    options.adjustment.face_weighting = "per_point"
    options.adjustment.sigma_generalisation = 0.2
    result = refine(scene.sfm, scene.store, scene.gnss(), options, progress=False,
                    checkpoints=known, checkpoint_observations=observations)
    return result, known, observations


def test_refine_reports_delta_and_sigma_of_checkpoints(refined_with_checkpoints, tmp_path):
    from colmap_citymodel.precision.checkpoints import main as evaluate_main

    result, known, observations = refined_with_checkpoints
    evaluation = result.checkpoints
    assert sorted(evaluation.ids) == sorted(known)
    # Check points are not added to the reconstruction (never tie points, never assigned).
    assert result.reconstruction.num_points3D() == len(result.assignment.point_ids)
    assert set(evaluation.covariances) == {"classical", "generalisation_aware"}
    classical, aware = (evaluation.sigmas_of(m) for m in ("classical", "generalisation_aware"))
    assert np.all(aware >= classical) and np.all(classical > 0)
    assert evaluation.rms_3d < 0.2

    out = write_refined(result, tmp_path / "refined")
    report = json.loads((out / "report.json").read_text())
    c = report["checkpoints"]
    assert c["num_checkpoints"] == len(known)
    for model in ("classical", "generalisation_aware"):
        table = c["delta_sigma_by_model"][model]
        for axis in "XYZ":
            for stage in ("before_helmert", "after_helmert"):
                row = table[stage][axis]
                assert row["ratio"] == pytest.approx(row["rms_delta"] / row["rms_sigma"])
    assert c["sigma_model"] == "generalisation_aware"
    assert report["precision"]["generalisation"]["mode"] == "consider"
    text = (out / "report.md").read_text()
    assert "## Check points" in text and text.count("Delta/sigma,") == 2
    with open(out / "checkpoint_precision.csv") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(known) and "sigma_Z_generalisation_aware_m" in rows[0]
    page = (out / "report.html").read_text()
    assert "check point errors" in page and "Delta| vs sigma" in page
    points = _read_ply(out / "point_precision.ply")
    assert np.all(points["sigma_z_aware"] >= points["sigma_z"] - 1e-7)

    # evaluate on the written model picks up the covariances (checkpoint_precision.json).
    cp_file, obs_file = tmp_path / "cp.txt", tmp_path / "obs.txt"
    cp_file.write_text("".join(f"{k} {x:.6f} {y:.6f} {z:.6f}\n"
                               for k, (x, y, z) in known.items()))
    obs_file.write_text("".join(f"{n} {k} {x:.6f} {y:.6f}\n" for n, k, x, y in observations))
    again = evaluate_main(out, cp_file, obs_file)["evaluated"]
    for model in ("classical", "generalisation_aware"):
        ours = c["delta_sigma_by_model"][model]["before_helmert"]
        theirs = again["delta_sigma_by_model"][model]["before_helmert"]
        for axis in "XYZ":
            assert theirs[axis]["rms_delta"] == pytest.approx(ours[axis]["rms_delta"], abs=1e-6)
            assert theirs[axis]["rms_sigma"] == pytest.approx(ours[axis]["rms_sigma"], rel=1e-9)



def test_refine_cli_checkpoint_options(tmp_path, capsys):
    from colmap_citymodel.cli import build_parser
    from colmap_citymodel.cli import main as cli_main

    args = build_parser().parse_args([
        "refine", "--input_path", "in", "--citymodel", "m.gml", "--output_path", "out",
        "--checkpoints", "cp.txt", "--checkpoint_observations", "obs.txt",
        "--sigma_generalisation", "0.2", "--variance_components"])
    assert (args.checkpoints, args.checkpoint_observations) == ("cp.txt", "obs.txt")
    assert args.sigma_generalisation == 0.2 and args.variance_components is True
    defaults = build_parser().parse_args(["refine", "--input_path", "in", "--citymodel", "m.gml",
                                          "--output_path", "out"])
    assert defaults.sigma_generalisation is None and defaults.variance_components is None
    # Observations without their check points are an input error, before any work
    # (--checkpoints alone is a gcp_list.txt of check marks).
    code = cli_main(["refine", "--input_path", str(tmp_path), "--citymodel", "m.gml",
                     "--output_path", str(tmp_path / "out"), "--checkpoint_observations",
                     "obs.txt"])
    assert code == 2
    assert "--checkpoint_observations needs --checkpoints" in capsys.readouterr().err


def test_refine_with_variance_components(scene):
    # Image noise 0.5 px against the stated 1 px; tie points ~3 cm (relief) plus 5 % clutter
    # off their planes against the stated 0.2 m: VCE must scale both down and re-solve.
    options = RefineOptions()
    options.precision.variance_components = True
    result = refine(scene.sfm, scene.store, scene.gnss(), options, progress=False)
    vce = result.variance_components
    assert vce is not None and vce.converged
    assert set(vce.history[0]) == {"image", "dTP"}
    assert vce.factors["image"] == pytest.approx(0.5, rel=0.1)
    assert 0.01 < vce.sigmas["dTP"] < 0.12
    assert vce.sigmas["gnss"] == pytest.approx(3.0)  # not estimated (time-correlated errors)
    # The result is the re-weighted solve: its s0 per estimated group is ~1 in units of the
    # estimated sigmas, and the covariances are scaled by that solve's s0^2.
    p = result.precision
    assert p.variance.sigma0_by_group["image"] == pytest.approx(vce.factors["image"], rel=0.05)
    assert p.variance.sigma0_by_group["dTP"] == pytest.approx(vce.factors["image"], rel=0.1)
    assert p.has_covariances
