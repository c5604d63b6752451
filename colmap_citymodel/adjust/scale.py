"""Holding the block's scale at the GNSS-only block's, and its height where the first
assignment put it (where GNSS itself is precise: where GNSS put it), where the planes cannot
determine them."""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from ..block.priors import GNSSPriors
from ..block.reconstruction import observer_centres
from .observability import gnss_bias_sigmas
from .problem import LEVEL_FREE, BaselinePriors

logger = logging.getLogger(__name__)


#: A solve that changes the block's scale from the GNSS-only one by more than this many GNSS
#: scale sigmas holds the scale from then on (BaselinePriors): GNSS puts the true scale within
#: three sigma, so further is the point-to-plane residuals shrinking.
SCALE_RUNAWAY_SIGMAS = 3.0

#: Up to this many sigmas the solve is kept and the next one, with the scale held, takes the
#: scale back; further, the block may have collapsed onto a few planes and the solve is undone
#: and repeated from the state before it. Repeating costs the first iteration's two solves
#: again, the most expensive of a refine, so a moderate change is left to the next solve.
SCALE_UNDO_SIGMAS = 10.0


#: A solve refines a placement: one that moves the cameras on average further from GNSS's
#: positions along an axis, by more than this many sigmas of GNSS's datum there (the mean
#: position's sigma with the error common to the block), has run away along a direction the
#: planes hardly fix (a height that only the small tilts of near-vertical walls hold). It is
#: undone and repeated with that axis held. A move towards GNSS (out of a wrong placement) is
#: not one.
SHIFT_UNDO_SIGMAS = 5.0


def shift_runaway(before: np.ndarray, after: np.ndarray, priors, bias_share: float
                  ) -> np.ndarray:
    """bool (3,) E N U: the axes along which the GNSS images' mean move from `before` to
    `after` ((N, 3) m, their centres in `priors.image_ids` order, nan where not registered)
    leads away from GNSS's positions by more than SHIFT_UNDO_SIGMAS of GNSS's datum sigma: the
    sigma of the mean of its positions with `bias_share` of their stated sigma common to the
    block (AdjustmentOptions.gnss_bias_share)."""
    if before.shape != after.shape or not len(before) or not len(priors.sigmas):
        return np.zeros(3, bool)
    both = np.all(np.isfinite(before) & np.isfinite(after), axis=1)
    if not both.any():
        return np.zeros(3, bool)
    bias = gnss_bias_sigmas(priors, bias_share)
    datum = np.sqrt(gnss_mean_sigmas(priors) ** 2 + (0.0 if bias is None else bias ** 2))
    positions = np.asarray(priors.positions, float)[both]
    off_before = np.mean(before[both] - positions, axis=0)
    off_after = np.mean(after[both] - positions, axis=0)
    return (np.abs(off_after - off_before) > SHIFT_UNDO_SIGMAS * datum) \
        & (np.abs(off_after) > np.abs(off_before))


def gnss_mean_sigmas(priors: GNSSPriors) -> np.ndarray:
    """(3,) m: the sigma of the weighted mean of the GNSS positions per axis, E N U."""
    return 1.0 / np.sqrt(np.sum(1.0 / np.asarray(priors.sigmas, float) ** 2, axis=0))


def scale_change(reference: pycolmap.Reconstruction, rec: pycolmap.Reconstruction,
                 image_ids) -> float:
    """Relative scale of the camera centres of `image_ids` in `rec` against `reference`
    (similarity fit) - 1."""
    ids = [int(i) for i in image_ids]
    a = np.array([reference.image(i).projection_center() for i in ids])
    b = np.array([rec.image(i).projection_center() for i in ids])
    similarity = pycolmap.estimate_sim3d(a, b)
    return float(similarity.scale) - 1.0 if similarity is not None else 0.0


#: Where the planes do not determine the scale, the baseline priors hold the GNSS-only
#: block's scale this many times tighter than GNSS's own scale sigma: point-to-plane residuals
#: shrink with the block (a similarity changes no reprojection error), and a few GNSS priors
#: do not hold thousands of them.
BASELINE_TIGHTENING = 10.0


