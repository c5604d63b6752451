"""The error model of one refine, built once from its options and the block's GNSS: what every
stage's score (errormodel.score.PlacementScore) and test reads its sigmas from."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..options import AdjustmentOptions
from .gnss import GNSSErrorModel
from .score import PlacementScore, SurfaceErrorModel

#: Sigma (m) of a tie point's own scatter about the surface it lies on, beyond its face's
#: error: facade relief (window recesses, pilasters) and the point's triangulation noise, a few
#: centimetres. What sigma_dtp holds beyond it is its face's error, shared by the face's points.
POINT_SCATTER = 0.05


def surface_model(options: AdjustmentOptions) -> SurfaceErrorModel:
    """The tie points' distances to their surfaces: sigma_dtp in all, of which all but
    POINT_SCATTER is their face's error, shared by its points (a detailed model's sigma_dtp is
    about the scatter alone: its points are independent)."""
    sigma = float(options.sigma_dtp)
    rho = float(np.clip(1.0 - (POINT_SCATTER / sigma) ** 2, 0.0, 1.0))
    return SurfaceErrorModel(sigma, rho)


def gnss_model(priors, centres: np.ndarray, options: AdjustmentOptions
               ) -> GNSSErrorModel | None:
    """GNSS's error model (errormodel.gnss) of `priors` (block.priors.GNSSPriors, None: no
    GNSS), its track along `centres` (where the block puts its positions)."""
    if priors is None or not len(priors.image_ids):
        return None
    model = GNSSErrorModel.from_priors(priors, centres, options.gnss_bias_share,
                                       options.gnss_drift_share, options.gnss_drift_length)
    prior = priors.offset_prior_sigma
    if priors.estimates_offset and prior is not None:
        # An offset estimated with a prior about the positions as read is a bias of that
        # sigma along its axes (the positions as read are the observations).
        axes = np.asarray(priors.offset_axes, bool)
        bias = np.where(axes, np.maximum(model.bias, np.broadcast_to(prior, 3)), model.bias)
        model = replace(model, bias=bias)
    return model


def placement_score(surface, points: np.ndarray, priors, antennas: np.ndarray | None,
                    options: AdjustmentOptions) -> PlacementScore:
    """The placement score of a block whose tie points are `points` and whose GNSS antennas
    (what GNSS observed) the block puts at `antennas`, against `surface`: GNSS's positions as
    read, any offset of them an error of its model (a bias), not subtracted."""
    gnss = gnss_model(priors, antennas, options) if antennas is not None else None
    return PlacementScore(surface, surface_model(options), points, gnss, antennas,
                          None if gnss is None else priors.positions)
