"""Initial georegistration of an SfM reconstruction (method.md section 4, Unger 3.2.5).

A robust 7-parameter similarity (Sim3: scale, rotation, translation) from the COLMAP camera
centres to the GNSS positions of the same images in the store's local frame (CRS minus origin),
estimated with pycolmap's LO-RANSAC (`pycolmap.estimate_sim3d_robust`) and refined by least
squares on the inliers. Where the camera centres with GNSS lie (nearly) on a line, GNSS fixes
the line, its scale and position, and the cameras' upright orientation the rotation about it
(`upright_line_similarity`), or where they look sideways the tie points' walls and level
planes (`level_about_line`). Without GNSS the user gives the transform
(`read_initial_transform`).

Sim3 convention (pycolmap.Sim3d, "tgt_from_src"): x_tgt = scale * R @ x_src + t.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np

from ..errors import GeoregistrationError, InputError

logger = logging.getLogger(__name__)


@dataclass
class GeoregistrationOptions:
    """Tolerances of the initial georegistration (one place)."""

    # RANSAC inlier distance (m) in the target frame; None: sigma_factor x the largest per-axis
    # median GNSS sigma (3 x 5 m = 15 m with the default sigmas 3, 3, 5 m). The largest axis is
    # used (not only the horizontal ones) so that true vertical errors of 2-3 sigma stay inliers.
    max_error: float | None = None
    sigma_factor: float = 3.0
    min_inliers: int = 3
    # Camera centres whose second principal extent is below this fraction of the first are
    # collinear: GNSS cannot fix the rotation about that line, the cameras' upright
    # orientation does (upright_line_similarity).
    min_noncollinearity: float = 1e-2
    # Centres that deviate from a line by less than the GNSS sigma: the 7-parameter fit is
    # kept while the GNSS scatter fixes the rotation about the line to this (deg), else the
    # cameras' upright orientation fixes it (upright_line_similarity).
    max_roll_sigma_deg: float = 5.0
    # The GNSS spread (largest principal std) must exceed this many GNSS sigmas.
    min_baseline_sigmas: float = 2.0
    random_seed: int = 0
    confidence: float = 0.9999
    max_num_trials: int = 100000


#: Datum cues of the 7-parameter fit to GNSS, and of the fit to a (nearly) straight line.
SIMILARITY_CUES = {"translation": "gnss", "scale": "gnss", "rotation": "gnss"}
LINE_CUES = {"translation": "gnss", "scale": "gnss", "heading_and_pitch": "gnss",
             "roll_about_line": "images (cameras upright)"}


@dataclass
class Georegistration:
    """Result: sim3 maps the reconstruction frame to the local (store) frame."""

    sim3: "pycolmap.Sim3d"  # noqa: F821
    inlier_mask: np.ndarray  # (K,) bool over the given image_ids
    residuals: np.ndarray  # (K,3) GNSS - sim3 * centre, metres in the target frame
    rms: float  # 3D RMS of the inlier residuals, metres
    image_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    max_error: float = float("nan")
    warnings: list[str] = field(default_factory=list)
    # Which observation fixed each datum parameter (the model may fix some of them later).
    cues: dict[str, str] = field(default_factory=lambda: dict(SIMILARITY_CUES))

    @property
    def num_inliers(self) -> int:
        return int(np.sum(self.inlier_mask))

    def todict(self) -> dict:
        return {
            "scale": float(self.sim3.scale),
            "rotation_xyzw": np.asarray(self.sim3.rotation.quat).tolist(),
            "translation": np.asarray(self.sim3.translation).reshape(3).tolist(),
            "matrix": np.asarray(self.sim3.matrix()).tolist(),
            "num_positions": int(len(self.inlier_mask)),
            "num_inliers": self.num_inliers,
            "rms_m": float(self.rms),
            "max_error_m": float(self.max_error),
            "outlier_image_ids": [int(i) for i in self.image_ids[~self.inlier_mask]],
            "warnings": list(self.warnings),
            "cues": dict(self.cues),
        }


def camera_centres(reconstruction, image_ids) -> np.ndarray:
    """(K,3) projection centres (world frame) of the given images (COLMAP 4:
    `Image.projection_center()`, which composes rig and frame poses)."""
    centres = np.empty((len(image_ids), 3), dtype=np.float64)
    for k, image_id in enumerate(image_ids):
        image = reconstruction.image(int(image_id))
        if not image.has_pose:
            raise GeoregistrationError(f"image {image.name!r} (id {image_id}) has no pose")
        centres[k] = image.projection_center()
    return centres


def _principal_std(points: np.ndarray) -> np.ndarray:
    centred = points - points.mean(axis=0)
    return np.linalg.svd(centred, compute_uv=False) / np.sqrt(max(len(points), 1))


def transform_points(sim3, points: np.ndarray) -> np.ndarray:
    """(N, 3) `points` mapped by the similarity `sim3`."""
    matrix = np.asarray(sim3.matrix())
    return points @ matrix[:, :3].T + matrix[:, 3]


def estimate_georegistration(
    reconstruction,
    gnss_positions_local,
    image_ids,
    *,
    sigmas=None,
    max_error: float | None = None,
    min_inliers: int = 3,
    options: GeoregistrationOptions | None = None,
) -> Georegistration:
    """Robust Sim3 from the camera centres of `image_ids` to `gnss_positions_local` (K,3).

    `sigmas` (K,3) GNSS sigmas set the default RANSAC threshold (see GeoregistrationOptions);
    without them the default sigmas 3, 3, 5 m are assumed. Centres on (or, for the GNSS
    noise, nearly on) a line take the rotation about it from the cameras (`cues` says so).
    Raises GeoregistrationError for fewer than 3 positions, coinciding centres, a GNSS spread
    within its noise, RANSAC failure or fewer than `min_inliers` inliers.
    """
    options = replace(options or GeoregistrationOptions())  # never alter the caller's options
    if max_error is not None:
        options.max_error = max_error
    min_inliers = max(3, int(min_inliers if min_inliers is not None else options.min_inliers))
    image_ids = np.asarray(image_ids, dtype=np.int64).reshape(-1)
    target = np.asarray(gnss_positions_local, dtype=np.float64).reshape(-1, 3)
    if len(target) != len(image_ids):
        raise ValueError("gnss_positions_local and image_ids differ in length")
    if len(target) < 3:
        raise GeoregistrationError(
            f"only {len(target)} GNSS position(s) for registered images; at least 3 "
            "non-collinear ones are needed for the 7-parameter transform"
        )
    sigmas = (np.tile([3.0, 3.0, 5.0], (len(target), 1)) if sigmas is None
              else np.asarray(sigmas, dtype=np.float64).reshape(-1, 3))
    source = camera_centres(reconstruction, image_ids)
    geometry = _Geometry.of(source, target, sigmas, options)
    line = partial(_along_the_line, reconstruction, image_ids, source, target, geometry.lateral)
    if geometry.spread_src[1] < options.min_noncollinearity * geometry.spread_src[0]:
        return line("collinear")
    threshold = (options.max_error if options.max_error is not None
                 else options.sigma_factor * float(geometry.sigma_axis.max()))
    sim3, inliers = _robust_similarity(source, target, threshold, min_inliers, options)
    residuals = target - transform_points(sim3, source)
    num = int(inliers.sum())
    rms = float(np.sqrt(np.mean(np.sum(residuals[inliers] ** 2, axis=1))))
    if num < len(target):
        worst = np.argsort(-np.linalg.norm(residuals, axis=1))[: min(5, len(target) - num)]
        names = [reconstruction.image(int(image_ids[i])).name for i in worst]
        logger.warning(
            "%d of %d GNSS positions rejected as outliers (> %.2f m), e.g. %s",
            len(target) - num, len(target), threshold, names,
        )
    roll_sigma = geometry.roll_sigma(target, residuals[inliers])
    if roll_sigma is not None and roll_sigma > options.max_roll_sigma_deg:
        return line(f"GNSS fixes the rotation about it to {roll_sigma:.0f} deg")
    logger.info(
        "Georegistration: scale %.6g, %d/%d inliers, RMS %.3f m", sim3.scale, num, len(target), rms
    )
    return Georegistration(sim3=sim3, inlier_mask=inliers, residuals=residuals, rms=rms,
                           image_ids=image_ids, max_error=float(threshold), warnings=[])


@dataclass
class _Geometry:
    """The camera centres' and GNSS positions' spread (principal standard deviations), GNSS's
    median sigma per axis and how far (m) the centres deviate from a line."""

    spread_src: np.ndarray
    sigma_axis: np.ndarray
    sigma_horizontal: float
    lateral: float

    @classmethod
    def of(cls, source: np.ndarray, target: np.ndarray, sigmas: np.ndarray,
           options: GeoregistrationOptions) -> "_Geometry":
        """The geometry checks: the reconstruction's centres are noise-free in their own
        frame, so collinearity is judged there; the baseline is judged against the GNSS
        noise (the main axis of a flight is horizontal: against the horizontal sigma)."""
        spread_src = _principal_std(source)
        if spread_src[0] <= 0:
            raise GeoregistrationError(
                f"the {len(source)} camera centres with GNSS coincide: no baseline for a "
                "similarity transform")
        sigma_axis = np.median(sigmas, axis=0)
        spread_tgt = _principal_std(target)
        sigma_horizontal = float(sigma_axis[:2].max())
        if spread_tgt[0] < options.min_baseline_sigmas * sigma_horizontal:
            raise GeoregistrationError(
                f"the GNSS positions spread only {spread_tgt[0]:.2f} m (std along the main "
                f"axis), not more than {options.min_baseline_sigmas:g} x their horizontal "
                f"sigma ({sigma_horizontal:.2f} m): not enough baseline for a similarity "
                "transform")
        lateral = spread_src[1] * spread_tgt[0] / spread_src[0]
        return cls(spread_src, sigma_axis, sigma_horizontal, float(lateral))

    def roll_sigma(self, target: np.ndarray, residuals: np.ndarray) -> float | None:
        """How well GNSS fixes the rotation about a nearly straight line (deg): its scatter
        across the line over the centres' deviation from it (what the data show, not the
        stated sigma: filtered GNSS scatters far less than it states); None where the
        centres deviate from a line by more than GNSS's horizontal sigma."""
        if self.lateral >= self.sigma_horizontal:
            return None
        direction = np.linalg.svd(target - target.mean(0))[2][0]
        across = residuals - np.outer(residuals @ direction, direction)
        scatter = float(np.sqrt(np.mean(np.sum(across ** 2, axis=1)) / 2))
        return float(np.degrees(scatter / (self.lateral * np.sqrt(len(residuals)))))


