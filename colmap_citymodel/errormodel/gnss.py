"""GNSS's error over a block: white noise per position, a bias common to the block, and a
slowly varying part along the track.

A receiver's error over a flight is not independent per image. Per axis a, with the stated
sigma s_k of position k:

    g_k = C_k + b + m_k + w_k,   w_k ~ N(0, s_k^2)                    white
                                 b ~ N(0, (share_b s)^2)              common to the block
                                 m_k first-order Gauss-Markov along the track:
                                 cov(m_k, m_l) = (share_m s)^2 exp(-|t_k - t_l| / L)

(t the distance travelled along the camera path, L the correlation length; s the median stated
sigma of the axis). The positions' covariance per axis is Sigma = diag(s_k^2) + b^2 1 1^T +
m^2 K. What GNSS says of the block's position is then sqrt(1 / (1^T Sigma^-1 1)) per axis: about
sqrt(s^2 / n + b^2 + m^2 L / (L + length)), not s / sqrt(n): 120 images at 3 m know the block's
position to about 1.6 m, not 0.27 m.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np


@dataclass(frozen=True, eq=False)
class GNSSErrorModel:
    """The GNSS positions' covariance over a block (module docstring), per axis E, N, U.
    `free_axes`: the axes along which a GNSS offset is an unknown without a prior (another
    height system): there GNSS keeps only differences between its positions."""

    sigmas: np.ndarray  # (n, 3) stated white sigma per position (m)
    bias: np.ndarray  # (3,) sigma of the bias common to the block (m)
    drift: np.ndarray  # (3,) sigma of the slowly varying part (m)
    length: float  # its correlation length along the track (m)
    track: np.ndarray  # (n,) distance travelled along the camera path (m)
    free_axes: np.ndarray  # (3,) bool

    @classmethod
    def from_priors(cls, priors, centres: np.ndarray, bias_share: float, drift_share: float,
                    length: float) -> "GNSSErrorModel":
        """The error model of `priors` (block.priors.GNSSPriors): bias and drift sigmas the
        given shares of the median stated sigma per axis (AdjustmentOptions.gnss_bias_share,
        gnss_drift_share), the drift's correlation length `length` (m) along the track that
        `centres` (n, 3: where the block puts the positions, in their order) travel: the
        block's own shape, not the noisy positions, measures the distance."""
        sigmas = np.asarray(priors.sigmas, float).reshape(-1, 3)
        median = np.median(sigmas, axis=0) if len(sigmas) else np.zeros(3)
        return cls(sigmas, bias_share * median, drift_share * median, float(length),
                   track_distance(np.asarray(centres, float)),
                   np.asarray(priors.free_offset_axes, bool).copy())

    @classmethod
    def independent(cls, sigmas, free_axes=None) -> "GNSSErrorModel":
        """Positions with white noise of `sigmas` (n, 3) only, the level free along
        `free_axes` (bool (3,))."""
        sigmas = np.asarray(sigmas, float).reshape(-1, 3)
        free = np.zeros(3, bool) if free_axes is None else np.asarray(free_axes, bool)
        return cls(sigmas, np.zeros(3), np.zeros(3), 0.0, np.zeros(len(sigmas)), free)

    def covariance(self, axis: int) -> np.ndarray:
        """(n, n) covariance of the positions along `axis` (free axes: their white part and
        drift only; the common level is free)."""
        s = self.sigmas[:, axis]
        cov = np.diag(s ** 2)
        if self.drift[axis] > 0 and self.length > 0:
            lag = np.abs(self.track[:, None] - self.track[None, :])
            cov += self.drift[axis] ** 2 * np.exp(-lag / self.length)
        if self.bias[axis] > 0 and not self.free_axes[axis]:
            cov += self.bias[axis] ** 2
        return cov

    def weights(self, axis: int) -> np.ndarray:
        """(n, n) the inverse of `covariance(axis)`; with the common level free along a free
        axis (its projector removed)."""
        return self._weights[axis]

    @cached_property
    def _weights(self) -> list[np.ndarray]:
        return [self._inverse(axis) for axis in range(3)]

    def _inverse(self, axis: int) -> np.ndarray:
        inverse = np.linalg.inv(self.covariance(axis))
        if self.free_axes[axis]:
            one = inverse.sum(axis=1)
            inverse = inverse - np.outer(one, one) / one.sum()
        return inverse

    def weigh(self, axis: int, x: np.ndarray) -> np.ndarray:
        """`weights(axis)` @ x for x (n,) or (n, k): without the slowly varying part in closed
        form (the white noise's diagonal and the bias's rank one, Woodbury), so a block of
        thousands of images needs no dense matrix."""
        x = np.asarray(x, float)
        if self.drift[axis] > 0 and self.length > 0:
            return self.weights(axis) @ x
        inverse_diagonal = 1.0 / self.sigmas[:, axis] ** 2
        d = inverse_diagonal.reshape((-1,) + (1,) * (x.ndim - 1)) * x
        if self.free_axes[axis]:  # the level free: its projector removed
            return d - np.multiply.outer(inverse_diagonal, d.sum(axis=0)) / inverse_diagonal.sum()
        if self.bias[axis] > 0:
            denominator = 1.0 / self.bias[axis] ** 2 + inverse_diagonal.sum()
            return d - np.multiply.outer(inverse_diagonal, d.sum(axis=0)) / denominator
        return d

    def shift_sigma(self) -> np.ndarray:
        """(3,) sigma (m) of the block's position from GNSS alone per axis: 1 / sqrt(1^T W 1);
        inf along a free axis."""
        out = np.full(3, np.inf)
        ones = np.ones(len(self.sigmas))
        for axis in range(3):
            if not self.free_axes[axis] and len(self.sigmas):
                out[axis] = 1.0 / np.sqrt(max(float(self.weigh(axis, ones).sum()), 1e-300))
        return out

    def datum_information(self, positions: np.ndarray, centre: np.ndarray) -> np.ndarray:
        """7x7 information of the block's datum (shifts, log scale, rotations about `centre`)
        from GNSS at `positions` (n, 3: where the block puts what GNSS observed)."""
        positions = np.asarray(positions, float).reshape(-1, 3)
        info = np.zeros((7, 7))
        for axis in range(3):
            directions = np.zeros_like(positions)
            directions[:, axis] = 1.0
            jacobian = datum_jacobian(positions, directions, centre)
            info += jacobian.T @ self.weigh(axis, jacobian)
        return info

    def chi2(self, residuals: np.ndarray) -> float:
        """The squared Mahalanobis norm of (n, 3) residuals (where the block puts what GNSS
        observed minus the observations) under the model."""
        v = np.asarray(residuals, float).reshape(-1, 3)
        return float(sum(v[:, a] @ self.weigh(a, v[:, a]) for a in range(3)))

    def shift_quadratic(self, residuals: np.ndarray) -> "ShiftQuadratic":
        """chi2 of the residuals after a common shift t of the block, as a quadratic in t:
        chi2(t) = c + 2 q.t + t.P.t (P diagonal: the axes are independent)."""
        v = np.asarray(residuals, float).reshape(-1, 3)
        p, q, c = np.zeros(3), np.zeros(3), 0.0
        for axis in range(3):
            ones = self.weigh(axis, np.ones(len(v)))
            p[axis] = float(ones.sum())
            q[axis] = float(ones @ v[:, axis])
            c += float(v[:, axis] @ self.weigh(axis, v[:, axis]))
        return ShiftQuadratic(c, q, p)


