"""Check point evaluation: Helmert transform, RMS, triangulation, the evaluate CLI."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.errors import InputError
from colmap_citymodel.precision.checkpoints import evaluate_checkpoints, helmert_transform, main, read_checkpoint_observations, read_checkpoints, triangulate_checkpoints


def test_helmert_recovers_known_similarity_exactly():
    rng = np.random.default_rng(1)
    estimated = rng.uniform(-50, 50, size=(12, 3)) + [691_000.0, 5_336_000.0, 520.0]
    omega, phi, kappa = 0.02, -0.015, 0.05  # degrees
    rotation = Rotation.from_euler("XYZ", [omega, phi, kappa], degrees=True).as_matrix()
    scale = 1 + 150e-6
    shift = np.array([0.30, -0.12, 0.45])
    centre = estimated.mean(axis=0)
    known = centre + shift + scale * (estimated - centre) @ rotation.T
    result = helmert_transform(known, estimated)
    np.testing.assert_allclose(result.translation, shift, atol=1e-9)
    np.testing.assert_allclose(result.angles_deg, [omega, phi, kappa], atol=1e-9)
    assert result.scale_ppm == pytest.approx(150.0, abs=1e-6)
    np.testing.assert_allclose(result.centre, centre)
    assert result.rms_3d < 1e-8
    d = result.todict()
    assert d["tx"] == pytest.approx(0.30, abs=1e-9) and d["kappa_deg"] == pytest.approx(0.05)


def test_rms_on_hand_made_example():
    # Four check points; the estimate is the truth plus hand-chosen errors.
    known = {
        "1": np.array([0.0, 0.0, 0.0]),
        "2": np.array([2.0, 0.0, 0.0]),
        "3": np.array([0.0, 2.0, 0.0]),
        "4": np.array([0.0, 0.0, 2.0]),
    }
    errors = np.array([[0.1, 0.0, 0.0], [-0.1, 0.0, 0.2], [0.1, 0.0, -0.2], [-0.1, 0.0, 0.0]])
    ids = ["1", "2", "3", "4"]
    estimated = np.array([known[i] for i in ids]) - errors
    # RMS per axis by hand: X sqrt(4 * 0.01 / 4) = 0.1, Y 0, Z sqrt(2 * 0.04 / 4) = 0.1414
    rms_axes = np.sqrt(np.mean(errors**2, axis=0))
    np.testing.assert_allclose(rms_axes, [0.1, 0.0, np.sqrt(0.02)])
    rec, observations = _scene_with_checkpoints(dict(zip(ids, estimated)))
    evaluation = evaluate_checkpoints(rec, known, observations)
    np.testing.assert_allclose(evaluation.errors, errors, atol=1e-9)
    np.testing.assert_allclose(evaluation.rms_axes, [0.1, 0.0, np.sqrt(0.02)], atol=1e-9)
    assert evaluation.rms_3d == pytest.approx(np.sqrt(0.01 + 0.02), abs=1e-9)
    # A pure shift of the estimate is taken out entirely by the Helmert transform.
    shifted, obs2 = _scene_with_checkpoints({i: known[i] - [0.5, 0.2, -0.1] for i in ids})
    ev2 = evaluate_checkpoints(shifted, known, obs2)
    assert ev2.rms_3d == pytest.approx(np.linalg.norm([0.5, 0.2, 0.1]), abs=1e-9)
    assert ev2.rms_3d_after_helmert < 1e-8
    np.testing.assert_allclose(ev2.helmert.translation, [0.5, 0.2, -0.1], atol=1e-9)


def _synthetic(num_frames=6, seed=2, model=None):
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_frames_per_rig = num_frames
    options.num_points3D = 30
    if model is not None:
        options.camera_model_id = model[0]
        options.camera_params = model[1]
    pycolmap.set_random_seed(seed)
    return pycolmap.synthesize_dataset(options)


def _scene_with_checkpoints(points: dict, offset=np.zeros(3)):
    """A synthetic reconstruction (moved by `offset`) observing the given points exactly."""
    rec = _synthetic()
    if np.any(offset):
        rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), offset))
    observations = []
    for pid, xyz in points.items():
        for image in rec.images.values():
            xy = image.project_point(np.asarray(xyz, dtype=np.float64))  # None: behind
            if xy is not None:
                observations.append((image.name, pid, float(xy[0]), float(xy[1])))
    return rec, observations


def test_triangulation_recovers_synthetic_points_any_camera_model():
    for model in [None, (pycolmap.CameraModelId.OPENCV_FISHEYE,
                         [900.0, 910.0, 512.0, 384.0, 0.05, -0.02, 0.01, 0.0])]:
        rec = _synthetic(model=model)
        observations, truth = [], {}
        for point_id, point in rec.points3D.items():
            truth[str(point_id)] = point.xyz.copy()
            for element in point.track.elements:
                image = rec.image(element.image_id)
                xy = image.points2D[element.point2D_idx].xy
                observations.append((image.name, str(point_id), float(xy[0]), float(xy[1])))
        estimated = triangulate_checkpoints(rec, observations)
        assert set(estimated) == set(truth)
        worst = max(np.linalg.norm(estimated[k] - truth[k]) for k in truth)
        assert worst < 1e-6


def test_triangulation_in_crs_coordinates_keeps_precision():
    # The same exact scene moved to UTM-sized coordinates: no precision loss.
    offset = np.array([691_000.0, 5_336_000.0, 500.0])
    rec = _synthetic()
    truth = {str(pid): p.xyz + offset for pid, p in rec.points3D.items()}
    observations = []
    for point_id, point in rec.points3D.items():
        for element in point.track.elements:
            image = rec.image(element.image_id)
            xy = image.points2D[element.point2D_idx].xy
            observations.append((image.name, str(point_id), float(xy[0]), float(xy[1])))
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), offset))
    evaluation = evaluate_checkpoints(rec, truth, observations)
    assert evaluation.frame == "crs" and len(evaluation.ids) == len(truth)
    assert evaluation.rms_3d < 1e-6
    # The same model in the local frame (CRS minus origin) with the origin given.
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), -offset))
    local = evaluate_checkpoints(rec, truth, observations, origin=offset)
    assert local.frame == "local" and local.rms_3d < 1e-6


def test_too_few_views_and_unknown_images():
    rec = _synthetic()
    point_id, point = next(iter(rec.points3D.items()))
    element = point.track.elements[0]
    image = rec.image(element.image_id)
    xy = image.points2D[element.point2D_idx].xy
    observations = [(image.name, "single", float(xy[0]), float(xy[1])),
                    ("ghost.png", "single", 1.0, 2.0)]
    evaluation = evaluate_checkpoints(rec, {"single": point.xyz}, observations)
    assert evaluation.ids == [] and evaluation.missing == ["single"]
    assert np.isnan(evaluation.rms_3d) and evaluation.helmert is None


def _write_workspace(tmp_path, offset=np.array([691_000.0, 5_336_000.0, 500.0]), error=0.05):
    rec = _synthetic()
    rng = np.random.default_rng(3)
    lines_cp, lines_obs = [], []
    for point_id, point in list(rec.points3D.items())[:10]:
        # Known coordinates differ from the model's point by a known error.
        known = point.xyz + offset + rng.normal(0, error, 3)
        lines_cp.append(f"CP{point_id} {known[0]:.6f} {known[1]:.6f} {known[2]:.6f}")
        for element in point.track.elements:
            image = rec.image(element.image_id)
            xy = image.points2D[element.point2D_idx].xy
            lines_obs.append(f"{image.name} CP{point_id} {xy[0]:.9f} {xy[1]:.9f}")
    (tmp_path / "checkpoints.txt").write_text("# id X Y Z\n" + "\n".join(lines_cp) + "\n")
    (tmp_path / "obs.txt").write_text("\n".join(lines_obs) + "\n")
    truth = tmp_path / "truth"
    truth.mkdir()
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), offset))
    rec.write(str(truth))
    model = tmp_path / "sparse"
    model.mkdir()
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), [0.3, 0.0, 0.0]))  # a datum shift
    rec.write(str(model))
    return model


def test_main_and_cli_with_truth(tmp_path, capsys):
    model = _write_workspace(tmp_path)
    out = main(model, tmp_path / "checkpoints.txt", tmp_path / "obs.txt")
    ev, tr = out["evaluated"], out["truth"]
    assert ev["num_checkpoints"] == 10 and tr is not None
    assert tr["rms_3d"] < 0.15  # only the 5 cm per axis known-coordinate noise
    assert abs(ev["helmert"]["tx"] + 0.3) < 0.1  # the 0.3 m shift shows up as a datum error
    assert ev["rms_x"] > 0.2 and ev["rms_3d_after_helmert"] < 0.15
    printed = capsys.readouterr().out
    assert "RMS X" in printed and "truth poses" in printed

    code = cli_main(["evaluate", "--input_path", str(model), "--checkpoints",
                     str(tmp_path / "checkpoints.txt"), "--observations",
                     str(tmp_path / "obs.txt"), "--json"])
    assert code == 0
    data = json.loads(capsys.readouterr().out)
    assert data["evaluated"]["rms_3d"] == pytest.approx(ev["rms_3d"])

    code = cli_main(["evaluate", "--input_path", str(tmp_path / "nope"), "--checkpoints",
                     str(tmp_path / "checkpoints.txt"), "--observations",
                     str(tmp_path / "obs.txt")])
    assert code == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.parametrize(
    "reader, content, match",
    [
        (read_checkpoints, "A 1 2\n", "line 1: expected 'id X Y Z'"),
        (read_checkpoints, "A 1 2 3\nA 1 2 3\n", "line 2: check point 'A' given twice"),
        (read_checkpoints, "A 1 2 z\n", "line 1: not a number"),
        (read_checkpoints, "# nothing\n", "no check points"),
        (read_checkpoint_observations, "img.jpg A 1\n", "line 1: expected 'image_name id x y'"),
        (read_checkpoint_observations, "img.jpg A 1 inf\n", "line 1: non-finite"),
    ],
)
def test_malformed_files(tmp_path, reader, content, match):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(InputError, match=match) as info:
        reader(path)
    assert "bad.txt" in str(info.value)


def test_delta_sigma_from_a_checkpoint_precision_file(tmp_path, capsys):
    # Two stochastic models for the same check points: sigma 0.01 m (over-optimistic for the
    # 0.3 m datum shift + 5 cm errors) and 0.25 m; evaluate divides its own Delta by them.
    model = _write_workspace(tmp_path)
    ids = [line.split()[0] for line in (tmp_path / "checkpoints.txt").read_text().splitlines()
           if line and not line.startswith("#")]
    n = 3 * len(ids)
    precision = tmp_path / "cp_precision.json"
    precision.write_text(json.dumps({
        "ids": ids, "covariance": {"classical": (np.eye(n) * 0.01 ** 2).tolist(),
                                   "generalisation_aware": (np.eye(n) * 0.25 ** 2).tolist()},
        "note": {"classical": "tiny", "generalisation_aware": "honest"}}))
    code = cli_main(["evaluate", "--input_path", str(model), "--checkpoints",
                     str(tmp_path / "checkpoints.txt"), "--observations",
                     str(tmp_path / "obs.txt"), "--checkpoint_precision", str(precision),
                     "--json"])
    assert code == 0
    out = json.loads(capsys.readouterr().out)["evaluated"]
    tables = out["delta_sigma_by_model"]
    x = tables["classical"]["before_helmert"]["X"]
    assert x["rms_sigma"] == pytest.approx(0.01)
    assert x["ratio"] == pytest.approx(out["rms_x"] / 0.01)
    assert x["ratio"] > 20  # the 0.3 m shift against 1 cm
    assert 0.5 < tables["generalisation_aware"]["before_helmert"]["X"]["ratio"] < 2
    # After the Helmert fit the shift is gone; the residual sigma is below sigma (7 of 30
    # degrees of freedom fitted).
    after = tables["classical"]["after_helmert"]["X"]
    assert after["rms_delta"] < 0.1 < x["rms_delta"]
    assert after["rms_sigma_residual"] < after["rms_sigma"]
    assert out["sigma_model"] == "generalisation_aware"
    assert out["points"][ids[0]]["sigma"] == pytest.approx([0.25] * 3)
    # A broken file is one clear input error.
    precision.write_text("{}")
    code = cli_main(["evaluate", "--input_path", str(model), "--checkpoints",
                     str(tmp_path / "checkpoints.txt"), "--observations",
                     str(tmp_path / "obs.txt"), "--checkpoint_precision", str(precision)])
    assert code == 2 and "check point precision file" in capsys.readouterr().err


def test_origin_text_file_with_comment_lines(tmp_path):
    """truth/origin.txt as simulate writes it: a comment header, the numbers, a CRS comment."""
    from colmap_citymodel.errors import InputError
    from colmap_citymodel.precision.checkpoints import _read_origin

    path = tmp_path / "origin.txt"
    path.write_text("# origin X Y Z: local = model CRS - origin\n691000.0 5336000.0 515.0\n"
                    "# crs: EPSG:25832\n")
    origin, frame = _read_origin(path)
    np.testing.assert_array_equal(origin, [691000.0, 5336000.0, 515.0])
    assert frame is None
    path.write_text("# nothing here\n1 2\n")
    with pytest.raises(InputError, match="three numbers"):
        _read_origin(path)