def _robust_similarity(source: np.ndarray, target: np.ndarray, threshold: float,
                       min_inliers: int, options: GeoregistrationOptions):
    """pycolmap's LO-RANSAC similarity from `source` to `target` within `threshold` (m), then
    least-squares refits on the inliers until they are stable: (Sim3d, inlier mask)."""
    import pycolmap

    ransac = pycolmap.RANSACOptions()
    ransac.max_error = float(threshold)
    ransac.confidence = options.confidence
    ransac.max_num_trials = options.max_num_trials
    ransac.random_seed = options.random_seed
    ransac.min_inlier_ratio = min(0.99, max(0.01, (min_inliers - 0.5) / len(target)))
    # pycolmap 4.2.1 returns {"tgt_from_src", "num_inliers", "inlier_mask"} or None (its
    # docstring says Sim3d | None); accept both.
    found = pycolmap.estimate_sim3d_robust(source, target, ransac)
    sim3 = found.get("tgt_from_src") if isinstance(found, dict) else found
    if sim3 is None:
        raise GeoregistrationError(
            f"RANSAC found no similarity transform from {len(target)} camera centres to GNSS "
            f"within {threshold:.2f} m"
        )
    inliers = np.linalg.norm(target - transform_points(sim3, source), axis=1) <= threshold
    for _ in range(3):
        # Least-squares refit on the inliers (deterministic), re-classify, until stable.
        if inliers.sum() < 3:
            break
        refit = pycolmap.estimate_sim3d(source[inliers], target[inliers])
        if refit is None:
            break
        new_inliers = np.linalg.norm(target - transform_points(refit, source), axis=1) <= threshold
        if new_inliers.sum() < inliers.sum():
            break
        stable = np.array_equal(new_inliers, inliers)
        sim3, inliers = refit, new_inliers
        if stable:
            break
    if int(inliers.sum()) < min_inliers:
        raise GeoregistrationError(
            f"only {int(inliers.sum())} of {len(target)} GNSS positions agree with a similarity "
            f"transform within {threshold:.2f} m (at least {min_inliers} needed)"
        )
    return sim3, inliers


