"""Control marks in COLMAP's bundle adjuster (group "gcp"): marks alone georeference a block,
a mark 2 m off is named and left out, and the datum's observability names the marks."""

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.marks import (control_marks, datum_observations,
                                           marks_in_adjustment, similarity_from_marks)
from colmap_citymodel.adjust.observability import observability
from colmap_citymodel.adjust.problem import HybridProblem
from colmap_citymodel.block.marks import GroundMark, GroundMarks
from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.simulate.synthetic import (StreetSceneOptions, centre_errors,
                                                 make_street_scene, street_marks)
from colmap_citymodel.workflow import adjust_without_model


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


@pytest.fixture(scope="module")
def scene():
    return make_street_scene(StreetSceneOptions(seed=5, num_stations=12),
                             crs=user_crs("EPSG:25832"))


def ground_marks(scene, count=6, off=None):
    """`count` marks from the truth with 0.7 px noise; `off`: (name, metres E N U) a mark whose
    surveyed coordinates are wrong by that much."""
    marks = []
    for name, xyz, obs in street_marks(scene, count, 0.7, seed=9, min_views=6):
        if off is not None and name == off[0]:
            xyz = xyz + np.asarray(off[1])
        marks.append(GroundMark(name, xyz, np.array([0.02, 0.02, 0.03]), obs))
    return GroundMarks(marks, scene.store.crs, "EPSG:25832")


def placed_by_marks(scene, marks):
    """The SfM block moved into the local frame by the marks' similarity (no GNSS)."""
    rec = pycolmap.Reconstruction(scene.sfm)
    sim = similarity_from_marks(marks, rec)
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), -scene.store.origin) * sim)
    return rec


def test_marks_alone_georeference_the_block(scene):
    marks = ground_marks(scene)
    rec = placed_by_marks(scene, marks)
    control = control_marks(marks, rec, scene.store.origin, 1.0)
    with marks_in_adjustment(control):
        problem = HybridProblem(rec, None, None, None, RefineOptions().adjustment,
                                robust_images=False, robust_planes=False)
        assert not problem.gauge_fixed  # the marks hold the datum
        report = problem.solve()
    assert report.count["gcp"] == 3 * len(marks) + 2 * sum(len(m.observations)
                                                           for m in marks.marks)
    assert report.rms["gcp"] < 1.5  # normalised by their sigmas
    assert rms(centre_errors(rec, scene.truth)) < 0.05
    # Outside the run the marks are in no problem.
    again = HybridProblem(rec, None, None, None, RefineOptions().adjustment,
                          robust_images=False, robust_planes=False)
    assert again.counts["gcp"] == 0 and again.gauge_fixed


def test_a_mark_in_one_image_is_in_the_adjustment(scene):
    name, xyz, obs = street_marks(scene, 1, 0.0, seed=3, min_views=6)[0]
    marks = GroundMarks([GroundMark(name, xyz, np.array([0.02, 0.02, 0.03]), obs[:1])],
                        scene.store.crs, "EPSG:25832")
    rec = pycolmap.Reconstruction(scene.truth)
    with marks_in_adjustment(control_marks(marks, rec, scene.store.origin, 1.0)):
        problem = HybridProblem(rec, None, None, None, RefineOptions().adjustment,
                                robust_images=False, robust_planes=False)
    # Its surveyed position and its one ray; one mark does not hold the datum.
    assert problem.counts["gcp"] == 3 + 2 and problem.gauge_fixed
    residuals = problem.group_residuals()["gcp"]
    assert np.all(np.abs(residuals) < 1e-6)  # the true point on its true ray


def test_the_datum_is_fixed_by_the_marks(scene):
    marks = ground_marks(scene)
    rec = placed_by_marks(scene, marks)
    control = control_marks(marks, rec, scene.store.origin, 1.0)
    rows = observability(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0, np.int64), None, None,
                         0.2, 0.2, marks=datum_observations(control, rec))
    assert {row["source"] for row in rows.values()} == {"gcp"}
    assert rows["E"]["sigma"] < 0.05 and rows["U"]["sigma_gcp"] < 0.05
    assert rows["E"]["shares"] == {"gcp": 1.0}


def test_a_mark_two_metres_off_is_named_and_left_out(scene):
    options = RefineOptions()
    results = {}
    for case, off in (("clean", None), ("blunder", ("M3", (1.2, -1.6, 0.0)))):
        marks = ground_marks(scene, off=off)
        rec = placed_by_marks(scene, marks)
        control = control_marks(marks, rec, scene.store.origin, 1.0)
        with marks_in_adjustment(control):
            rec, *_ = adjust_without_model(rec, None, options)
        results[case] = (rms(centre_errors(rec, scene.truth)), dict(control.excluded),
                         dict(control.tests))
    error, excluded, tests = results["blunder"]
    assert list(excluded) == ["M3"]
    assert excluded["M3"].startswith("blunder")
    # Named with how far the block adjusted without it puts it from its coordinates.
    offset = np.asarray(tests["M3"]["offset_m"])
    np.testing.assert_allclose(-offset, (1.2, -1.6, 0.0), atol=0.05)
    assert tests["M3"]["without_it"]
    assert results["clean"][1] == {}
    assert error < 0.05
    assert error <= results["clean"][0] + 0.005  # no worse than without it
