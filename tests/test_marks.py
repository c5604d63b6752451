"""Ground marks: OpenDroneMap's gcp_list.txt read into the model's CRS, the marks' geometry in
a reconstruction, the C++ ray cost, and the check marks' accuracy statistics."""

import numpy as np
import pycolmap
import pyproj
import pytest

from colmap_citymodel._ext import load_core
from colmap_citymodel.adjust.marks import control_marks
from colmap_citymodel.block.marks import (PIXEL_CENTRE, header_crs, read_gcp_list,
                                          triangulate_mark, write_gcp_list)
from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.errors import CRSError, InputError
from colmap_citymodel.precision.accuracy import (HORIZONTAL_95, VERTICAL_95, asprs_figures,
                                                 check_accuracy)
from colmap_citymodel.precision.checkpoints import CheckpointEvaluation
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene, street_marks

UTM = user_crs("EPSG:25832")
A = (691000.123, 5335000.456, 512.25)
B = (691020.5, 5335010.0, 515.0)


def write(tmp_path, text, name="gcp_list.txt"):
    path = tmp_path / name
    path.write_text(text)
    return path


def test_epsg_header_marks_by_name_pixels_and_sigmas(tmp_path):
    path = write(tmp_path, "EPSG:25832\n"
                 f"{A[0]} {A[1]} {A[2]} 100 200 img1.jpg gcp1\n"
                 f"{A[0]} {A[1]} {A[2]} 110.5 210 img2.jpg gcp1\n"
                 f"# a comment\n\n"
                 f"{B[0]} {B[1]} {B[2]} 300 400 img1.jpg gcp2 0.05 0.08\n"
                 f"{B[0]} {B[1]} {B[2]} 500 400 img1.jpg gcp3 extra1 extra2\n")
    marks = read_gcp_list(path, UTM, (0.02, 0.03))
    assert marks.names == ["gcp1", "gcp2", "gcp3"]
    np.testing.assert_allclose(marks.marks[0].position, A, atol=1e-6)
    np.testing.assert_allclose(marks.marks[1].position, B, atol=1e-6)
    # OpenSfM's pixel centres are integers; COLMAP's are at +0.5.
    assert marks.marks[0].observations == [("img1.jpg", 100 + PIXEL_CENTRE, 200 + PIXEL_CENTRE),
                                           ("img2.jpg", 111.0, 210.5)]
    np.testing.assert_allclose(marks.marks[0].sigma, [0.02, 0.02, 0.03])
    np.testing.assert_allclose(marks.marks[1].sigma, [0.05, 0.05, 0.08])  # its own columns
    np.testing.assert_allclose(marks.marks[2].sigma, [0.02, 0.02, 0.03])  # extras ignored
    known, observations = marks.checkpoints()
    assert set(known) == {"gcp1", "gcp2", "gcp3"} and len(observations) == 4


def test_a_mark_without_a_height_holds_the_block_horizontally_only(tmp_path):
    from colmap_citymodel.block.marks import NO_HEIGHT_SIGMA

    path = write(tmp_path, "EPSG:25832\n"
                 f"{A[0]} {A[1]} NaN 100 200 img1.jpg flat\n"
                 f"{A[0]} {A[1]} nan 120 220 img2.jpg flat\n"
                 f"{B[0]} {B[1]} {B[2]} 300 400 img1.jpg full\n")
    marks = read_gcp_list(path, UTM)
    flat = marks.marks[0]
    assert not flat.has_height and flat.sigma[2] == NO_HEIGHT_SIGMA
    np.testing.assert_allclose(flat.position[:2], A[:2], atol=1e-6)
    assert list(marks.checkpoints()[0]) == ["full"]  # no check in 3D without a height


def test_marks_without_names_are_grouped_by_their_coordinates(tmp_path):
    path = write(tmp_path, "EPSG:25832\n"
                 f"{A[0]} {A[1]} {A[2]} 100 200 img1.jpg\n"
                 f"{B[0]} {B[1]} {B[2]} 300 400 img1.jpg\n"
                 f"{A[0]} {A[1]} {A[2]} 120 220 img2.jpg\n")
    marks = read_gcp_list(path, UTM)
    assert [len(m.observations) for m in marks.marks] == [2, 1]
    assert marks.names == ["unnamed-1", "unnamed-2"]


