"""Initial values for the hybrid adjustment: the block's similarity to its assigned planes.

After georegistration to GNSS the block is metres off the model (method.md section 4). The
hybrid bundle adjustment would have to carry the whole block there through Levenberg-Marquardt
steps; most of that move is one 7-parameter similarity, which is cheap to estimate from the
assigned tie points alone. Applying it first leaves the bundle adjustment only the block's
deformation, in a fraction of the Ceres iterations. A similarity does not change any
reprojection error, so the adjustment's optimum is the same.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pycolmap

logger = logging.getLogger(__name__)


#: With a scale prior, the fitted scale never leaves +- this many of its sigmas.
SCALE_BOUND_SIGMAS = 3.0


@dataclass
class PlaneAlignment:
    """The similarity found and how well the points fit before and after it."""

    sim3: pycolmap.Sim3d
    rms_before: float
    """RMS point-to-plane distance (m) of the inliers (|r| <= loss scale) before, and after."""
    rms_after: float
    iterations: int


def _skew(v: np.ndarray) -> np.ndarray:
    """[v]_x for each row of v: (n, 3, 3)."""
    out = np.zeros((len(v), 3, 3))
    out[:, 0, 1], out[:, 0, 2] = -v[:, 2], v[:, 1]
    out[:, 1, 0], out[:, 1, 2] = v[:, 2], -v[:, 0]
    out[:, 2, 0], out[:, 2, 1] = -v[:, 1], v[:, 0]
    return out


def similarity_to_planes(points: np.ndarray, normals: np.ndarray, offsets: np.ndarray,
                         sigma_plane: float, loss_scale: float = 2.0,
                         antennas: np.ndarray | None = None, gnss: np.ndarray | None = None,
                         gnss_sigmas: np.ndarray | None = None, max_iterations: int = 50,
                         scale_sigma: float | None = None, gnss_free_axes=None
                         ) -> PlaneAlignment:
    """The similarity X -> c + s R (X - c) + t that puts `points` on their planes.

    Minimises sum rho((n.X' + d) / sigma_plane) with Huber's rho (scale `loss_scale`, the f_dTP
    loss of the hybrid adjustment) plus, when given, sum ((A' - G) / sigma_G)^2 of the GNSS
    antenna positions A (current block) against their observations G, plus (log s / scale_sigma)^2
    when `scale_sigma` is given: the scale may change only as far as GNSS determines it (planes
    alone pull a block whose assignments are partly wrong towards a smaller size, where every
    distance is shorter); the scale is also bounded to +- SCALE_BOUND_SIGMAS of it. Along
    `gnss_free_axes` (bool (3,)) a constant offset of all GNSS positions is an unknown as well
    (GNSSPriors.offset_axes), so GNSS holds only the block's shape there, not its level.
    Gauss-Newton with iteratively reweighted least squares; analytic Jacobian about the
    centroid c.
    """
    points = np.asarray(points, float)
    normals = np.asarray(normals, float)
    offsets = np.asarray(offsets, float)
    centre = points.mean(0)
    # The similarity accumulated so far: X' = centre + scale * rotation (X - centre) + shift.
    rotation, scale, shift = np.eye(3), 1.0, np.zeros(3)
    free = (np.zeros(3, bool) if gnss_free_axes is None or gnss is None
            else np.asarray(gnss_free_axes, bool))
    num_free = int(free.sum())
    offset = np.zeros(3)  # the GNSS offset along the free axes (unknowns 7.. of the system)

    def apply(x: np.ndarray) -> np.ndarray:
        return centre + scale * (x - centre) @ rotation.T + shift

    def plane_residuals(x: np.ndarray) -> np.ndarray:
        return (np.einsum("ij,ij->i", normals, x) + offsets) / sigma_plane

    def inlier_rms(r: np.ndarray) -> float:
        inliers = np.abs(r) <= loss_scale
        return float(np.sqrt(np.mean(r[inliers] ** 2)) * sigma_plane) if inliers.any() else np.nan

    rms_before = inlier_rms(plane_residuals(points))
    iteration = 0
    for iteration in range(1, max_iterations + 1):
        moved = apply(points)
        r = plane_residuals(moved)
        y = moved - centre
        # d r / d (omega, t, log s) at the current state, for X' -> X' + omega x y + t + y ds.
        jacobian = np.hstack([np.cross(y, normals), normals,
                              np.einsum("ij,ij->i", normals, y)[:, None]]) / sigma_plane
        weights = np.minimum(1.0, loss_scale / np.maximum(np.abs(r), 1e-12))  # Huber IRLS
        size = 7 + num_free
        jacobian = np.hstack([jacobian, np.zeros((len(jacobian), num_free))])
        normal_matrix = jacobian.T @ (jacobian * weights[:, None])
        rhs = -jacobian.T @ (weights * r)
        if gnss is not None and len(gnss):
            a = apply(antennas) - centre
            rg = ((a + centre - gnss - offset) / gnss_sigmas).ravel()
            jo = -np.broadcast_to(np.eye(3)[:, free], (len(a), 3, num_free))
            jg = np.concatenate([-_skew(a), np.broadcast_to(np.eye(3), (len(a), 3, 3)),
                                 a[:, :, None], jo], axis=2) / gnss_sigmas[:, :, None]
            jg = jg.reshape(-1, size)
            normal_matrix += jg.T @ jg
            rhs -= jg.T @ rg
        if scale_sigma is not None:
            normal_matrix[6, 6] += 1.0 / scale_sigma ** 2
            rhs[6] -= np.log(scale) / scale_sigma ** 2
        # A tiny damping keeps directions no plane constrains (e.g. parallel facades) at zero.
        damping = 1e-9 * max(np.trace(normal_matrix), 1.0)
        step = np.linalg.solve(normal_matrix + damping * np.eye(size), rhs)
        omega, dt, ds = step[:3], step[3:6], step[6]
        offset[free] += step[7:]
        increment = np.asarray(pycolmap.Rotation3d(omega).matrix())
        # Compose: new X' = centre + e^ds * dR (X'_old - centre) + dt.
        if scale_sigma is not None:
            # Many wrongly assigned points outweigh any prior: bound the scale hard as well.
            bound = SCALE_BOUND_SIGMAS * scale_sigma
            ds = float(np.clip(np.log(scale) + ds, -bound, bound) - np.log(scale))
        rotation = increment @ rotation
        scale *= float(np.exp(ds))
        shift = np.exp(ds) * increment @ shift + dt
        # Converged when the update moves no point by more than 0.1 mm.
        radius = float(np.max(np.linalg.norm(y, axis=1)))
        if (np.linalg.norm(omega) + abs(ds)) * radius + np.linalg.norm(dt) < 1e-4:
            break
    sim3 = pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation),
                          centre + shift - scale * rotation @ centre)
    return PlaneAlignment(sim3, rms_before, inlier_rms(plane_residuals(apply(points))), iteration)
