"""Does the assignment fix the datum? Plane orientations that received tie points."""

from __future__ import annotations

import logging

import numpy as np

from ..assign.assignment import Assignment
from ..citymodel.store import PlaneStore
from ..errors import DatumError

logger = logging.getLogger(__name__)


# Two plane normals closer than this (either sign) count as the same orientation for the datum.
SAME_ORIENTATION_DEG = 10.0


# A direction whose weight in sum(n n^T) is below this fraction of the largest is "weak".
WEAK_DIRECTION_RATIO = 0.05


def check_datum(store: PlaneStore, assignment: Assignment, has_gnss: bool,
                observability: dict | None = None) -> list[str]:
    """Without GNSS the planes alone must fix the 7 datum parameters. Unger 3.2.3: four planes
    of different orientation do; fewer may too (three orthogonal orientations, with parallel
    planes apart for the scale: a straight street's facades, cross walls and roofs). With
    `observability` (adjust.observability, from the assigned tie points) it decides: raise
    when a parameter has no source or rests on a single plane; without it, at least four
    orientations are required. Warn about weak directions (e.g. only parallel facades leave
    the translation along the street free)."""
    normals = store.normals[assignment.faces]
    orientations: list[np.ndarray] = []
    cos_same = np.cos(np.radians(SAME_ORIENTATION_DEG))
    for n in normals:
        if all(abs(n @ o) < cos_same for o in orientations):
            orientations.append(n)
    if not has_gnss and observability is not None:
        free = [name for name, row in observability.items() if row.get("source") == "none"]
        if free:
            raise DatumError(
                f"without GNSS the model planes must fix the datum, but those that received "
                f"tie points ({len(normals)} planes, {len(orientations)} orientation(s)) leave "
                f"{', '.join(free)} free or on a single plane: give GNSS positions or a model "
                "that covers more of the scene", store.source or None)
    elif len(orientations) < 4 and not has_gnss:
        raise DatumError(
            f"only {len(orientations)} model plane orientation(s) received tie points "
            f"({len(normals)} planes); at least 4 different orientations are needed to fix the "
            "datum without GNSS: give GNSS positions or a model that covers more of the scene",
            store.source or None)
    warnings = []
    if len(normals):
        scatter = normals.T @ normals
        eigenvalues, eigenvectors = np.linalg.eigh(scatter)
        for value, direction in zip(eigenvalues, eigenvectors.T):
            if value < WEAK_DIRECTION_RATIO * eigenvalues[-1]:
                warnings.append(
                    f"the assigned planes hardly constrain the translation along {describe(direction)}"
                    + ("; only GNSS fixes it" if has_gnss else ""))
    for w in warnings:
        logger.warning(w)
    return warnings


def describe(direction: np.ndarray) -> str:
    """A direction in words: vertical, or a horizontal azimuth in the CRS (clockwise from north)."""
    if abs(direction[2]) > 0.9:
        return "the vertical"
    azimuth = np.degrees(np.arctan2(direction[0], direction[1])) % 180.0
    return f"the horizontal direction of azimuth {azimuth:.0f} deg"


def hold_where_gnss_alone(rec, gnss_only, image_ids: np.ndarray, alone: np.ndarray):
    """No move without evidence: of the similarity that takes the block `rec` onto the
    GNSS-only block `gnss_only` (their cameras of `image_ids`, about their centroid in `rec`),
    the parameters `alone` ((7,) bool, adjust.observability.DATUM: E, N, U shifts, scale,
    rotations about E, N, U) marks, those GNSS fixes and the planes and terrain do not
    (adjust.observability.left_to_gnss), are applied to `rec` (in place): along them the
    model gave the block no reason to move. Returns the applied (7,) parameters (m, relative
    scale change, rad) and the similarity applied (pycolmap.Sim3d)."""
    import pycolmap
    from scipy.spatial.transform import Rotation

    alone = np.asarray(alone, bool)
    applied = np.zeros(7)
    if gnss_only is None or not alone.any() or len(image_ids) < 3:
        return applied, pycolmap.Sim3d()
    here = np.array([rec.image(int(i)).projection_center() for i in image_ids])
    there = np.array([gnss_only.image(int(i)).projection_center() for i in image_ids])
    centre = here.mean(axis=0)
    found = pycolmap.estimate_sim3d(here - centre, there - centre)
    if found is None:
        return applied, pycolmap.Sim3d()
    rotation = Rotation.from_matrix(np.asarray(found.rotation.matrix())).as_rotvec()
    applied[:3] = np.where(alone[:3], np.asarray(found.translation, float), 0.0)
    applied[3] = float(found.scale) - 1.0 if alone[3] else 0.0
    applied[4:] = np.where(alone[4:], rotation, 0.0)
    turn = Rotation.from_rotvec(applied[4:]).as_matrix()
    scale = 1.0 + applied[3]
    moved = pycolmap.Sim3d(scale, pycolmap.Rotation3d(turn),
                           centre + applied[:3] - scale * turn @ centre)
    rec.transform(moved)
    logger.info("the planes leave %s to GNSS: the block moved back there (shift %s m, scale "
                "%+.2g, turn %s deg)", ", ".join(n for n, f in zip(DATUM_NAMES, alone) if f),
                np.round(applied[:3], 3).tolist(), applied[3],
                np.round(np.degrees(applied[4:]), 4).tolist())
    return applied, moved


#: The datum parameters in adjust.observability's order.
DATUM_NAMES = ("E", "N", "U", "scale", "rotation_E", "rotation_N", "rotation_U")
