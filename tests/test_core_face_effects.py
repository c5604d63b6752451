"""The tie point to face distance with the face's generalisation effects (offset and two
tilts) in the block's units: closed form, Jacobians against finite differences, and the
block's scale leaving the points' relief about their face unchanged."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_core_costs import evaluate, numeric_jacobians

from colmap_citymodel import _ext


@pytest.fixture(scope="module")
def core():
    return _ext.load_core()


def rig_from_world(centre: np.ndarray, rotation: Rotation) -> np.ndarray:
    """COLMAP's rig_from_world params [qx, qy, qz, qw, t] of a rig at `centre`."""
    return np.concatenate([rotation.as_quat(), -rotation.apply(centre)])


def test_face_effects_distance_closed_form_and_jacobians(core):
    rng = np.random.default_rng(3)
    for _ in range(5):
        point, reference = rng.normal(scale=20.0, size=(2, 3))
        normal = rng.normal(size=3)  # not unit: the cost divides by |n|
        offset = rng.normal(size=1)
        effects = rng.normal(scale=[0.2, 1.0, 1.0])
        axes = rng.normal(scale=0.01, size=(2, 3))
        centres = rng.normal(scale=50.0, size=(2, 3))
        frames = [rig_from_world(c, Rotation.random(random_state=rng)) for c in centres]
        length0 = 0.9 * np.linalg.norm(centres[0] - centres[1])
        sigma = rng.uniform(0.05, 0.5)
        cost = core.PointPlaneEffectsDistanceCost(sigma, reference, axes, length0, True)
        assert cost.parameter_block_sizes() == [3, 3, 1, 3, 7, 7]
        blocks = [point, normal, offset, effects, *frames]
        residuals, jacobians = evaluate(cost, *blocks)
        unit = normal / np.linalg.norm(normal)
        lever = point - reference
        distance = unit @ lever + offset[0] + effects[0] + effects[1:] @ (axes @ lever)
        scale = np.linalg.norm(centres[0] - centres[1]) / length0
        np.testing.assert_allclose(residuals, [distance / sigma / scale], rtol=1e-10)
        for analytic, numeric in zip(jacobians, numeric_jacobians(cost, blocks), strict=True):
            np.testing.assert_allclose(analytic, numeric, rtol=1e-5, atol=1e-6)
        # Unscaled, with the effects at zero: the plain point-plane distance.
        plain, _ = evaluate(core.PointPlaneDistanceCost(sigma, reference), point, normal,
                            offset)
        flat, _ = evaluate(core.PointPlaneEffectsDistanceCost(sigma, reference, axes, 1.0,
                                                              False),
                           point, normal, offset, np.zeros(3), *frames)
        np.testing.assert_allclose(flat, plain, rtol=1e-12)


def test_the_relief_does_not_shrink_with_the_block(core):
    """A point 0.3 m in front of its face, and the block (the point, the face's offset at its
    reference, the two frames) scaled about the reference: in metres its distance scales with
    the block; in the block's units it stays 0.3 m."""
    reference = np.array([5.0, 2.0, 1.0])
    normal = np.array([0.0, 1.0, 0.0])
    point = reference + [3.0, 0.3, 4.0]
    centres = np.array([[0.0, -30.0, 2.0], [60.0, -25.0, 3.0]])
    frames = [rig_from_world(c, Rotation.identity()) for c in centres]
    length0 = float(np.linalg.norm(centres[0] - centres[1]))
    cost = core.PointPlaneEffectsDistanceCost(0.1, reference, np.zeros((2, 3)), length0, True)
    for k in (0.97, 1.0, 1.04):
        moved = reference + k * (point - reference)
        scaled = [rig_from_world(reference + k * (c - reference), Rotation.identity())
                  for c in centres]
        residual, _ = evaluate(cost, moved, normal, np.zeros(1), np.zeros(3), *scaled)
        metres, _ = evaluate(core.PointPlaneDistanceCost(0.1, reference), moved, normal,
                             np.zeros(1))
        np.testing.assert_allclose(residual, [3.0], rtol=1e-12)
        np.testing.assert_allclose(metres, [3.0 * k], rtol=1e-12)


def test_face_effects_cost_rejects_bad_input(core):
    axes = np.zeros((2, 3))
    with pytest.raises(ValueError):
        core.PointPlaneEffectsDistanceCost(0.0, np.zeros(3), axes, 10.0, True)
    with pytest.raises(ValueError):
        core.PointPlaneEffectsDistanceCost(0.1, np.zeros(3), axes, 0.0, True)
    with pytest.raises(ValueError):
        core.PointPlaneEffectsDistanceCost(0.1, np.zeros(3), np.full((2, 3), np.nan), 1.0,
                                           True)
