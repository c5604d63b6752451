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
                         scale_sigma: float | None = None, gnss_free_axes=None,
                         gnss_model=None) -> PlaneAlignment:
    """The similarity X -> c + s R (X - c) + t that puts `points` on their planes.

    Minimises sum rho((n.X' + d) / sigma_plane) with Huber's rho (scale `loss_scale`, the f_dTP
    loss of the hybrid adjustment) plus, when given, the chi-square of the GNSS antenna
    positions A (current block) against their observations G under GNSS's error model
    (`gnss_model`, errormodel.gnss.GNSSErrorModel: white noise, the bias common to the block,
    the slowly varying part; else independent positions of `gnss_sigmas`, with the level free
    along `gnss_free_axes`, bool (3,)), plus (log s / scale_sigma)^2 when `scale_sigma` is
    given: the scale may change only as far as GNSS determines it (planes alone pull a block
    whose assignments are partly wrong towards a smaller size, where every distance is
    shorter); the scale is also bounded to +- SCALE_BOUND_SIGMAS of it. Gauss-Newton with
    iteratively reweighted least squares; analytic Jacobian about the centroid c.
    """
    from ..errormodel.gnss import GNSSErrorModel

    points, normals = np.asarray(points, float), np.asarray(normals, float)
    offsets = np.asarray(offsets, float)
    planes = _PlaneTerm(points, normals, offsets, sigma_plane, loss_scale)
    if gnss is not None and len(gnss) and gnss_model is None:
        gnss_model = GNSSErrorModel.independent(gnss_sigmas, gnss_free_axes)
    term = None if gnss is None or not len(gnss) else _GNSSTerm(
        np.asarray(antennas, float), np.asarray(gnss, float), gnss_model)
    centre = points.mean(0)
    # The similarity accumulated so far: X' = centre + scale * rotation (X - centre) + shift.
    rotation, scale, shift = np.eye(3), 1.0, np.zeros(3)

    def apply(x: np.ndarray) -> np.ndarray:
        return centre + scale * (x - centre) @ rotation.T + shift

    rms_before = planes.inlier_rms(points)
    iteration = 0
    for iteration in range(1, max_iterations + 1):
        moved = apply(points)
        normal_matrix, rhs = planes.normal_equations(moved, centre)
        if term is not None:
            gain, right = term.normal_equations(apply(term.antennas), centre)
            normal_matrix, rhs = normal_matrix + gain, rhs + right
        if scale_sigma is not None:
            normal_matrix[6, 6] += 1.0 / scale_sigma ** 2
            rhs[6] -= np.log(scale) / scale_sigma ** 2
        # A tiny damping keeps directions no plane constrains (e.g. parallel facades) at zero.
        damping = 1e-9 * max(np.trace(normal_matrix), 1.0)
        step = np.linalg.solve(normal_matrix + damping * np.eye(7), rhs)
        omega, dt, ds = step[:3], step[3:6], step[6]
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
        radius = float(np.max(np.linalg.norm(moved - centre, axis=1)))
        if (np.linalg.norm(omega) + abs(ds)) * radius + np.linalg.norm(dt) < 1e-4:
            break
    sim3 = pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation),
                          centre + shift - scale * rotation @ centre)
    return PlaneAlignment(sim3, rms_before, planes.inlier_rms(apply(points)), iteration)


@dataclass
class _PlaneTerm:
    """The tie points' part of similarity_to_planes: Huber-weighted distances to their planes."""

    points: np.ndarray
    normals: np.ndarray
    offsets: np.ndarray
    sigma: float
    loss_scale: float

    def residuals(self, x: np.ndarray) -> np.ndarray:
        return (np.einsum("ij,ij->i", self.normals, x) + self.offsets) / self.sigma

    def inlier_rms(self, x: np.ndarray) -> float:
        r = self.residuals(x)
        inliers = np.abs(r) <= self.loss_scale
        return float(np.sqrt(np.mean(r[inliers] ** 2)) * self.sigma) if inliers.any() else np.nan

    def normal_equations(self, moved: np.ndarray, centre: np.ndarray):
        """(7x7, 7) of the Huber IRLS step in (omega, t, log s) at the moved points."""
        r = self.residuals(moved)
        y = moved - centre
        # d r / d (omega, t, log s) at the current state, for X' -> X' + omega x y + t + y ds.
        jacobian = np.hstack([np.cross(y, self.normals), self.normals,
                              np.einsum("ij,ij->i", self.normals, y)[:, None]]) / self.sigma
        weights = np.minimum(1.0, self.loss_scale / np.maximum(np.abs(r), 1e-12))
        return jacobian.T @ (jacobian * weights[:, None]), -jacobian.T @ (weights * r)


@dataclass
class _GNSSTerm:
    """GNSS's part of similarity_to_planes: the antennas against the observations, per axis
    weighted by the inverse of GNSS's covariance over the block (its error model)."""

    antennas: np.ndarray
    observed: np.ndarray
    model: object  # errormodel.gnss.GNSSErrorModel

    def normal_equations(self, moved: np.ndarray, centre: np.ndarray):
        """(7x7, 7) of the Gauss-Newton step in (omega, t, log s) at the moved antennas."""
        a = moved - centre
        jacobian = np.concatenate([-_skew(a), np.broadcast_to(np.eye(3), (len(a), 3, 3)),
                                   a[:, :, None]], axis=2)  # (n, 3, 7)
        v = moved - self.observed
        normal_matrix, rhs = np.zeros((7, 7)), np.zeros(7)
        for axis in range(3):
            j = jacobian[:, axis, :]
            normal_matrix += j.T @ self.model.weigh(axis, j)
            rhs -= j.T @ self.model.weigh(axis, v[:, axis])
        return normal_matrix, rhs
