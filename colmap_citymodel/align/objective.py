"""The one figure that every start-up move and refine iteration must lower: minus the log-
likelihood of the block's placement (errormodel.score.PlacementScore: the tie points' distances
to faces and terrain, faces as units, and GNSS with its bias)."""

from __future__ import annotations

import numpy as np
import pycolmap
from scipy import stats

from ..block.priors import GNSSPriors
from ..block.reconstruction import TiePointReader
from ..errormodel.model import gnss_model, surface_model
from ..errormodel.score import MAX_SCORE_POINTS, PlacementScore
from ..options import AdjustmentOptions
from .georegister import transform_points

#: Datum parameters a placement has (three shifts, three rotations, the scale): the degrees of
#: freedom of the likelihood-ratio test between two placements.
DATUM_PARAMETERS = 7


class BlockObjective:
    """Minus the placement's log-likelihood of a fixed subset of the block's tie points (and its
    GNSS), on the cluster weights of the block where it was first evaluated. `tolerance`: by
    how much a placement may score worse than another before the difference is significant at
    `alpha` (likelihood ratio, chi-square with DATUM_PARAMETERS degrees of freedom)."""

    def __init__(self, surface, priors: GNSSPriors | None, point_ids: np.ndarray,
                 options: AdjustmentOptions, alpha: float = 0.001):
        rng = np.random.default_rng(1)
        self.ids = np.sort(point_ids if len(point_ids) <= MAX_SCORE_POINTS else
                           rng.choice(point_ids, MAX_SCORE_POINTS, replace=False))
        self.surface, self.priors, self.options = surface, priors, options
        self.tolerance = 0.5 * float(stats.chi2.ppf(1.0 - alpha, DATUM_PARAMETERS))
        self._read = TiePointReader(ids=self.ids)
        self._gnss = None  # GNSS's error model, built where the objective is first evaluated
        self._weights: dict[int, float] | None = None  # the cluster weights of then

    def points(self, rec: pycolmap.Reconstruction) -> np.ndarray:
        """The subset's current coordinates (those of its points that `rec` has)."""
        return self._read(rec)[1]

    def score(self, rec: pycolmap.Reconstruction):
        """The placement score (errormodel.score.PlacementScore) of `rec`'s block as it is now
        (its weights those of the first evaluation)."""
        ids, points = self._read(rec)
        antennas = self.priors.observed_points(rec) if self.priors is not None else None
        if self._weights is None:
            self._gnss = (gnss_model(self.priors, antennas, self.options)
                          if antennas is not None else None)
        score = PlacementScore(self.surface, surface_model(self.options), points, self._gnss,
                               antennas, None if self._gnss is None else self.priors.positions)
        if self._weights is None:
            self._weights = dict(zip(ids.tolist(), score.weights.tolist()))
        score.weights = np.array([self._weights.get(i, 1.0) for i in ids.tolist()])
        return score

    def __call__(self, rec: pycolmap.Reconstruction, moved: pycolmap.Sim3d | None = None
                 ) -> float:
        score = self.score(rec)
        points, antennas = score.points, score.antennas
        if moved is not None:
            points = transform_points(moved, points)
            antennas = None if antennas is None else transform_points(moved, antennas)
        value = score.points_term(points)
        if antennas is not None:
            value += score.gnss_term(antennas)
        return -value