def baseline_priors(gnss_only: pycolmap.Reconstruction, priors: GNSSPriors,
                    scale_sigma: float | None, *, hold_scale: bool = True,
                    level: tuple[int, np.ndarray, np.ndarray] | None = None
                    ) -> BaselinePriors | None:
    """What the GNSS-only block holds: with `hold_scale`, pairs of GNSS images half the block
    apart along its main axis, with their distances in the GNSS-only adjustment, which together
    hold its scale to scale_sigma / BASELINE_TIGHTENING; with `level` (from `level_prior`), one
    image's projection centre along the axes it holds. None when neither is asked for."""
    ids = np.asarray(priors.image_ids)
    hold_scale = bool(hold_scale and scale_sigma and len(ids) > 1)
    pairs, lengths, sigmas = np.zeros((0, 2), np.int64), np.zeros(0), np.zeros(0)
    if hold_scale:
        centres = observer_centres(gnss_only, ids)
        axis = np.linalg.svd(centres - centres.mean(0))[2][0]
        order = np.argsort((centres - centres.mean(0)) @ axis)
        half = len(order) // 2
        first, second = order[:half], order[len(order) - half:]
        pairs = np.column_stack([ids[first], ids[second]])
        lengths = np.linalg.norm(centres[first] - centres[second], axis=1)
        relative = scale_sigma / BASELINE_TIGHTENING * np.sqrt(max(len(pairs), 1))
        sigmas = np.maximum(lengths * relative, 1e-6)
        logger.info("the planes do not fix the block's scale: %d baseline priors hold the "
                    "GNSS-only scale (sigma %.2g)", len(pairs), scale_sigma / BASELINE_TIGHTENING)
    if not hold_scale and level is None:
        return None
    holds = BaselinePriors(pairs, lengths, sigmas, tightening=BASELINE_TIGHTENING,
                           level_tightening=LEVEL_TIGHTENING)
    if level is not None:
        holds.level_image, holds.level_position, holds.level_sigmas = level
    return holds


#: Where the planes do not determine the height, the level prior holds it this many times
#: tighter than the mean of the GNSS heights: the planes' own information there, walls tilted
#: by a fraction of a degree, would otherwise move the block by metres
#: (`WorkflowOptions.hold_gnss_height`).
LEVEL_TIGHTENING = 10.0


def level_prior(block: pycolmap.Reconstruction, priors: GNSSPriors, axes: np.ndarray,
                gnss_only: pycolmap.Reconstruction | None = None
                ) -> tuple[int, np.ndarray, np.ndarray] | None:
    """The level of the block along `axes` (bool (3,), E N U: those the planes leave to GNSS)
    as one image holds it: of its GNSS images, the one whose projection centre is nearest
    their centroid, its centre in the GNSS-only block `gnss_only` (no move without evidence:
    nothing in the model says where else the block should be along those axes; without it, in
    `block`), and the sigmas that hold it there, the GNSS sigma of the mean of all positions /
    LEVEL_TIGHTENING (LEVEL_FREE elsewhere). One image near the middle leaves the block's
    rotations to the planes and GNSS. None when no axis is held."""
    axes = np.asarray(axes, bool)
    if not axes.any():
        return None
    ids = np.asarray(priors.image_ids)
    points = observer_centres(block, ids)
    anchor = int(np.argmin(np.linalg.norm(points - points.mean(0), axis=1)))
    position = np.array(points[anchor], dtype=np.float64)
    if gnss_only is not None:
        position = np.where(axes, observer_centres(gnss_only, ids[anchor:anchor + 1])[0],
                            position)
    sigmas = np.where(axes, gnss_mean_sigmas(priors) / LEVEL_TIGHTENING, LEVEL_FREE)
    logger.info("the planes do not fix the block's %s: held where %s put it (sigma %s m)",
                "/".join(a for a, h in zip("ENU", axes) if h),
                "GNSS" if gnss_only is not None else "the first assignment",
                "/".join(f"{v:.2g}" for v, h in zip(sigmas, axes) if h))
    return int(ids[anchor]), position, sigmas