def _along_the_line(reconstruction, image_ids, source: np.ndarray, target: np.ndarray,
                    lateral: float, reason: str) -> Georegistration:
    """GNSS fixes the line but not the rotation about it: that comes from the cameras, and
    where they look sideways, from the tie points' walls and level planes."""
    right, up = camera_axes(reconstruction, image_ids)
    sim3 = upright_line_similarity(source, target, right, up)
    sim3, levelled = level_about_line(sim3, reconstruction, source, right, up)
    residuals = target - transform_points(sim3, source)
    rms = float(np.sqrt(np.mean(np.sum(residuals ** 2, axis=1))))
    cues = dict(LINE_CUES)
    if levelled is not None:
        cues["roll_about_line"] = LEVEL_ROLL_CUE
    warning = (
        f"the camera centres with GNSS deviate only ~{lateral:.1f} m from a line ({reason}): "
        "the rotation about the flight line comes from "
        + ("the cameras' upright orientation" if levelled is None else
           f"the tie points' walls and level planes (turned {levelled:+.1f} deg from the "
           "cameras' upright orientation)")
        + " until the model planes fix it")
    logger.warning(warning)
    logger.info("Georegistration along a line: scale %.6g, RMS %.3f m", sim3.scale, rms)
    return Georegistration(sim3=sim3, inlier_mask=np.ones(len(target), bool),
                           residuals=residuals, rms=rms, image_ids=image_ids,
                           max_error=float("nan"), warnings=[warning], cues=cues)


