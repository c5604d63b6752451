"""The log-likelihood of a block's placement on the model: one score for the placement search,
the similarity rounds, the loop's stopping rule and the verdict's tests.

A placement moves the block rigidly (a rotation about its cameras' centre and a shift). Under
it each tie point i has the distance d_i to the nearest surface that can carry tie points: a
model face or a terrain cell. The error model (docs/method.md, "The error model"):

- a tie point lies on a modelled surface with prior probability ON_SURFACE, its distance from
  it then N(0, sigma^2) (sigma: sigma_dtp, the point's scatter and its face's error
  together); otherwise (a tree, a car, a detail the model lacks, a wrong model's chance) it
  lies anywhere within OFF_SURFACE_SPREAD of the nearest surface, uniformly. Relative to lying
  on none, a point adds log(1 + k exp(-d^2 / 2 sigma^2)) with
  k = ON_SURFACE / (1 - ON_SURFACE) * OFF_SURFACE_SPREAD * 2 / (sqrt(2 pi) sigma);
- the points of one face share its error (its offset, share `rho` of sigma^2), and where the
  block is placed wrongly they leave their surface together: they are not independent
  observations. The points within one cube of CLUSTER_SIZE metres (about a face, measured in
  the block's own frame, which a rigid move does not change) count as n / (1 + (n - 1) rho)
  observations, each point's term weighed by 1 / (1 + (n - 1) rho) (a composite likelihood with
  the cluster's correlation): a facade of 3,000 points weighs about like a few observations,
  not like 3,000;
- GNSS adds -chi2 / 2 of its residuals under its error model (errormodel.gnss: white noise, a
  bias common to the block, a slowly varying part), which holds the directions the surfaces
  leave free where GNSS puts them.

A coarse-to-fine search anneals sigma only (`level_sigma`): at a grid step h the points'
distances count with sqrt(sigma^2 + (h / 2)^2), so a grid that steps past the optimum still sees
it; the finest level is the error model itself.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .gnss import GNSSErrorModel

#: Prior probability that a tie point lies on a modelled surface (a face or the terrain): city
#: blocks put most of their points on walls, roofs and ground; trees, cars and details the
#: model lacks carry the rest.
ON_SURFACE = 0.5
#: How far (m) from the nearest modelled surface a tie point that lies on none is found, its
#: distance uniform within it: clutter and details stand up to a few metres off the faces.
OFF_SURFACE_SPREAD = 5.0
#: Side (m) of the cubes whose tie points are taken to share one surface error: about the
#: extent of a LoD2 face (a facade bay, a roof plane), measured in the block's own frame.
CLUSTER_SIZE = 6.0
#: Distances count up to this many sigmas of the level; beyond, the term is below 1e-3 of its
#: peak.
REACH_SIGMAS = 4.0
#: Tie points a score evaluates at most (a random, seeded subset of a larger block): the
#: standard error of a share of them is then below 1.2 % (sqrt(0.25 / 2000)), at a cost per
#: score that does not grow with the block.
MAX_SCORE_POINTS = 2000


@dataclass(frozen=True)
class SurfaceErrorModel:
    """The tie points' distances to their surfaces (module docstring)."""

    sigma: float  # m: a point's distance from its surface, point and face error together
    rho: float  # the share of sigma^2 a face's points share (its offset's)

    def gain(self, sigma: float) -> float:
        """k of the module docstring at the level's `sigma`."""
        return (ON_SURFACE / (1.0 - ON_SURFACE) * OFF_SURFACE_SPREAD * 2.0
                / (np.sqrt(2.0 * np.pi) * sigma))

    def level_sigma(self, step: float) -> float:
        """The sigma (m) a search level with grid step `step` (m) counts distances with."""
        return float(np.hypot(self.sigma, 0.5 * step))

    def terms(self, distances: np.ndarray, sigma: float | None = None) -> np.ndarray:
        """Each point's log-likelihood of lying where it does, relative to lying on no
        surface, at `sigma` (default the model's)."""
        sigma = self.sigma if sigma is None else sigma
        d = np.asarray(distances, float)
        return np.log1p(self.gain(sigma) * np.exp(-0.5 * (d / sigma) ** 2))


