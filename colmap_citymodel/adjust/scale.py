"""Holding the block's scale where the planes cannot determine it."""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from ..block.priors import GNSSPriors
from .problem import BaselinePriors

logger = logging.getLogger(__name__)


#: A solve that changes the block's scale from the GNSS-only one by more than this many GNSS
#: scale sigmas holds the scale from then on (BaselinePriors): GNSS puts the true scale within
#: three sigma, so further is the point-to-plane residuals shrinking.
SCALE_RUNAWAY_SIGMAS = 3.0

#: Up to this many sigmas the solve is kept and the next one, with the scale held, takes the
#: scale back; further, the block may have collapsed onto a few planes and the solve is undone
#: and repeated from the state before it. Repeating costs the first iteration's two solves
#: again, the most expensive of a refine (long Scn3, 0.57 % = 3.9 sigma: 47 s of 130 s, check
#: points 0.159 m either way).
SCALE_UNDO_SIGMAS = 10.0


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
#: shrink with the block (a similarity changes no reprojection error), and 16 GNSS priors do
#: not hold 2000 of them (a real drive past one facade row: -41 % with GNSS sigma 3 m).
BASELINE_TIGHTENING = 10.0


def baseline_priors(gnss_only: pycolmap.Reconstruction, priors: GNSSPriors,
                    scale_sigma: float) -> BaselinePriors:
    """Pairs of GNSS images half the block apart along its main axis, with their distances in
    the GNSS-only adjustment; together they hold its scale to scale_sigma / BASELINE_TIGHTENING."""
    ids = np.asarray(priors.image_ids)
    centres = np.array([gnss_only.image(int(i)).projection_center() for i in ids])
    axis = np.linalg.svd(centres - centres.mean(0))[2][0]
    order = ids[np.argsort((centres - centres.mean(0)) @ axis)]
    half = len(order) // 2
    pairs = np.column_stack([order[:half], order[len(order) - half:]])
    lengths = np.array([np.linalg.norm(gnss_only.image(int(a)).projection_center()
                                       - gnss_only.image(int(b)).projection_center())
                        for a, b in pairs])
    relative = scale_sigma / BASELINE_TIGHTENING * np.sqrt(max(len(pairs), 1))
    logger.info("the planes do not fix the block's scale: %d baseline priors hold the GNSS-only "
                "scale (sigma %.2g)", len(pairs), scale_sigma / BASELINE_TIGHTENING)
    return BaselinePriors(pairs, lengths, np.maximum(lengths * relative, 1e-6))