@dataclass(frozen=True)
class ShiftQuadratic:
    """chi2(t) = c + 2 q.t + sum_a p_a t_a^2 for shifts t (..., 3) of the block."""

    c: float
    q: np.ndarray
    p: np.ndarray

    def __call__(self, shifts: np.ndarray) -> np.ndarray:
        t = np.asarray(shifts, float)
        return self.c + 2.0 * t @ self.q + (t ** 2) @ self.p

    @property
    def minimum(self) -> np.ndarray:
        """(3,) the shift GNSS alone prefers (0 along an axis GNSS does not hold)."""
        return np.where(self.p > 0, -self.q / np.maximum(self.p, 1e-300), 0.0)


def datum_jacobian(points: np.ndarray, directions: np.ndarray, centre: np.ndarray
                   ) -> np.ndarray:
    """d (direction . X') / d (shift, log scale, rotation) for X' = X + t + s y + w x y, y =
    X - centre: (n, 7), the datum's order E, N, U, scale, rotations about E, N, U."""
    y = points - centre
    return np.hstack([directions, np.einsum("ij,ij->i", directions, y)[:, None],
                      np.cross(y, directions)])


def track_distance(positions: np.ndarray) -> np.ndarray:
    """(n,) distance (m) travelled along `positions` in their order, from the first."""
    if len(positions) < 2:
        return np.zeros(len(positions))
    steps = np.linalg.norm(np.diff(positions, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])