def test_a_proj_string_header_converts_like_its_epsg_code(tmp_path):
    line = f"{A[0]} {A[1]} {A[2]} 100 200 img1.jpg m1\n"
    proj = read_gcp_list(write(tmp_path, "+proj=utm +zone=32 +ellps=GRS80 +units=m +no_defs\n"
                               + line), UTM)
    np.testing.assert_allclose(proj.marks[0].position, A, atol=1e-3)
    # ODM's "WGS84 UTM 32N" names EPSG:32632.
    assert header_crs("WGS84 UTM 32N") == "EPSG:32632"
    assert header_crs("wgs84 utm 33s") == "EPSG:32733"
    utm = read_gcp_list(write(tmp_path, "WGS84 UTM 32N\n" + line, "b.txt"), UTM)
    np.testing.assert_allclose(utm.marks[0].position[:2], A[:2], atol=2.0)


def test_geographic_marks_come_into_the_model_crs_longitude_first(tmp_path):
    to_geo = pyproj.Transformer.from_crs("EPSG:25832", "EPSG:4326", always_xy=True)
    lon, lat = to_geo.transform(A[0], A[1])
    path = write(tmp_path, f"EPSG:4326\n{lon:.10f} {lat:.10f} {A[2]} 100 200 img1.jpg m1\n")
    marks = read_gcp_list(path, UTM)
    np.testing.assert_allclose(marks.marks[0].position, A, atol=1e-3)
    # EPSG:4326 names no height system: the heights are the model's, and a note says so.
    assert any("names no height system" in n for n in marks.notes)


@pytest.mark.parametrize("text, expected", [
    ("", "empty"),
    (f"{A[0]} {A[1]} {A[2]} 100 200 img1.jpg\n", "line 1 must name the CRS"),
    ("EPSG:25832\n", "no marks"),
    (f"EPSG:25832\n{A[0]} {A[1]} {A[2]} 100 img1.jpg\n", "line 2: expected"),
    (f"EPSG:25832\n{A[0]} x {A[2]} 100 200 img1.jpg\n", "line 2: not a number"),
    (f"EPSG:25832\n{A[0]} {A[1]} {A[2]} nan 200 img1.jpg\n", "not finite"),
    (f"EPSG:25832\n{A[0]} {A[1]} inf 100 200 img1.jpg\n", "not finite"),
    (f"EPSG:25832\n{A[0]} {A[1]} {A[2]} 1 2 i1.jpg m\n{B[0]} {B[1]} {B[2]} 1 2 i2.jpg m\n",
     "line 3: mark 'm' has other coordinates"),
    (f"EPSG:25832\n{A[0]} {A[1]} {A[2]} 1 2 i1.jpg m\n{A[0]} {A[1]} {A[2]} 3 4 i1.jpg m\n",
     "measured twice in image 'i1.jpg'"),
])
def test_bad_files_are_refused_naming_the_file_and_line(tmp_path, text, expected):
    path = write(tmp_path, text)
    with pytest.raises(InputError, match=expected) as error:
        read_gcp_list(path, UTM)
    assert error.value.path == path


def test_an_unknown_crs_is_a_crs_error(tmp_path):
    with pytest.raises(CRSError):
        read_gcp_list(write(tmp_path, f"EPSG:999999\n{A[0]} {A[1]} {A[2]} 1 2 i1.jpg m\n"),
                      UTM)


@pytest.fixture(scope="module")
def scene():
    return make_street_scene(StreetSceneOptions(seed=3, num_stations=10), crs=UTM)


def test_written_marks_read_back_exactly(scene, tmp_path):
    marks = street_marks(scene, 4, 0.7, seed=2)
    rows = [(xyz, image, x, y, name) for name, xyz, obs in marks for image, x, y in obs]
    write_gcp_list(tmp_path / "g.txt", "EPSG:25832", rows)
    read = read_gcp_list(tmp_path / "g.txt", scene.store.crs)
    for (name, xyz, obs), mark in zip(marks, read.marks):
        assert mark.name == name
        np.testing.assert_allclose(mark.position, xyz, atol=1e-4)
        np.testing.assert_allclose([o[1:] for o in mark.observations], [o[1:] for o in obs],
                                   atol=1e-3)


def test_missing_images_are_dropped_and_a_mark_in_one_image_is_kept(scene, tmp_path):
    name, xyz, obs = street_marks(scene, 1, 0.0, seed=2)[0]
    rows = [(xyz, obs[0][0], obs[0][1], obs[0][2], "one_image"),
            (xyz + 2.0, "not_in_block.jpg", 10.0, 10.0, "lost")]
    write_gcp_list(tmp_path / "g.txt", "EPSG:25832", rows)
    marks = read_gcp_list(tmp_path / "g.txt", scene.store.crs)
    control = control_marks(marks, scene.truth, scene.store.origin, 1.0)
    assert control.missing_images == {"lost": ["not_in_block.jpg"]}
    assert "no registered image" in control.excluded["lost"]
    assert [control.names[k] for k in control.used] == ["one_image"]
    # One image: in the adjustment (its ray through the point), but not triangulated.
    assert control.triangulated(scene.truth, control.used[0]) is None


