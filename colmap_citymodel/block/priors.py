"""GNSS positions as priors of the adjustment, in the plane store's local frame."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap

from .reconstruction import position_in_rig

#: Axis names of the local frame (easting, northing, height).
AXES = ("E", "N", "U")
#: The GNSS offset's unknown components per AdjustmentOptions.gnss_offset.
OFFSET_AXES = {"none": (False, False, False), "height": (False, False, True),
               "all": (True, True, True)}


@dataclass
class GNSSPriors:
    """GNSS projection centres matched to the reconstruction, in the local frame.

    What GNSS observed is `positions + offset`: `offset` is a constant offset of all positions
    (a height offset between height systems, a bias common to the flight). Its components named
    by `offset_axes` are unknowns of the adjustment, fixed by the model planes (`--gnss_height_offset
    auto`: U; `--gnss_bias auto`: E, N, U), with the prior N(0, offset_prior_sigma^2) about the
    positions as read (one sigma, or one per axis E N U), or free (None); the others stay 0.
    `bias_is_random`: the offset is the GNSS error common to the block, a random effect with its
    prior (never dropped): GNSS keeps its level at that sigma (`free_offset_axes` none)."""

    image_ids: np.ndarray  # (N,) int
    positions: np.ndarray  # (N, 3)
    sigmas: np.ndarray  # (N, 3)
    # GNSS antenna in the rig frame (for a single camera: x right, y down, z along the view);
    # None: the positions are of the projection centres.
    lever_arm: np.ndarray | None = None
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))  # (3,) metres, E N U
    offset_axes: np.ndarray = field(default_factory=lambda: np.zeros(3, bool))  # (3,) bool
    offset_prior_sigma: float | np.ndarray | None = None
    bias_is_random: bool = False

    def __len__(self) -> int:
        return len(self.image_ids)

    @property
    def estimates_offset(self) -> bool:
        return bool(np.any(self.offset_axes))

    @property
    def free_offset_axes(self) -> np.ndarray:
        """(3,) bool: the axes along which GNSS keeps no level of its own (an offset estimated
        without a prior of the GNSS's bias)."""
        if self.bias_is_random:
            return np.zeros(3, bool)
        return np.asarray(self.offset_axes, bool)

    @property
    def observed(self) -> np.ndarray:
        """The GNSS positions with the current offset: (N, 3)."""
        return self.positions + self.offset

    def offset_directions(self) -> np.ndarray:
        """(3, k) unit columns of the offset's unknown components (k = number of them)."""
        return np.eye(3)[:, np.asarray(self.offset_axes, bool)]

    def offset_weights(self) -> np.ndarray:
        """(N, 3) weights 1/sigma^2 of each position in the offset's least-squares estimate."""
        return 1.0 / self.sigmas ** 2

    def normalised_residuals(self, antennas: np.ndarray) -> np.ndarray:
        """(antennas - observed) / sigmas, with the weighted mean removed on the offset's
        unknown axes: there the offset follows the block, so no common shift costs anything."""
        v = antennas - self.observed
        axes = np.asarray(self.offset_axes, bool)
        if axes.any():
            w = self.offset_weights()
            v[:, axes] -= (np.sum(w * v, axis=0) / np.sum(w, axis=0))[axes]
        return v / self.sigmas

    def fit_offset(self, rec: pycolmap.Reconstruction) -> np.ndarray:
        """Set the offset's unknown components to the weighted mean of (where the block puts
        the antennas - the positions); returns the offset."""
        axes = np.asarray(self.offset_axes, bool)
        if axes.any():
            w = self.offset_weights()
            mean = np.sum(w * (self.observed_points(rec) - self.positions), axis=0) / np.sum(w, 0)
            self.offset = np.where(axes, mean, self.offset)
        return self.offset

    def offset_mean_sigma(self) -> np.ndarray:
        """(3,) sigma (m) of the mean of the positions per axis: what GNSS noise adds to an
        offset the planes fix."""
        return 1.0 / np.sqrt(np.sum(self.offset_weights(), axis=0))

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


def priors_of_registered_images(gnss, rec: pycolmap.Reconstruction, origin: np.ndarray,
                                **fields) -> GNSSPriors:
    """The GNSS positions (block.gnss.GNSSObservations) of `rec`'s registered images as priors
    in the local frame of `origin`, with the observations' lever arm; `fields` set the rest
    (offset_axes, offset)."""
    from .gnss import match_to_reconstruction

    image_ids, positions, sigmas = match_to_reconstruction(gnss, rec, origin)
    lever_arm = getattr(gnss, "lever_arm", None)
    return GNSSPriors(np.asarray(image_ids), np.asarray(positions), np.asarray(sigmas),
                      None if lever_arm is None else np.asarray(lever_arm, float), **fields)


def scale_sigma_from_gnss(priors: GNSSPriors) -> float:
    """Relative sigma of the block's scale that its GNSS positions determine."""
    spread = priors.positions - priors.positions.mean(0)
    return float(np.median(priors.sigmas) / np.sqrt(max(np.sum(spread ** 2), 1e-12)))