def camera_axes(reconstruction, image_ids) -> tuple[np.ndarray, np.ndarray]:
    """(right, up) unit vectors (K,3) of the cameras in the reconstruction frame: the image x
    axis and the image -y axis (COLMAP: x right, y down)."""
    right = np.empty((len(image_ids), 3))
    up = np.empty((len(image_ids), 3))
    for k, image_id in enumerate(image_ids):
        rotation = np.asarray(reconstruction.image(int(image_id)).cam_from_world().rotation.matrix())
        right[k], up[k] = rotation[0], -rotation[1]
    return right, up


#: The cue of the rotation about a straight line when the tie points' planes fixed it.
LEVEL_ROLL_CUE = "images (tie point walls vertical, ground and flat roofs level)"
#: Cameras whose image x axes lie this close to across the line (mean |sin| of the angle
#: between x axis and line) look along it: their horizontal x axes hold the roll.
LOOKING_ALONG = 0.5
#: The tie points' planes must fit their orientations better by this much (share of plane
#: points) than at the cameras' roll for their roll to be taken.
MIN_LEVEL_GAIN = 0.05


def level_about_line(sim3, reconstruction, source: np.ndarray, right: np.ndarray,
                     up: np.ndarray):
    """`sim3` (from `upright_line_similarity`) turned about the flight line so that the tie
    points' planes are walls or level (align.coarse.level_roll), where the cameras look
    sideways: their image "up" holds the roll only to their tilt (with a UAV camera pitched
    35 deg down, the block's walls can end 35 deg off the vertical). Cameras looking along the
    line keep their roll (their horizontal x axes fix it to a fraction of a degree). `source`: the
    camera centres, `right`, `up`: their axes (`camera_axes`), in the reconstruction's frame.
    Returns (the similarity, the roll added in degrees or None where none was)."""
    import pycolmap

    from ..block.reconstruction import tie_points
    from .coarse import level_roll

    rotation = np.asarray(sim3.rotation.matrix())
    view = np.cross(right, -up)  # the image z axis: x right, y down
    right, up, view = right @ rotation.T, up @ rotation.T, view @ rotation.T
    centres = transform_points(sim3, source)
    centre = centres.mean(axis=0)
    axis = np.linalg.svd(centres - centre)[2][0]
    if float(np.mean(np.linalg.norm(np.cross(right, axis), axis=1))) > LOOKING_ALONG:
        return sim3, None
    _, points = tie_points(reconstruction)
    if not len(points):
        return sim3, None
    roll = level_roll(transform_points(sim3, points), axis, centre, up, view)
    if roll is None or roll.score < roll.score_at_zero + MIN_LEVEL_GAIN:
        return sim3, None
    turn = roll.rotation
    levelled = pycolmap.Sim3d(1.0, pycolmap.Rotation3d(turn), centre - turn @ centre) * sim3
    return levelled, float(np.degrees(roll.angle))


