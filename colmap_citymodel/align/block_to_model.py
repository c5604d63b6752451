"""Bring the block into the model's local frame (a similarity to GNSS, or a given transform)
and keep the part of the model that it overlaps."""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
import pycolmap

from ..block.priors import OFFSET_AXES, GNSSPriors
from ..block.reconstruction import camera_centres, tie_points
from ..citymodel.store import PlaneStore
from ..errors import GeoregistrationError, GNSSError, NoOverlapError

logger = logging.getLogger(__name__)


def crop_to_reconstruction(store: PlaneStore, rec: pycolmap.Reconstruction, margin: float
                           ) -> PlaneStore:
    """Keep the model faces near the georegistered reconstruction; none: NoOverlapError."""
    _, points = tie_points(rec)
    xyz = np.vstack([points, camera_centres(rec)])
    lower = np.percentile(xyz, 1, axis=0) - margin
    upper = np.percentile(xyz, 99, axis=0) + margin
    # Heights are not trusted yet (GNSS heights may be ellipsoidal): crop in plan only.
    lower[2], upper[2] = -1e9, 1e9
    cropped = store.subset_bbox(lower, upper)
    if len(cropped.faces) == 0:
        raise NoOverlapError(
            "the city model does not overlap the georegistered reconstruction: model bbox "
            f"{_fmt_box(store.bbox_crs)} vs reconstruction bbox "
            f"{_fmt_box(np.array([lower, upper]) + store.origin)} (model CRS); check the CRS "
            "of the GNSS positions or the initial transform, and the model", store.source)
    return cropped


def _fmt_box(box: np.ndarray) -> str:
    return "[" + ", ".join(f"{v:.1f}" for v in np.asarray(box).ravel()) + "]"


def georegister(rec: pycolmap.Reconstruction, store: PlaneStore, gnss, initial_transform,
                details: dict | None = None, gnss_offset: str = "none"
                ) -> tuple[pycolmap.Sim3d, GNSSPriors | None, float | None]:
    """Bring the reconstruction into the store's local frame; return the applied similarity.
    `details`, when given, receives which cue fixed each datum parameter ("cues").
    `gnss_offset` (AdjustmentOptions.gnss_offset): the GNSS offset the adjustment estimates;
    with "height" or "all", heights that PROJ could not convert are accepted as they are."""
    from ..block.priors import priors_of_registered_images
    from .georegister import estimate_georegistration

    priors = None
    rms = None
    cues = {"translation": "initial transform", "scale": "initial transform",
            "rotation": "initial transform"}
    if gnss is not None:
        axes = np.array(OFFSET_AXES[gnss_offset], bool)
        if getattr(gnss, "vertical_applied", None) is False and not axes[2]:
            raise GNSSError(
                f"the GNSS heights ({gnss.path or gnss.source}) could not be converted to the "
                f"model's height system {store.crs.label} (PROJ lacks the geoid grid and the "
                "worldwide EGM96 grid of Debian's proj-data is not installed; see the warning "
                "above): let refine "
                "estimate the offset from the model (--gnss_height_offset auto), install "
                "proj-data or the national grid, give the heights already converted, or "
                "--gnss_height_offset METRES (model height minus GNSS height, e.g. about -47 "
                "for ellipsoidal heights in Germany)")
        priors = priors_of_registered_images(gnss, rec, store.origin, offset_axes=axes)
    if initial_transform is not None:
        # The given transform maps the input frame to model CRS coordinates.
        to_local = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), -store.origin)
        sim3 = to_local * initial_transform
    elif priors is not None:
        result = estimate_georegistration(rec, priors.positions, priors.image_ids,
                                          sigmas=priors.sigmas)
        sim3, rms, cues = result.sim3, result.rms, result.cues
        logger.info("georegistration to %d GNSS positions: scale %.4f, RMS %.2f m, %d inliers",
                    len(priors), sim3.scale, rms, int(np.count_nonzero(result.inlier_mask)))
        if not np.all(result.inlier_mask):
            # Positions the similarity rejected as gross errors would tear the block apart in
            # every later adjustment: they are not priors.
            keep = np.isin(priors.image_ids, result.image_ids[result.inlier_mask])
            priors = dataclasses.replace(priors, image_ids=priors.image_ids[keep],
                                         positions=priors.positions[keep],
                                         sigmas=priors.sigmas[keep])
            logger.warning("%d GNSS position(s) of %s left out of the adjustment as outliers",
                           int(np.count_nonzero(~keep)), gnss.path or gnss.source)
    else:
        raise GeoregistrationError(
            "no GNSS positions and no initial transform: give --database/--gnss/--exif or "
            "--initial_transform")
    rec.transform(sim3)
    if details is not None:
        details["cues"] = dict(cues)
    return sim3, priors, rms
