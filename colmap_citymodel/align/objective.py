"""The one figure that every start-up move and refine iteration must lower."""

from __future__ import annotations

import numpy as np
import pycolmap

from ..block.priors import GNSSPriors
from ..block.reconstruction import TiePointReader
from .georegister import transform_points


class BlockObjective:
    """One figure that every start-up move and loop iteration must lower: minus the share of a
    fixed subset of tie points near the model surfaces, plus the mean squared normalised GNSS
    residual (a one-sigma shift of the whole block costs as much as 1 % of the tie points on
    the model; none along the axes where a GNSS offset is estimated,
    GNSSPriors.normalised_residuals)."""

    def __init__(self, surface, priors: GNSSPriors | None, point_ids: np.ndarray,
                 radius: float):
        from .coarse import MAX_SEARCH_POINTS, SHIFT_PENALTY

        rng = np.random.default_rng(1)
        self.ids = (point_ids if len(point_ids) <= 2 * MAX_SEARCH_POINTS else
                    rng.choice(point_ids, 2 * MAX_SEARCH_POINTS, replace=False))
        self.surface, self.priors, self.radius = surface, priors, radius
        self.penalty = SHIFT_PENALTY
        self._read = TiePointReader(ids=self.ids)

    def points(self, rec: pycolmap.Reconstruction) -> np.ndarray:
        """The subset's current coordinates (those of its points that `rec` has)."""
        return self._read(rec)[1]

    def __call__(self, rec: pycolmap.Reconstruction, moved: pycolmap.Sim3d | None = None
                 ) -> float:
        from .coarse import near_share

        points, antennas = self.points(rec), None
        if self.priors is not None:
            antennas = self.priors.observed_points(rec)
        if moved is not None:
            points = transform_points(moved, points)
            if antennas is not None:
                antennas = transform_points(moved, antennas)
        value = -near_share(self.surface(points, self.radius), self.radius)
        if antennas is not None:
            v = self.priors.normalised_residuals(antennas)
            value += self.penalty * float(np.mean(np.sum(v ** 2, axis=1)))
        return value