def test_a_mark_is_triangulated_where_it_is_with_its_rays_covariance(scene):
    errors, sigmas = [], []
    for name, xyz, obs in street_marks(scene, 8, 0.5, seed=5, min_views=4):
        ids = {im.name: im.image_id for im in scene.truth.images.values()}
        found = triangulate_mark(scene.truth, [(ids[i], np.array([x, y])) for i, x, y in obs],
                                 0.5)
        point, covariance, rms = found
        errors.append(point + scene.store.origin - xyz)
        sigmas.append(np.sqrt(np.diag(covariance)))
        assert rms < 2.0
    errors, sigmas = np.array(errors), np.array(sigmas)
    # As large as the rays' sigmas say (0.5 px noise): normalised, about one on average.
    normalised = np.mean((errors / sigmas) ** 2)
    assert 0.2 < normalised < 3.0, normalised
    assert np.all(sigmas < 0.2)


def test_the_ray_cost_is_the_pixel_error_over_its_sigma():
    core = load_core()
    focal, sigma = 800.0, 0.5
    rotation = pycolmap.Rotation3d(np.array([0.1, -0.2, 0.3]))
    pose = pycolmap.Rigid3d(rotation, np.array([0.5, -1.0, 4.0]))
    point = np.array([1.0, 2.0, 10.0])
    cam = np.asarray(rotation.matrix()) @ point + np.array([0.5, -1.0, 4.0])
    measured = cam[:2] / cam[2] + np.array([0.002, -0.001])  # normalised plane
    cost = core.MarkRayCost(measured, focal, sigma)
    params = np.asarray(pose.params, float)
    residuals = np.asarray(cost.evaluate(point, params)[0]).reshape(-1)
    np.testing.assert_allclose(residuals, focal / sigma * (cam[:2] / cam[2] - measured),
                               rtol=1e-9)
    with pytest.raises(ValueError):
        core.MarkRayCost(measured, focal, 0.0)


def _evaluation(errors, covariance=None):
    names = [f"c{k}" for k in range(len(errors))]
    known = np.zeros((len(errors), 3))
    evaluation = CheckpointEvaluation(names, known, known + errors, -np.asarray(errors), None,
                                      {n: 3 for n in names}, [], "local")
    if covariance is not None:
        evaluation.attach_covariance(names, covariance)
    return evaluation


class _Marks:
    def __init__(self, names, sigma):
        from colmap_citymodel.block.marks import GroundMark

        self.marks = [GroundMark(n, np.zeros(3), np.asarray(sigma, float), [("i.jpg", 1, 2)])
                      for n in names]


def test_asprs_figures_follow_the_standard():
    errors = np.array([[0.03, -0.04, 0.05], [-0.03, 0.04, -0.05]])
    survey = np.tile([0.02, 0.02, 0.03], (2, 1))
    figures = asprs_figures(errors, survey)
    h1, v1 = 0.05, 0.05  # sqrt(0.03^2 + 0.04^2), 0.05
    h2, v2 = np.sqrt(2) * 0.02, 0.03
    assert figures["rmse_h1_m"] == pytest.approx(h1)
    assert figures["rmse_v1_m"] == pytest.approx(v1)
    assert figures["rmse_h_m"] == pytest.approx(np.hypot(h1, h2))
    assert figures["rmse_v_m"] == pytest.approx(np.hypot(v1, v2))
    assert figures["horizontal_accuracy_95_m"] == pytest.approx(HORIZONTAL_95 * np.hypot(h1, h2))
    assert figures["vertical_accuracy_95_m"] == pytest.approx(VERTICAL_95 * np.hypot(v1, v2))
    assert "at least 30" in figures["note"]


def test_check_statistics_test_the_block_and_name_a_blunder():
    rng = np.random.default_rng(4)
    sigma = np.array([0.02, 0.02, 0.03])
    cameras = 0.01 ** 2 * np.eye(18)
    errors = rng.normal(0.0, 1.0, (6, 3)) * np.sqrt(sigma ** 2 + 0.01 ** 2)
    marks = _Marks([f"c{k}" for k in range(6)] + ["seen_once"], sigma)
    sound = check_accuracy(_evaluation(errors, cameras), marks, 0.001)
    assert sound["test"]["passed"] and not sound["blunders"]
    # A mark the block could not triangulate (one image) is named, not counted.
    assert "fewer than two" in sound["not_triangulated"]["seen_once"]
    assert sound["num_used"] == 6
    assert sound["rmse_m"] == pytest.approx(np.sqrt(np.mean(errors ** 2, axis=0)).tolist())
    assert sound["rmse_3d_m"] == pytest.approx(np.sqrt(np.sum(np.mean(errors ** 2, axis=0))))
    # A mark 2 m off (its coordinates from another point) is named and left out.
    wrong = errors.copy()
    wrong[2] += [1.2, -1.6, 0.0]
    found = check_accuracy(_evaluation(wrong, cameras), marks, 0.001)
    assert list(found["blunders"]) == ["c2"] and found["num_used"] == 5
    assert not found["marks"]["c2"]["used"]
    assert found["test"]["passed"]
    assert found["rmse_3d_m"] < 0.1
    # A block off by 0.5 m as a whole: no mark stands out, the test fails.
    shifted = check_accuracy(_evaluation(errors + [0.5, 0.0, 0.0], cameras), marks, 0.001)
    assert not shifted["blunders"] and not shifted["test"]["passed"]


