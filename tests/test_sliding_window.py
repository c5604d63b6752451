"""The sliding-window workflow on a synthetic street sequence with known truth.

The street is 40 stations (120 images) long; GNSS (biased by about 2 m) only for the first 60
images, as in a flight that loses GNSS between buildings. Windows of 45 images move on by 15:
the window must move along the whole sequence, every window after the first must be held by
the images kept from the one before, and the block must end on the truth after the windows
alone and after the final global adjustment.
"""

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.sliding_window import (
    capture_order,
    held_stations,
    moved_pose,
    natural_key,
    similarity_between,
    sliding_window,
    window_reconstruction,
    window_starts,
)
from colmap_citymodel.adjust.steps import step2_bundle_adjustment
from colmap_citymodel.align.block_to_model import crop_to_reconstruction, georegister
from colmap_citymodel.align.coarse import SurfaceDistance
from colmap_citymodel.errors import InputError
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, centre_errors, make_street_scene
from colmap_citymodel.workflow import refine

NUM_GNSS = 60


def rms(values):
    return float(np.sqrt(np.mean(np.square(values))))


@pytest.fixture(scope="module")
def sequence():
    scene = make_street_scene(StreetSceneOptions(num_stations=40, seed=3))
    gnss = scene.gnss()
    first = type(gnss)(gnss.image_names[:NUM_GNSS], gnss.positions[:NUM_GNSS],
                       gnss.sigmas[:NUM_GNSS], gnss.crs, "synthetic")
    return scene, first


def window_options(mode="sliding_window"):
    options = RefineOptions()
    options.precision.covariances = "off"
    options.workflow.mode = mode
    options.workflow.window_size = 45
    options.workflow.window_new = 15
    return options


def test_window_starts_cover_the_sequence_with_full_windows():
    assert window_starts(50, 100, 33) == [0]
    starts = window_starts(340, 100, 33)
    assert starts[:3] == [0, 33, 66] and starts[-1] == 240
    assert all(b - a <= 33 for a, b in zip(starts, starts[1:]))


def test_capture_order_is_the_natural_name_order():
    assert sorted(["img10.jpg", "img9.jpg", "img100.jpg"], key=natural_key) == \
        ["img9.jpg", "img10.jpg", "img100.jpg"]


def test_similarity_between_poses_is_recovered_and_moves_poses_like_the_block(sequence):
    scene, _ = sequence
    rec = pycolmap.Reconstruction(scene.truth)
    order = capture_order(rec)[:20]
    before = [pycolmap.Rigid3d(np.asarray(rec.frame(f).rig_from_world.matrix())) for f in order]
    sim3 = pycolmap.Sim3d(1.3, pycolmap.Rotation3d(np.array([0.1, -0.2, 0.3])), [5.0, -2.0, 1.0])
    rec.transform(sim3)
    after = [rec.frame(f).rig_from_world for f in order]
    found = similarity_between(before, after)
    np.testing.assert_allclose(np.asarray(found.matrix()), np.asarray(sim3.matrix()), atol=1e-9)
    for pose, moved in zip(before, after):
        np.testing.assert_allclose(np.asarray(moved_pose(pose, sim3).matrix()),
                                   np.asarray(moved.matrix()), atol=1e-9)


def test_window_reconstruction_keeps_ids_and_cuts_tracks(sequence):
    scene, _ = sequence
    rec = scene.truth
    frames = capture_order(rec)[:30]
    sub = window_reconstruction(rec, frames)
    images = {d.id for f in frames for d in rec.frame(f).image_ids}
    assert set(sub.reg_image_ids()) == images
    assert sub.num_points3D() > 1000
    for point_id, point in list(sub.points3D.items())[:200]:
        np.testing.assert_allclose(point.xyz, rec.point3D(point_id).xyz)
        assert {e.image_id for e in point.track.elements} <= images
        assert point.track.length() >= 2


def test_held_images_span_distinct_stations(sequence):
    scene, _ = sequence
    rec = scene.truth
    kept = capture_order(rec)[15:45]
    held = held_stations(rec, kept, 3)
    centres = {tuple(np.round(rec.frame(f).rig_from_world.inverse().translation, 3))
               for f in held}
    assert len(centres) == 3 and len(held) == 9  # three stations of three cameras each
    assert held == kept[:9]


