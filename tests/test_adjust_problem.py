"""adjust.problem: our residual blocks act on the very parameter blocks of COLMAP's bundle
adjuster (pycolmap 4.2.1, pyceres 2.6; docs/ceres_blocks.md), and HybridProblem keeps them alive."""

from __future__ import annotations

import gc

import numpy as np
import pyceres
import pycolmap
import pytest

from colmap_citymodel import _ext
from colmap_citymodel.adjust.problem import HybridProblem
from colmap_citymodel.block.priors import GNSSPriors
from colmap_citymodel.block.reconstruction import position_in_rig
from colmap_citymodel.options import AdjustmentOptions

#: COLMAP 4's pose parameter block: Rigid3d.params, quaternion xyzw + translation.
POSE_BLOCK_SIZE = 7


@pytest.fixture(scope="module")
def core():
    return _ext.load_core()


def _scene(num_cameras_per_rig: int = 1, seed: int = 11) -> pycolmap.Reconstruction:
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_cameras_per_rig = num_cameras_per_rig
    options.num_frames_per_rig = 5
    options.num_points3D = 40
    pycolmap.set_random_seed(seed)
    return pycolmap.synthesize_dataset(options)


def _adjuster(reconstruction, gauge=pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD):
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in reconstruction.images:
        config.add_image(image_id)
    config.fix_gauge(gauge)
    options = pycolmap.BundleAdjustmentOptions()
    options.print_summary = False
    options.refine_focal_length = False
    options.refine_extra_params = False
    return pycolmap.create_default_ceres_bundle_adjuster(options, config, reconstruction)


def _address(array: np.ndarray) -> int:
    return array.__array_interface__["data"][0]


def test_point_xyz_is_the_problem_block_and_writes_through():
    reconstruction = _scene()
    problem = _adjuster(reconstruction).problem
    num_blocks = problem.num_parameter_blocks()
    for point_id in reconstruction.points3D:
        block = reconstruction.points3D[point_id].xyz
        # A view, not a copy: the same address on every access.
        assert _address(block) == _address(reconstruction.points3D[point_id].xyz)
        assert block.shape == (3,) and block.dtype == np.float64
        assert problem.has_parameter_block(block)
        assert not problem.is_parameter_block_constant(block)
        assert problem.parameter_block_size(block) == 3
    # A copy is not a block: a residual on a copy would be a new unknown.
    assert not problem.has_parameter_block(block.copy())
    block[:] = [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(reconstruction.points3D[point_id].xyz, [1.0, 2.0, 3.0])
    assert problem.num_parameter_blocks() == num_blocks


def test_frame_pose_is_one_block_and_the_gauge_fixes_two_frames():
    reconstruction = _scene()
    problem = _adjuster(reconstruction).problem
    tangent_sizes = []
    for frame_id, frame in reconstruction.frames.items():
        block = frame.rig_from_world.params
        assert _address(block) == _address(reconstruction.frames[frame_id].rig_from_world.params)
        assert block.shape == (POSE_BLOCK_SIZE,)
        assert problem.has_parameter_block(block)
        np.testing.assert_allclose(block[:4], frame.rig_from_world.rotation.quat)
        np.testing.assert_allclose(block[4:], frame.rig_from_world.translation)
        tangent_sizes.append(0 if problem.is_parameter_block_constant(block)
                             else problem.parameter_block_tangent_size(block))
    # TWO_CAMS_FROM_WORLD: one frame constant, one with 5 DOF (fixed baseline length), rest 6.
    assert sorted(tangent_sizes) == [0, 5, 6, 6, 6]
    block[4:] += 1.0  # writing the view moves the frame
    np.testing.assert_allclose(reconstruction.frames[frame_id].rig_from_world.translation,
                               block[4:])


def test_sensor_from_rig_of_a_non_reference_camera_is_a_block():
    reconstruction = _scene(num_cameras_per_rig=2)
    problem = _adjuster(reconstruction, pycolmap.BundleAdjustmentGauge.UNSPECIFIED).problem
    rig = next(iter(reconstruction.rigs.values()))
    sensors = list(rig.non_ref_sensors)
    assert len(sensors) == 1
    block = reconstruction.rigs[rig.rig_id].non_ref_sensors[sensors[0]].params
    assert problem.has_parameter_block(block)
    assert problem.parameter_block_tangent_size(block) == 6
    block[4] += 1.0
    np.testing.assert_allclose(rig.sensor_from_rig(sensors[0]).translation[0], block[4])


def test_position_in_rig_gives_projection_centres():
    reconstruction = _scene(num_cameras_per_rig=2)
    non_reference = 0
    for image in reconstruction.images.values():
        frame = reconstruction.frames[image.frame_id]
        offset = position_in_rig(reconstruction, image)
        non_reference += bool(np.any(offset != 0))
        centre = frame.rig_from_world.inverse() * offset
        np.testing.assert_allclose(centre, image.projection_center(), atol=1e-9)
    assert non_reference == 5


def test_hybrid_problem_keeps_its_costs_alive_and_gnss_pulls_a_shifted_block_back():
    """GNSS priors (the live HybridProblem's f_pos) pull a shifted block back to the truth; the
    costs survive dropping every other reference before the solve (pyceres keeps them only as
    long as the Python problem they were added through)."""
    reconstruction = _scene()
    ids = np.array(sorted(reconstruction.reg_image_ids()))
    truth = np.array([reconstruction.image(int(i)).projection_center() for i in ids])
    shift = np.array([0.5, -0.3, 0.2])
    reconstruction.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), shift))
    priors = GNSSPriors(ids, truth, np.full((len(ids), 3), 0.001))
    problem = HybridProblem(reconstruction, None, None, priors, AdjustmentOptions(),
                            robust_images=False, robust_planes=False)
    gc.collect()
    gnss = problem.group_residuals()["gnss"].reshape(-1, 3)
    np.testing.assert_allclose(np.abs(gnss), np.tile(np.abs(shift) / 0.001, (len(ids), 1)),
                               rtol=1e-6)
    problem.solve()
    centres = np.array([reconstruction.image(int(i)).projection_center() for i in ids])
    assert np.abs(centres - truth).max() < 1e-4


def test_plane_normals_live_on_a_wrapped_sphere_manifold():
    """The plane blocks of HybridProblem: normal on pyceres's SphereManifold (tangent size 2),
    set through set_manifold so that COLMAP's problem, which owns manifolds, does not free it
    a second time (that would abort the test process at the end)."""
    reconstruction = _scene()
    adjuster = _adjuster(reconstruction)
    problem = adjuster.problem
    normal = np.array([0.0, 0.0, 1.0])
    offset = np.array([-2.0])
    sphere = pyceres.SphereManifold(3)
    problem.add_parameter_block(normal, 3)
    problem.set_manifold(normal, sphere)
    problem.add_parameter_block(offset, 1)
    assert problem.parameter_block_tangent_size(normal) == 2
    assert problem.parameter_block_tangent_size(offset) == 1
    del problem, adjuster
    gc.collect()