def upright_line_similarity(source: np.ndarray, target: np.ndarray, right: np.ndarray,
                            up: np.ndarray) -> "pycolmap.Sim3d":  # noqa: F821
    """Similarity from (nearly) collinear camera centres `source` to GNSS `target`.

    Scale, translation and the line's direction come from GNSS; the rotation about the line
    from the cameras: a camera held upright has a horizontal x axis (a strong cue when the
    cameras look along the line, as from a vehicle) and its image "up" (-y) above the horizon
    (the only cue for cameras looking sideways: it is off by their tilt, which the model then
    fixes).
    """
    import pycolmap

    cs, ct = source.mean(0), target.mean(0)
    ds = np.linalg.svd(source - cs)[2][0]
    dt = np.linalg.svd(target - ct)[2][0]
    ps, pt = (source - cs) @ ds, (target - ct) @ dt
    if ps @ pt < 0:
        dt, pt = -dt, -pt
    scale = float(ps @ pt / (ps @ ps))
    # Unit vectors orthogonal to the line, in the source frame; the vertical is among them.
    e1 = np.linalg.svd(np.eye(3) - np.outer(ds, ds))[0][:, 0]
    e1 -= (e1 @ ds) * ds
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(ds, e1)
    angles = np.radians(np.arange(0.0, 360.0, 0.25))
    verticals = np.cos(angles)[:, None] * e1 + np.sin(angles)[:, None] * e2
    cost = np.mean((right @ verticals.T) ** 2, axis=0) - 0.1 * np.mean(up @ verticals.T, axis=0)
    vs = verticals[int(np.argmin(cost))]
    vt = np.array([0.0, 0.0, 1.0]) - dt[2] * dt
    if np.linalg.norm(vt) < 1e-6:  # a vertical line: any horizontal reference
        vt = np.array([1.0, 0.0, 0.0]) - dt[0] * dt
    vt /= np.linalg.norm(vt)
    frame_src = np.column_stack([ds, vs, np.cross(ds, vs)])
    frame_tgt = np.column_stack([dt, vt, np.cross(dt, vt)])
    rotation = frame_tgt @ frame_src.T
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), ct - scale * rotation @ cs)


def apply_sim3(reconstruction, sim3) -> None:
    """Transform the reconstruction in place (all frames/images and points): new_from_old."""
    reconstruction.transform(sim3)


def sim3_to_local(sim3, origin):
    """A Sim3 mapping input -> model CRS turned into input -> local (CRS minus origin)."""
    import pycolmap

    matrix = np.array(sim3.matrix(), dtype=np.float64)
    matrix[:, 3] -= np.asarray(origin, dtype=np.float64).reshape(3)
    return pycolmap.Sim3d(matrix)


def _sim3_from_matrix(matrix: np.ndarray, path) -> "pycolmap.Sim3d":  # noqa: F821
    import pycolmap

    from ..citymodel.raw_model import MAX_PROJECTED_COORDINATE

    min_scale = 1e-8  # input frame units per metre: beyond 1e8 either way is a damaged number

    matrix = np.asarray(matrix, dtype=np.float64)
    if matrix.shape == (4, 4):
        if not np.allclose(matrix[3], [0, 0, 0, 1], atol=1e-9):
            raise InputError("the last row of the 4x4 transform must be 0 0 0 1", path)
        matrix = matrix[:3]
    if matrix.shape != (3, 4) or not np.all(np.isfinite(matrix)):
        raise InputError("the transform must be a finite 4x4 (or 3x4) matrix", path)
    if np.abs(matrix[:, 3]).max() > MAX_PROJECTED_COORDINATE:
        raise InputError(f"the transform's translation {matrix[:, 3].tolist()} lies beyond "
                         f"{MAX_PROJECTED_COORDINATE:.0e} m, outside any projected CRS", path)
    linear = matrix[:, :3]
    if np.abs(linear).max() > 1.0 / min_scale:
        raise InputError(f"the transform's 3x3 part holds {np.abs(linear).max():.6g}, beyond "
                         f"any scale x rotation (scale at most {1 / min_scale:.0e})", path)
    with np.errstate(over="ignore", invalid="ignore"):
        det = np.linalg.det(linear)
    if not det > 0:
        raise InputError("the transform's 3x3 part has a non-positive determinant", path)
    scale = det ** (1.0 / 3.0)
    if not min_scale <= scale <= 1.0 / min_scale:
        raise InputError(f"the transform's scale {scale:.6g} is not plausible (it must lie "
                         f"between {min_scale:.0e} and {1 / min_scale:.0e})", path)
    rotation = linear / scale
    if not np.allclose(rotation.T @ rotation, np.eye(3), atol=1e-6):
        raise InputError(
            "the transform's 3x3 part is not scale x rotation (a similarity is required)", path
        )
    u, _, vt = np.linalg.svd(rotation)  # re-orthonormalise what was written with few digits
    rotation = u @ vt
    return pycolmap.Sim3d(np.column_stack([scale * rotation, matrix[:, 3]]))