def test_bad_window_options_are_input_errors(sequence):
    scene, gnss = sequence
    options = window_options()
    options.workflow.window_new = 45
    with pytest.raises(InputError, match="window_new"):
        refine(scene.sfm, scene.store, gnss, options, progress=False)


@pytest.mark.slow
def test_windows_alone_move_along_the_sequence_onto_the_truth(sequence):
    scene, gnss = sequence
    rec = pycolmap.Reconstruction(scene.sfm)
    _, priors, _ = georegister(rec, scene.store, gnss, None)
    store = crop_to_reconstruction(scene.store, rec, 30.0)
    options = window_options()
    step2_bundle_adjustment(rec, priors, options)
    before = rms(centre_errors(rec, scene.truth))
    result = sliding_window(rec, store, priors, options,
                            SurfaceDistance(store, options.assignment.excluded_classes),
                            progress=False)
    windows = result.windows
    assert len(windows) == len(window_starts(120, 45, 15)) == 6
    assert windows[0].num_new == 45 and windows[0].num_held == 0
    assert all(w.num_new == 15 and w.num_held > 0 for w in windows[1:])
    assert windows[-1].num_gnss == 0  # the last windows have only the held poses and planes
    assert all(w.note is None and w.num_planes >= 10 for w in windows)
    after = rms(centre_errors(rec, scene.truth))
    assert before > 0.5  # GNSS alone, and only for the first half: metres off
    assert after < 0.03, (before, after)


@pytest.mark.slow
def test_refine_with_the_sliding_window_ends_with_the_global_adjustment(sequence):
    scene, gnss = sequence
    result = refine(scene.sfm, scene.store, gnss, window_options(), progress=False)
    windows = result.sliding_window
    assert windows is not None and windows["num_windows"] == 6
    assert windows["windows"][-1]["last_image"] == "s0039_R.jpg"
    # The final global adjustment ran over all images, with the model.
    assert result.iterations and result.iterations[-1].num_faces >= 20
    assert result.reconstruction.num_reg_images() == 120
    errors = centre_errors(result.reconstruction, scene.truth)
    assert len(errors) == 120 and rms(errors) < 0.03
    assert result.quality.verdict in ("ok", "weak")
    assert "sliding_window" in result.seconds


def test_cli_passes_the_workflow_on(monkeypatch):
    import types

    import colmap_citymodel.workflow as workflow
    from colmap_citymodel import cli

    seen = {}

    def fake_main(*args, **kwargs):
        seen.update(kwargs)
        return types.SimpleNamespace(quality=types.SimpleNamespace(verdict="ok"))

    monkeypatch.setattr(workflow, "main", fake_main)
    assert cli.main(["refine", "--input_path", "in", "--citymodel", "m.gml", "--output_path",
                     "out", "--workflow", "sliding_window"]) == 0
    assert seen["workflow"] == "sliding_window"


def test_an_unknown_workflow_is_an_input_error(tmp_path):
    from colmap_citymodel.workflow import main

    with pytest.raises(InputError, match="workflow.mode"):
        main(tmp_path / "in", tmp_path / "m.gml", tmp_path / "out", workflow="windowed")
    options = RefineOptions().mergedict({"workflow": {"mode": "sliding_window",
                                                      "window_size": 60, "window_new": 20}})
    assert (options.workflow.mode, options.workflow.window_size) == ("sliding_window", 60)


def test_pose_priors_of_three_stations_hold_the_datum(sequence):
    from colmap_citymodel.adjust.problem import HybridProblem, PosePriors

    scene, _ = sequence
    truth = scene.truth
    order = capture_order(truth)
    sub = window_reconstruction(truth, order[:18])
    held = held_stations(truth, order[:18], 3)
    priors = PosePriors(
        np.array([next(iter(truth.frame(f).image_ids)).id for f in held]),
        [pycolmap.Rigid3d(np.asarray(truth.frame(f).rig_from_world.matrix())) for f in held],
        0.01, np.radians(0.01))
    sub.transform(pycolmap.Sim3d(1.02, pycolmap.Rotation3d(np.array([0.0, 0.0, 0.01])),
                                 [0.5, -0.3, 0.2]))
    problem = HybridProblem(sub, None, None, None, RefineOptions().adjustment,
                            robust_images=False, robust_planes=False, pose_priors=priors)
    assert not problem.gauge_fixed and problem.counts["pose"] == 9 * len(held)
    problem.solve()
    assert rms(centre_errors(sub, truth)) < 0.01
