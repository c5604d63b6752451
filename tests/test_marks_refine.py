"""refine with ground marks on the synthetic street (GNSS 4 m off, 5 control and 5 check marks
measured with 0.7 px noise): the block within 0.05 m, the check marks' RMS within 0.05 m and
equal to an independent triangulation from the refined cameras, marks, model and GNSS all in
the adjustment; without GNSS the marks place the block. Each refine takes 10-25 s."""

import json

import numpy as np
import pytest

from colmap_citymodel.block.marks import (GroundMark, GroundMarks, measurements_in,
                                          triangulate_mark)
from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.output.write import write_refined
from colmap_citymodel.simulate.synthetic import (StreetSceneOptions, centre_errors,
                                                 make_street_scene, street_marks)
from colmap_citymodel.workflow import refine

pytestmark = pytest.mark.slow


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


@pytest.fixture(scope="module")
def scene():
    # A GNSS bias of 4.0 m (3.0, -2.0, 1.7) plus the slowly varying part.
    return make_street_scene(StreetSceneOptions(seed=7, gnss_bias=(3.0, -2.0, 1.7)),
                             crs=user_crs("EPSG:25832"))


@pytest.fixture(scope="module")
def marks(scene):
    """Ten marks along the street from the truth, 0.7 px noise: odd ones control, even ones
    check."""
    found = [GroundMark(name, xyz, np.array([0.02, 0.02, 0.03]), obs)
             for name, xyz, obs in street_marks(scene, 10, 0.7, seed=1, min_views=8)]
    return (GroundMarks(found[0::2], scene.store.crs, "EPSG:25832"),
            GroundMarks(found[1::2], scene.store.crs, "EPSG:25832"))


@pytest.fixture(scope="module")
def refined(scene, marks):
    control, check = marks
    return refine(scene.sfm, scene.store, scene.gnss(), RefineOptions(), progress=False,
                  marks=control, check_marks=check)


@pytest.mark.ci
def test_control_and_check_marks_with_gnss_four_metres_off(scene, marks, refined):
    assert np.linalg.norm([3.0, -2.0, 1.7]) == pytest.approx(4.0, abs=0.02)
    assert rms(centre_errors(refined.reconstruction, scene.truth)) < 0.05
    accuracy = refined.checkpoints.accuracy
    assert accuracy["num_used"] == 5 and not accuracy["blunders"]
    assert accuracy["rmse_3d_m"] < 0.05
    assert accuracy["test"]["passed"] and accuracy["test"]["sigmas"] == "survey and cameras"
    assert refined.quality.verdict == "ok"
    # An independent triangulation from the refined cameras gives the same RMS.
    rec, origin = refined.reconstruction, scene.store.origin
    errors = []
    for mark in marks[1].marks:
        point = triangulate_mark(rec, measurements_in(rec, mark)[0])[0]
        errors.append(point + origin - mark.position)
    assert abs(np.linalg.norm(np.sqrt(np.mean(np.square(errors), axis=0)))
               - accuracy["rmse_3d_m"]) < 0.02
    # Every control mark in the adjustment, none named a blunder.
    assert refined.control_marks["num_used"] == 5 and not refined.control_marks["blunders"]


def test_marks_model_and_gnss_all_contribute(refined):
    count = refined.iterations[-1].final.count
    assert count["gcp"] > 0 and count["gnss"] > 0 and count["dTP"] > 0
    for name in ("E", "N", "U"):
        row = refined.observability[name]
        assert set(row["shares"]) == {"planes", "gnss", "gcp"}
        assert all(share > 0 for share in row["shares"].values())
        assert row["sigma"] < min(row["sigma_planes"], row["sigma_gcp"])


def test_the_report_holds_the_marks(refined, tmp_path):
    write_refined(refined, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    check = report["checkpoints"]
    for key in ("rmse_m", "rmse_3d_m", "rmse_h_m", "rmse_v_m", "asprs", "test", "marks"):
        assert key in check
    row = next(iter(check["marks"].values()))
    assert {"images", "error_enu_m", "survey_sigma_enu_m", "sigma_enu_m"} <= set(row)
    assert check["asprs"]["horizontal_accuracy_95_m"] == pytest.approx(
        1.7308 * check["asprs"]["rmse_h_m"])
    assert report["control_marks"]["num_used"] == 5
    assert report["quality"]["metrics"]["checkpoints"]["test"]["passed"]
    markdown = (tmp_path / "out" / "report.md").read_text()
    assert "## Control marks" in markdown and "### Check marks" in markdown
    page = (tmp_path / "out" / "report.html").read_text()
    assert "check marks (5)" in page and "control marks (5)" in page


def test_marks_alone_georeference_the_block(scene, marks):
    control, check = marks
    result = refine(scene.sfm, scene.store, None, RefineOptions(), progress=False,
                    marks=control, check_marks=check)
    assert rms(centre_errors(result.reconstruction, scene.truth)) < 0.05
    assert result.checkpoints.accuracy["rmse_3d_m"] < 0.05
    assert all("gnss" not in row["shares"] and row["shares"]["gcp"] > 0
               for row in result.observability.values())


def test_refine_and_evaluate_through_the_cli(scene, marks, tmp_path, capsys):
    """refine --gcp --checkpoints --output_frame local, then evaluate --checkpoints on its
    output: the same check marks' figures."""
    from colmap_citymodel.block.marks import write_gcp_list
    from colmap_citymodel.citymodel.write_citygml import raw_from_store, write_citygml
    from colmap_citymodel.cli import main as cli_main

    (tmp_path / "sparse").mkdir()
    scene.sfm.write_binary(str(tmp_path / "sparse"))
    write_citygml(tmp_path / "model.gml", raw_from_store(scene.store))
    (tmp_path / "gnss.txt").write_text("\n".join(
        f"{n} {x:.4f} {y:.4f} {z:.4f} 3 3 5"
        for n, (x, y, z) in zip(scene.gnss_names, scene.gnss_positions_crs)) + "\n")
    for name, group in (("gcp.txt", marks[0]), ("check.txt", marks[1])):
        write_gcp_list(tmp_path / name, "EPSG:25832",
                       [(m.position, image, x, y, m.name) for m in group.marks
                        for image, x, y in m.observations])
    out = tmp_path / "refined"
    assert cli_main(["refine", "--no_progress", "--input_path", str(tmp_path / "sparse"),
                     "--citymodel", str(tmp_path / "model.gml"), "--output_path", str(out),
                     "--gnss", str(tmp_path / "gnss.txt"), "--gnss_crs", "EPSG:25832",
                     "--gcp", str(tmp_path / "gcp.txt"), "--gcp_sigma", "0.02", "0.03",
                     "--checkpoints", str(tmp_path / "check.txt"),
                     "--output_frame", "local"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["control_marks"]["num_used"] == 5
    assert report["inputs"]["gcp"] == str(tmp_path / "gcp.txt")
    capsys.readouterr()
    assert cli_main(["evaluate", "--input_path", str(out), "--checkpoints",
                     str(tmp_path / "check.txt"), "--json"]) in (0, None)
    evaluated = json.loads(capsys.readouterr().out)["evaluated"]
    assert evaluated["frame"] == "local"
    # The covariances refine wrote (checkpoint_precision.json) give the same test.
    assert evaluated["test"]["sigmas"] == "survey and cameras"
    assert evaluated["rmse_3d_m"] == pytest.approx(report["checkpoints"]["rmse_3d_m"], abs=1e-6)