def read_initial_transform(path) -> "pycolmap.Sim3d":  # noqa: F821
    """Read a user-given similarity mapping the INPUT reconstruction frame to MODEL CRS
    coordinates (unshifted; use sim3_to_local(sim3, store.origin) for the local frame).

    Formats:
    - text: a 4x4 matrix [scale*R | t; 0 0 0 1] (or 3x4), whitespace/comma separated, `#` comments;
    - JSON: {"scale": s, "rotation": [qw, qx, qy, qz] or a 3x3 matrix, "translation": [tx, ty, tz]}
      or {"matrix": 4x4}.
    Malformed files raise InputError naming the file.
    """
    import pycolmap

    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"cannot read transform file: {error}", path) from None
    stripped = text.strip()
    if stripped.startswith("{"):
        try:
            data = json.loads(stripped)
        except json.JSONDecodeError as error:
            raise InputError(f"invalid JSON: {error}", path) from None
        if "matrix" in data:
            return _sim3_from_matrix(_as_array(data["matrix"], path, "matrix"), path)
        missing = [k for k in ("scale", "rotation", "translation") if k not in data]
        if missing:
            raise InputError(f"JSON transform lacks {missing}", path)
        try:
            scale = float(data["scale"])
        except (TypeError, ValueError, OverflowError):
            raise InputError("'scale' must be a number", path) from None
        if not np.isfinite(scale) or scale <= 0:
            raise InputError("'scale' must be positive", path)
        rotation = _as_array(data["rotation"], path, "rotation")
        if not np.all(np.isfinite(rotation)):
            raise InputError("'rotation' holds a value that is not finite", path)
        if rotation.shape == (4,):
            if np.abs(rotation).max() > 0:  # scaled first: the squares of 1e200 overflow
                rotation = rotation / np.abs(rotation).max()
            norm = np.linalg.norm(rotation)
            if norm < 1e-9:
                raise InputError("'rotation' quaternion is zero", path)
            qw, qx, qy, qz = rotation / norm
            rotation = pycolmap.Rotation3d(np.array([qx, qy, qz, qw])).matrix()
        elif rotation.shape != (3, 3):
            raise InputError("'rotation' must be [qw, qx, qy, qz] or a 3x3 matrix", path)
        translation = _as_array(data["translation"], path, "translation")
        if translation.shape != (3,):
            raise InputError("'translation' must have 3 numbers", path)
        return _sim3_from_matrix(np.column_stack([scale * rotation, translation]), path)
    rows = []
    for number, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].replace(",", " ").strip()
        if not content:
            continue
        try:
            rows.append([float(v) for v in content.split()])
        except ValueError:
            raise InputError(f"line {number}: not a number in {content!r}", path) from None
    if len(rows) not in (3, 4) or any(len(r) != 4 for r in rows):
        raise InputError(
            f"expected a 4x4 matrix (4 rows of 4 numbers), got {len(rows)} row(s) of "
            f"{sorted({len(r) for r in rows})} numbers",
            path,
        )
    return _sim3_from_matrix(np.array(rows), path)


def _as_array(value, path, key) -> np.ndarray:
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"'{key}' must contain numbers", path) from None
