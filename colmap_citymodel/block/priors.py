"""GNSS positions as priors of the adjustment, in the plane store's local frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from .reconstruction import position_in_rig


@dataclass
class GNSSPriors:
    """GNSS projection centres matched to the reconstruction, in the local frame."""

    image_ids: np.ndarray  # (N,) int
    positions: np.ndarray  # (N, 3)
    sigmas: np.ndarray  # (N, 3)
    # GNSS antenna in the rig frame (for a single camera: x right, y down, z along the view);
    # None: the positions are of the projection centres.
    lever_arm: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.image_ids)

    def observed_in_rig(self, rec: pycolmap.Reconstruction, image: pycolmap.Image
                        ) -> np.ndarray:
        """What GNSS observed, in the image's rig frame: the antenna (lever arm) or the camera's
        projection centre."""
        if self.lever_arm is not None:
            return np.asarray(self.lever_arm, float)
        return position_in_rig(rec, image)

    def observed_points(self, rec: pycolmap.Reconstruction) -> np.ndarray:
        """Where the block currently puts what GNSS observed (antennas or centres): (N, 3)."""
        out = np.empty((len(self), 3))
        for k, image_id in enumerate(self.image_ids):
            image = rec.image(int(image_id))
            out[k] = (rec.frame(image.frame_id).rig_from_world.inverse()
                      * self.observed_in_rig(rec, image))
        return out


def scale_sigma_from_gnss(priors: GNSSPriors) -> float:
    """Relative sigma of the block's scale that its GNSS positions determine."""
    spread = priors.positions - priors.positions.mean(0)
    return float(np.median(priors.sigmas) / np.sqrt(max(np.sum(spread ** 2), 1e-12)))