def test_evaluate_check_marks_on_a_model_in_another_frame(scene, tmp_path, capsys):
    """The true block written in the local frame (CRS minus origin, as refine --output_frame
    local writes it), its check marks (measured without noise) given in longitude/latitude:
    converted into the model's CRS, compared in its frame."""
    import json

    from colmap_citymodel.cli import main as cli_main

    model = tmp_path / "model"
    model.mkdir()
    scene.truth.write_binary(str(model))
    (model / "georeference.json").write_text(json.dumps({
        "crs": {"label": "EPSG:25832", "wkt": UTM.wkt}, "output_frame": "local",
        "origin": scene.store.origin.tolist()}))
    to_geo = pyproj.Transformer.from_crs("EPSG:25832", "EPSG:4326", always_xy=True)
    rows = []
    for name, xyz, obs in street_marks(scene, 5, 0.0, seed=4, min_views=5):
        lon, lat = to_geo.transform(xyz[0], xyz[1])
        rows += [((lon, lat, xyz[2]), image, x, y, name) for image, x, y in obs]
    lines = ["EPSG:4326"] + [f"{p[0]:.10f} {p[1]:.10f} {p[2]:.4f} {x - PIXEL_CENTRE:.3f} "
                             f"{y - PIXEL_CENTRE:.3f} {image} {name}"
                             for p, image, x, y, name in rows]
    (tmp_path / "check.txt").write_text("\n".join(lines) + "\n")
    code = cli_main(["evaluate", "--input_path", str(model), "--checkpoints",
                     str(tmp_path / "check.txt"), "--json", "--output_path",
                     str(tmp_path / "evaluation")])
    assert code in (0, None)
    out = json.loads(capsys.readouterr().out)["evaluated"]
    assert out["frame"] == "local" and out["num_checkpoints"] == 5
    # The true block, marks measured without noise: only the conversions could err.
    assert out["rmse_3d_m"] < 0.005
    assert out["asprs"]["num_checkpoints"] == 5 and out["test"]["sigmas"].startswith("survey and rays")
    assert out["test"]["passed"] and not out["blunders"]
    assert set(out["marks"]) == {f"M{k}" for k in range(1, 6)}
    assert (tmp_path / "evaluation" / "report.html").is_file()
    # Without a georeference, the model's CRS must be named.
    (model / "georeference.json").unlink()
    assert cli_main(["evaluate", "--input_path", str(model), "--checkpoints",
                     str(tmp_path / "check.txt")]) == 2
    assert "--crs" in capsys.readouterr().err


def test_the_verdict_takes_the_check_marks_test():
    from colmap_citymodel.precision.quality import QualityReport, checkpoint_verdict

    sigma = np.array([0.02, 0.02, 0.03])
    marks = _Marks([f"c{k}" for k in range(5)], sigma)
    errors = np.random.default_rng(1).normal(0.0, 0.02, (5, 3))
    cameras = 0.01 ** 2 * np.eye(15)
    passed = checkpoint_verdict(QualityReport("ok"), check_accuracy(
        _evaluation(errors, cameras), marks, 0.001))
    assert passed.verdict == "ok" and passed.metrics["checkpoints"]["test"]["passed"]
    failed = checkpoint_verdict(QualityReport("ok"), check_accuracy(
        _evaluation(errors + [0.0, 0.0, 0.4], cameras), marks, 0.001))
    assert failed.verdict == "weak"
    assert failed.reasons[0].startswith("check points: errors beyond their sigmas")
    # A failed block stays failed; no check marks, no change.
    assert checkpoint_verdict(QualityReport("failed"), check_accuracy(
        _evaluation(errors + [0.0, 0.0, 0.4], cameras), marks, 0.001)).verdict == "failed"
    assert checkpoint_verdict(QualityReport("ok"), None).metrics == {}