def cluster_weights(points: np.ndarray, size: float, rho: float) -> np.ndarray:
    """(n,) each point's weight 1 / (1 + (m - 1) rho), m the number of `points` in its cube of
    side `size` (m): the cube's points together count as m / (1 + (m - 1) rho) observations."""
    if not len(points):
        return np.zeros(0)
    cells = np.floor(np.asarray(points, float) / size).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    return 1.0 / (1.0 + (counts[inverse.reshape(-1)] - 1) * rho)


def subsample(points: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """At most `n` of `points`, a seeded random subset."""
    if len(points) <= n:
        return points
    return points[np.random.default_rng(seed).choice(len(points), n, replace=False)]


class PlacementScore:
    """The log-likelihood (module docstring) of rigid moves of a block: its tie points
    `points` (n, 3) against `surface` (align.coarse.SurfaceDistance: faces and terrain), and,
    with `gnss` (errormodel.gnss.GNSSErrorModel), where the block puts what GNSS observed
    (`antennas`, (m, 3)) against the observations (`observed`)."""

    def __init__(self, surface, model: SurfaceErrorModel, points: np.ndarray,
                 gnss: GNSSErrorModel | None = None, antennas: np.ndarray | None = None,
                 observed: np.ndarray | None = None):
        self.surface, self.model, self.gnss = surface, model, gnss
        self.points = subsample(np.asarray(points, float).reshape(-1, 3), MAX_SCORE_POINTS)
        self.weights = cluster_weights(self.points, CLUSTER_SIZE, model.rho)
        self.antennas = None if gnss is None else np.asarray(antennas, float).reshape(-1, 3)
        self.observed = None if gnss is None else np.asarray(observed, float).reshape(-1, 3)

    @property
    def observations(self) -> float:
        """How many observations the tie points count as (the sum of their weights)."""
        return float(np.sum(self.weights))

    def points_term(self, points: np.ndarray, sigma: float | None = None) -> float:
        """The tie points' part of the log-likelihood for the moved `points` (this score's
        points moved, same order) at `sigma` (default the model's)."""
        sigma = self.model.sigma if sigma is None else sigma
        distances = self.surface(points, REACH_SIGMAS * sigma)
        return float(self.weights @ self.model.terms(distances, sigma))

    def gnss_term(self, antennas: np.ndarray) -> float:
        """GNSS's part: -chi2 / 2 of its residuals with the block's antennas at `antennas`."""
        if self.gnss is None:
            return 0.0
        return -0.5 * self.gnss.chi2(antennas - self.observed)

    def __call__(self, rotation: np.ndarray | None = None, shift=None, centre=None,
                 sigma: float | None = None) -> float:
        """The score of the block turned by `rotation` (3x3) about `centre` and moved by
        `shift` (3,); none: as it is."""
        points, antennas = self.points, self.antennas
        if rotation is not None:
            centre = np.zeros(3) if centre is None else np.asarray(centre, float)
            points = (points - centre) @ np.asarray(rotation).T + centre
            if antennas is not None:
                antennas = (antennas - centre) @ np.asarray(rotation).T + centre
        if shift is not None:
            points = points + shift
            antennas = None if antennas is None else antennas + shift
        return self.points_term(points, sigma) + (
            self.gnss_term(antennas) if antennas is not None else 0.0)

    def shift_scores(self, shifts: np.ndarray, sigma: float, points: np.ndarray | None = None,
                     antennas: np.ndarray | None = None) -> np.ndarray:
        """(k,) the score of each of `shifts` (k, 3) of the block (or of `points` and
        `antennas`, the block already turned) at `sigma`: exact distances per shift."""
        points = self.points if points is None else points
        shifts = np.asarray(shifts, float).reshape(-1, 3)
        moved = (points[None, :, :] + shifts[:, None, :]).reshape(-1, 3)
        d = self.surface(moved, REACH_SIGMAS * sigma).reshape(len(shifts), len(points))
        out = self.model.terms(d, sigma) @ self.weights
        return out + self.gnss_shift_terms(shifts, antennas)

    def gnss_shift_terms(self, shifts: np.ndarray, antennas: np.ndarray | None = None
                         ) -> np.ndarray:
        """(k,) GNSS's part for each of `shifts` (k, 3) of the block (its antennas at
        `antennas`, default as it is)."""
        if self.gnss is None:
            return np.zeros(len(shifts))
        antennas = self.antennas if antennas is None else antennas
        return -0.5 * self.gnss.shift_quadratic(antennas - self.observed)(shifts)
