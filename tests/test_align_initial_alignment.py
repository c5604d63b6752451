"""The similarity that moves a block's tie points onto their assigned planes."""

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.align.initial_alignment import similarity_to_planes


def _box_scene(rng):
    """Points on six faces of a 40 x 20 x 15 m box: every direction constrained."""
    normals = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1.0]])
    half = np.array([20.0, 10.0, 7.5])
    offsets = -np.abs(normals @ half)
    points, faces = [], []
    for f, n in enumerate(normals):
        p = rng.uniform(-half, half, size=(200, 3))
        axis = int(np.argmax(np.abs(n)))
        p[:, axis] = n[axis] * half[axis]
        points.append(p)
        faces.append(np.full(200, f))
    return np.vstack(points), normals, offsets, np.concatenate(faces)


def _apply(sim3: pycolmap.Sim3d, x: np.ndarray) -> np.ndarray:
    m = np.asarray(sim3.matrix())
    return x @ m[:, :3].T + m[:, 3]


def test_recovers_a_known_similarity_with_outliers():
    rng = np.random.default_rng(3)
    truth, normals, offsets, faces = _box_scene(rng)
    truth = truth + rng.normal(0, 0.02, truth.shape)
    offset_sim3 = pycolmap.Sim3d(1.01, pycolmap.Rotation3d(np.array([0.01, -0.02, 0.015])),
                                 np.array([1.5, -2.0, 0.7]))
    moved = _apply(offset_sim3, truth)
    outliers = rng.choice(len(moved), 60, replace=False)
    moved[outliers] += rng.normal(0, 3.0, (60, 3))  # wrong assignments, metres off
    result = similarity_to_planes(moved, normals[faces], offsets[faces], sigma_plane=0.2)
    recovered = _apply(result.sim3, moved)
    inliers = np.setdiff1d(np.arange(len(moved)), outliers)
    error = np.linalg.norm(recovered[inliers] - truth[inliers], axis=1)
    assert np.sqrt(np.mean(error ** 2)) < 0.03  # of a 1.5-2.7 m offset; Huber keeps some pull
    assert result.rms_after < 0.03 < result.rms_before


def test_gnss_fixes_what_parallel_planes_leave_free():
    """Only the two long walls (normal +-y): x, z and the rotation about y are the GNSS's."""
    rng = np.random.default_rng(4)
    points, normals, offsets, faces = _box_scene(rng)
    walls = np.isin(faces, [2, 3])
    antennas = rng.uniform([-20, -5, 10], [20, 5, 12], size=(30, 3))
    shift = np.array([0.8, -0.5, 0.3])
    result = similarity_to_planes(points[walls] + shift, normals[faces[walls]],
                                  offsets[faces[walls]], sigma_plane=0.2,
                                  antennas=antennas + shift, gnss=antennas,
                                  gnss_sigmas=np.full((30, 3), 0.05))
    assert _apply(result.sim3, antennas + shift) == pytest.approx(antennas, abs=0.01)


def test_without_gnss_an_unconstrained_direction_stays_put():
    rng = np.random.default_rng(5)
    points, normals, offsets, faces = _box_scene(rng)
    walls = np.isin(faces, [2, 3])
    shift = np.array([0.0, -0.5, 0.0])
    result = similarity_to_planes(points[walls] + shift, normals[faces[walls]],
                                  offsets[faces[walls]], sigma_plane=0.2)
    moved = _apply(result.sim3, points[walls] + shift)
    # y is recovered; x (along the walls) gets no spurious move from the damping.
    assert np.abs(moved[:, 1] - points[walls][:, 1]).max() < 1e-3
    assert np.abs(moved[:, 0] - points[walls][:, 0]).max() < 1e-3
