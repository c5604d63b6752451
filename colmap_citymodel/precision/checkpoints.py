"""Check point evaluation (method.md section 7; Unger 5.1.3, eq. 10-11, Tables 10, 11, 15).

Check points (CPs) are targets with known coordinates in the model CRS, observed in the images.
They are triangulated with the evaluated poses and cameras (linear DLT, then Gauss-Newton on the
ray residuals), compared with the known coordinates (error = known - estimated), and a 7-parameter
Helmert transform (rotation centre at the centroid of the estimated CPs) separates the datum error
(shift, rotation, scale of the whole block) from the block deformation (RMS after the transform).

File formats (whitespace separated, `#` comments):
- check points:   ``id X Y Z``              (model CRS, unshifted)
- observations:   ``image_name id x y``     (pixels, COLMAP convention: the centre of the
  upper-left pixel is (0.5, 0.5), as in COLMAP's points2D)

Helmert convention: known = c + T + (1 + m) R (estimated - c), c = centroid of the estimated CPs,
R = R_x(omega) R_y(phi) R_z(kappa), m = scale_ppm * 1e-6.

Delta/sigma (Unger 6.3, Tables 12/13): when the a posteriori covariance of the check points is
known (refine computes it, precision.checkpoint_cofactors, and writes
`checkpoint_precision.json`), the table compares per axis the RMS of Delta = known - estimated
with the RMS of sigma_CP, before and after the Helmert transform. As in Unger's Table 13 the
ratio after Helmert divides by the same sigma_CP; beside it, `rms_sigma_residual` is the sigma
of the Helmert residuals themselves (the joint covariance propagated through the residual
projector I - A (A^T A)^-1 A^T of the linearised similarity), the fair yardstick for Delta after
Helmert when sigma_CP is dominated by the datum.
"""

from __future__ import annotations

import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import content_lines
from .accuracy import accuracy_markdown, check_accuracy, read_check_marks
from .quality import QualityThresholds

logger = logging.getLogger(__name__)

MIN_VIEWS = 2
GN_ITERATIONS = 20
AXES = ("X", "Y", "Z")
#: File refine writes next to the model: ids, check points and their joint covariance.
CHECKPOINT_PRECISION_FILE = "checkpoint_precision.json"


# --------------------------------------------------------------------------------------------
# Files


def _lines(path: Path):
    return ((number, content.split()) for number, content in content_lines(path))


def _floats(values, number, path) -> list[float]:
    try:
        out = [float(v) for v in values]
    except ValueError:
        raise InputError(f"line {number}: not a number in {' '.join(values)!r}", path) from None
    if not all(math.isfinite(v) for v in out):
        raise InputError(f"line {number}: non-finite value", path)
    return out


def read_checkpoints(path) -> dict[str, np.ndarray]:
    """``id X Y Z`` lines -> {id: (3,) float64} in the model CRS."""
    path = Path(path)
    points: dict[str, np.ndarray] = {}
    for number, parts in _lines(path):
        if len(parts) != 4:
            raise InputError(f"line {number}: expected 'id X Y Z', got {len(parts)} fields", path)
        if parts[0] in points:
            raise InputError(f"line {number}: check point {parts[0]!r} given twice", path)
        points[parts[0]] = np.array(_floats(parts[1:], number, path))
    if not points:
        raise InputError("no check points in file", path)
    return points


def read_checkpoint_observations(path) -> list[tuple[str, str, float, float]]:
    """``image_name id x y`` lines -> [(image_name, id, x, y)] (pixels, COLMAP convention)."""
    path = Path(path)
    observations = []
    for number, parts in _lines(path):
        if len(parts) != 4:
            raise InputError(
                f"line {number}: expected 'image_name id x y', got {len(parts)} fields", path
            )
        x, y = _floats(parts[2:], number, path)
        observations.append((parts[0], parts[1], x, y))
    if not observations:
        raise InputError("no check point observations in file", path)
    return observations


# --------------------------------------------------------------------------------------------
# Triangulation


@dataclass
class _View:
    rotation: np.ndarray  # (3,3) cam_from_world
    translation: np.ndarray  # (3,) in the shifted world frame
    ray: np.ndarray  # (3,) unit bearing in the camera frame
    focal: float  # pixels, scales ray residuals to ~pixels


def _tangent_basis(ray: np.ndarray) -> np.ndarray:
    """(3,2) orthonormal basis of the plane perpendicular to `ray`."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(ray[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(ray, helper)
    e1 /= np.linalg.norm(e1)
    return np.column_stack([e1, np.cross(ray, e1)])


def _triangulate(views: list[_View]) -> tuple[np.ndarray, float] | None:
    """Linear DLT (cross(ray, R X + t) = 0) then Gauss-Newton on the tangent-plane residuals.
    Returns (X in the shifted frame, RMS residual in ~pixels) or None (degenerate/behind)."""
    rows = []
    for v in views:
        skew = np.array([[0, -v.ray[2], v.ray[1]], [v.ray[2], 0, -v.ray[0]],
                         [-v.ray[1], v.ray[0], 0]])
        rows.append(skew @ np.column_stack([v.rotation, v.translation]))
    _, singular, vt = np.linalg.svd(np.vstack(rows))
    homogeneous = vt[-1]
    if abs(homogeneous[3]) < 1e-12 * np.linalg.norm(homogeneous):
        return None
    x = homogeneous[:3] / homogeneous[3]
    bases = [_tangent_basis(v.ray) for v in views]

    def residuals_and_jacobian(point):
        res, jac = [], []
        for v, basis in zip(views, bases):
            p = v.rotation @ point + v.translation
            norm = np.linalg.norm(p)
            u = p / norm
            res.append(v.focal * (basis.T @ u))
            jac.append(v.focal * basis.T @ ((np.eye(3) - np.outer(u, u)) / norm) @ v.rotation)
        return np.concatenate(res), np.vstack(jac)

    for _ in range(GN_ITERATIONS):
        r, j = residuals_and_jacobian(x)
        try:
            step = np.linalg.lstsq(j, -r, rcond=None)[0]
        except np.linalg.LinAlgError:
            return None
        x = x + step
        if np.linalg.norm(step) <= 1e-14 * max(1.0, np.linalg.norm(x)):
            break
    for v in views:  # cheirality: in front of (the ray side of) every camera
        if np.dot(v.rotation @ x + v.translation, v.ray) <= 0:
            return None
    r, _ = residuals_and_jacobian(x)
    return x, float(np.sqrt(np.mean(r**2)))


@dataclass
class TriangulationInfo:
    num_views: dict[str, int] = field(default_factory=dict)
    rms_px: dict[str, float] = field(default_factory=dict)
    failed: list[str] = field(default_factory=list)  # fewer than 2 views or degenerate
    unknown_images: list[str] = field(default_factory=list)
    shift: np.ndarray = field(default_factory=lambda: np.zeros(3))


def triangulate_checkpoints(
    reconstruction,
    observations,
    *,
    min_views: int = MIN_VIEWS,
    info: TriangulationInfo | None = None,
) -> dict[str, np.ndarray]:
    """Triangulate each check point from its observations with the reconstruction's poses and
    cameras (any COLMAP camera model: `camera.cam_ray_from_img` unprojects pixels).

    Works in a frame shifted by the mean of the observing cameras' centres so that models in CRS
    coordinates (millions of metres) lose no precision; the result is in the reconstruction's
    frame. Observations in unknown or unregistered images are ignored; points with fewer than
    `min_views` views or a degenerate geometry are left out (listed in `info.failed`).
    """
    info = info if info is not None else TriangulationInfo()
    by_name = {image.name: image for image in reconstruction.images.values()}
    grouped: dict[str, list[tuple[object, float, float]]] = {}
    unknown = set()
    for name, point_id, x, y in observations:
        image = by_name.get(name)
        if image is None or not image.has_pose:
            unknown.add(name)
            continue
        grouped.setdefault(point_id, []).append((image, x, y))
    info.unknown_images = sorted(unknown)
    if unknown:
        logger.warning("%d image(s) with check point observations are not registered in the "
                       "model, e.g. %s", len(unknown), info.unknown_images[:3])
    used_images = {image.image_id: image for obs in grouped.values() for image, _, _ in obs}
    centres = {i: image.projection_center() for i, image in used_images.items()}
    shift = np.mean(list(centres.values()), axis=0) if centres else np.zeros(3)
    info.shift = shift
    poses = {}
    for i, image in used_images.items():
        rotation = image.cam_from_world().rotation.matrix()
        poses[i] = (rotation, -rotation @ (centres[i] - shift))

    result: dict[str, np.ndarray] = {}
    for point_id in sorted(grouped):
        views = []
        for image, x, y in grouped[point_id]:
            camera = image.camera
            ray = camera.cam_ray_from_img(np.array([[x, y]], dtype=np.float64))
            ray = np.asarray(ray, dtype=np.float64).reshape(-1)
            if ray.size != 3 or not np.all(np.isfinite(ray)):
                continue
            rotation, translation = poses[image.image_id]
            views.append(_View(rotation, translation, ray / np.linalg.norm(ray),
                               float(camera.mean_focal_length())))
        info.num_views[point_id] = len(views)
        solved = _triangulate(views) if len(views) >= min_views else None
        if solved is None:
            info.failed.append(point_id)
            continue
        result[point_id] = solved[0] + shift
        info.rms_px[point_id] = solved[1]
    if info.failed:
        logger.warning("%d check point(s) could not be triangulated (< %d views or degenerate): %s",
                       len(info.failed), min_views, info.failed[:5])
    return result


# --------------------------------------------------------------------------------------------
# Helmert transform and statistics


def _rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(values**2))) if values.size else float("nan")


@dataclass
class HelmertResult:
    """known ~= centre + translation + scale * rotation @ (estimated - centre)."""

    translation: np.ndarray  # (3,) tx, ty, tz (m)
    rotation: np.ndarray  # (3,3)
    scale: float
    centre: np.ndarray  # (3,) centroid of the estimated points (rotation centre)
    residuals: np.ndarray  # (N,3) known - transformed estimated

    @property
    def angles_deg(self) -> np.ndarray:
        """omega, phi, kappa (degrees) with rotation = R_x(omega) R_y(phi) R_z(kappa)."""
        from scipy.spatial.transform import Rotation

        return Rotation.from_matrix(self.rotation).as_euler("XYZ", degrees=True)

    @property
    def scale_ppm(self) -> float:
        return (self.scale - 1.0) * 1e6

    @property
    def rms_axes(self) -> np.ndarray:
        return np.sqrt(np.mean(self.residuals**2, axis=0))

    @property
    def rms_3d(self) -> float:
        return float(np.sqrt(np.sum(self.rms_axes**2)))

    def apply(self, points) -> np.ndarray:
        points = np.asarray(points, dtype=np.float64)
        return self.centre + self.translation + self.scale * (points - self.centre) @ self.rotation.T

    def todict(self) -> dict:
        omega, phi, kappa = self.angles_deg
        return {
            "tx": float(self.translation[0]),
            "ty": float(self.translation[1]),
            "tz": float(self.translation[2]),
            "omega_deg": float(omega),
            "phi_deg": float(phi),
            "kappa_deg": float(kappa),
            "scale_ppm": float(self.scale_ppm),
            "rms_3d_after": self.rms_3d,
        }


def helmert_transform(known, estimated) -> HelmertResult:
    """7-parameter similarity (Umeyama/Horn closed form, least squares) taking `estimated`
    onto `known` (both (N,3), N >= 3, not collinear); rotation centre = centroid of `estimated`."""
    known = np.asarray(known, dtype=np.float64).reshape(-1, 3)
    estimated = np.asarray(estimated, dtype=np.float64).reshape(-1, 3)
    if len(known) != len(estimated) or len(known) < 3:
        raise ValueError("the Helmert transform needs at least 3 point pairs")
    centre = estimated.mean(axis=0)
    mean_known = known.mean(axis=0)
    a = estimated - centre
    b = known - mean_known
    covariance = b.T @ a / len(a)
    u, singular, vt = np.linalg.svd(covariance)
    variance = np.mean(np.sum(a**2, axis=1))
    if variance <= 0 or singular[1] <= 1e-12 * max(singular[0], 1e-300):
        raise ValueError("the Helmert transform needs non-collinear points")
    d = np.eye(3)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        d[2, 2] = -1.0
    rotation = u @ d @ vt
    scale = float(np.trace(np.diag(singular) @ d) / variance)
    translation = mean_known - centre
    result = HelmertResult(translation, rotation, scale, centre, np.zeros_like(known))
    result.residuals = known - result.apply(estimated)
    return result


def helmert_design_matrix(points) -> np.ndarray:
    """(3N, 7) derivative of the similarity c + T + (1 + m) R(w) (p - c) at T = w = m = 0 w.r.t.
    (T, w, m), c = centroid of `points`: the directions a Helmert transform removes."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    q = points - points.mean(axis=0)
    a = np.zeros((3 * len(q), 7))
    for i, (x, y, z) in enumerate(q):
        rows = slice(3 * i, 3 * i + 3)
        a[rows, :3] = np.eye(3)
        a[rows, 3:6] = [[0.0, z, -y], [-z, 0.0, x], [y, -x, 0.0]]  # d(w x q)/dw = -[q]x
        a[rows, 6] = (x, y, z)
    return a


def helmert_residual_sigmas(points, covariance) -> np.ndarray:
    """(N, 3) sigma of the residuals after a least-squares Helmert transform of `points`
    (joint covariance (3N, 3N); the known coordinates taken as exact): the diagonal of
    (I - P) C (I - P), P = A (A^T A)^-1 A^T the projector onto the similarity directions."""
    a = helmert_design_matrix(points)
    projector = np.eye(len(a)) - a @ np.linalg.solve(a.T @ a, a.T)
    residual = projector @ np.asarray(covariance, dtype=np.float64) @ projector.T
    return np.sqrt(np.maximum(np.diagonal(residual), 0.0)).reshape(-1, 3)


def _axis_rows(delta: np.ndarray, sigma: np.ndarray, sigma_residual: np.ndarray | None = None
               ) -> dict:
    out = {}
    for k, axis in enumerate(AXES):
        rms_delta, rms_sigma = _rms(delta[:, k]), _rms(sigma[:, k])
        row = {"rms_delta": rms_delta, "rms_sigma": rms_sigma,
               "ratio": rms_delta / rms_sigma if rms_sigma > 0 else float("nan")}
        if sigma_residual is not None:
            rms_residual = _rms(sigma_residual[:, k])
            row["rms_sigma_residual"] = rms_residual
            row["ratio_residual"] = (rms_delta / rms_residual if rms_residual > 0
                                     else float("nan"))
        out[axis] = row
    return out


def delta_sigma_table(errors, sigmas, errors_after_helmert=None, covariance=None,
                      estimated=None) -> dict:
    """Unger Tables 12/13 per axis: RMS of Delta, RMS of sigma_CP and their ratio, before and
    (if `errors_after_helmert`) after the Helmert transform, with the same sigma_CP; with the
    joint `covariance` and the `estimated` points also the sigma of the Helmert residuals."""
    errors = np.asarray(errors, dtype=np.float64).reshape(-1, 3)
    sigmas = np.asarray(sigmas, dtype=np.float64).reshape(-1, 3)
    table = {"num_checkpoints": int(len(errors)), "before_helmert": _axis_rows(errors, sigmas)}
    if errors_after_helmert is not None:
        residual = None
        if covariance is not None and estimated is not None and len(errors) >= 3:
            residual = helmert_residual_sigmas(estimated, covariance)
        table["after_helmert"] = _axis_rows(np.asarray(errors_after_helmert).reshape(-1, 3),
                                            sigmas, residual)
    return table


def format_delta_sigma(table: dict, title: str = "") -> str:
    """The table as markdown (one row per stage, columns per axis like Unger 12/13)."""
    lines = []
    if title:
        lines += [title, ""]
    head = "| | " + " | ".join(f"RMS Delta {a} (m)" for a in AXES) + " | " + " | ".join(
        f"RMS sigma {a} (m)" for a in AXES) + " | " + " | ".join(
        f"Delta/sigma {a}" for a in AXES) + " |"
    lines += [head, "|" + "---|" * 10]
    for stage, label in (("before_helmert", "before Helmert"), ("after_helmert", "after Helmert")):
        rows = table.get(stage)
        if not rows:
            continue
        lines.append(f"| {label} | " + " | ".join(f"{rows[a]['rms_delta']:.3f}" for a in AXES)
                     + " | " + " | ".join(f"{rows[a]['rms_sigma']:.4f}" for a in AXES) + " | "
                     + " | ".join(f"{rows[a]['ratio']:.2f}" for a in AXES) + " |")
        if "rms_sigma_residual" in rows[AXES[0]]:
            lines.append("| after Helmert, sigma of the residuals | " + " | ".join(
                f"{rows[a]['rms_delta']:.3f}" for a in AXES) + " | " + " | ".join(
                f"{rows[a]['rms_sigma_residual']:.4f}" for a in AXES) + " | " + " | ".join(
                f"{rows[a]['ratio_residual']:.2f}" for a in AXES) + " |")
    return "\n".join(lines) + "\n"


@dataclass
class CheckpointEvaluation:
    ids: list[str]
    known: np.ndarray  # (N,3) model CRS
    estimated: np.ndarray  # (N,3) model CRS
    errors: np.ndarray  # (N,3) known - estimated
    helmert: HelmertResult | None
    num_views: dict[str, int]
    missing: list[str]  # check points with observations that could not be triangulated
    frame: str  # "crs" or "local": the frame the evaluated model was in
    rms_px: dict[str, float] = field(default_factory=dict)
    covariances: dict[str, np.ndarray] = field(default_factory=dict)
    """Per stochastic model ("classical", "generalisation_aware"): the (3N, 3N) joint a
    posteriori covariance of the estimated check points in `ids` order (NaN for check points
    without one), from the adjustment (refine)."""
    sigma_notes: dict[str, str] = field(default_factory=dict)
    # The check marks' accuracy figures (precision.accuracy.check_accuracy: per mark, RMSE,
    # ASPRS, the chi-square test, blunders), merged into `todict`; None for other check points.
    accuracy: dict | None = None

    @property
    def covariance(self) -> np.ndarray | None:
        """The first attached covariance (the classical one when refine attached both)."""
        return next(iter(self.covariances.values()), None)

    def sigmas_of(self, model: str | None = None) -> np.ndarray | None:
        """(N, 3) a posteriori sigma X, Y, Z (m) of the check points under `model`."""
        covariance = self.covariance if model is None else self.covariances.get(model)
        if covariance is None:
            return None
        return np.sqrt(np.maximum(np.diagonal(covariance), 0.0)).reshape(-1, 3)

    @property
    def sigmas(self) -> np.ndarray | None:
        return self.sigmas_of()

    @property
    def primary_model(self) -> str | None:
        """The stochastic model whose sigma is `points[id]["sigma"]` and `delta_sigma` in
        `todict`: the generalisation-aware one when attached (the honest one), else the first."""
        if "generalisation_aware" in self.covariances:
            return "generalisation_aware"
        return next(iter(self.covariances), None)

    def attach_covariance(self, ids, covariance, note: str = "", model: str = "classical"
                          ) -> int:
        """Take the joint covariance of check points `ids` (3N, 3N) for the ones evaluated here;
        returns how many evaluated check points got one (the rest get NaN)."""
        ids = [str(i) for i in ids]
        covariance = np.asarray(covariance, dtype=np.float64).reshape(3 * len(ids), 3 * len(ids))
        where = {pid: k for k, pid in enumerate(ids)}
        index = np.full(3 * len(self.ids), -1, np.int64)
        for k, pid in enumerate(self.ids):
            if pid in where:
                index[3 * k:3 * k + 3] = 3 * where[pid] + np.arange(3)
        out = np.full((len(index), len(index)), np.nan)
        known = index >= 0
        out[np.ix_(known, known)] = covariance[np.ix_(index[known], index[known])]
        self.covariances[model] = out
        self.sigma_notes[model] = note
        return int(np.count_nonzero(known) // 3)

    def delta_sigma(self, model: str | None = None) -> dict | None:
        """Unger Tables 12/13 for the check points that have a covariance under `model`
        (default: the first attached), see `delta_sigma_table`."""
        model = model or next(iter(self.covariances), None)
        covariance = self.covariances.get(model) if model else None
        if covariance is None:
            return None
        have = np.isfinite(np.diagonal(covariance).reshape(-1, 3)).all(axis=1)
        if not have.any():
            return None
        rows = np.repeat(have, 3)
        after = None
        if self.helmert is not None:
            after = self.helmert.residuals[have]
        table = delta_sigma_table(self.errors[have], self.sigmas_of(model)[have], after,
                                  covariance[np.ix_(rows, rows)], self.estimated[have])
        table["model"] = model
        table["sigma_note"] = self.sigma_notes.get(model, "")
        return table

    @property
    def rms_axes(self) -> np.ndarray:
        return np.sqrt(np.mean(self.errors**2, axis=0)) if len(self.ids) else np.full(3, np.nan)

    @property
    def rms_3d(self) -> float:
        return float(np.sqrt(np.sum(self.rms_axes**2)))

    @property
    def rms_3d_after_helmert(self) -> float:
        return self.helmert.rms_3d if self.helmert is not None else float("nan")

    def todict(self) -> dict:
        rx, ry, rz = (float(v) for v in self.rms_axes)
        return {
            "num_checkpoints": len(self.ids),
            "rms_x": rx,
            "rms_y": ry,
            "rms_z": rz,
            "rms_3d": self.rms_3d,
            "rms_3d_after_helmert": self.rms_3d_after_helmert,
            "helmert": None if self.helmert is None else self.helmert.todict(),
            "frame": self.frame,
            "missing": list(self.missing),
            "points": {
                pid: {
                    "error": [float(v) for v in err],
                    "views": int(self.num_views.get(pid, 0)),
                    "rms_px": float(self.rms_px.get(pid, float("nan"))),
                    **({} if not self.covariances else
                       {"sigma": [float(v) for v in self.sigmas_of(self.primary_model)[k]]}),
                    **({f"sigma_{m}": [float(v) for v in self.sigmas_of(m)[k]]
                        for m in self.covariances}),
                }
                for k, (pid, err) in enumerate(zip(self.ids, self.errors))
            },
            **({} if not self.covariances else {
                "sigma_model": self.primary_model,
                "delta_sigma": self.delta_sigma(self.primary_model),
                "delta_sigma_by_model": {m: self.delta_sigma(m) for m in self.covariances}}),
            **(self.accuracy or {}),
        }

    def summary(self) -> str:
        rx, ry, rz = self.rms_axes
        lines = [
            f"check points: {len(self.ids)} evaluated ({self.frame} frame), "
            f"{len(self.missing)} not triangulated",
            f"RMS X {rx:.3f} m  Y {ry:.3f} m  Z {rz:.3f} m  3D {self.rms_3d:.3f} m",
        ]
        if self.helmert is not None:
            h = self.helmert.todict()
            lines.append(
                "Helmert: t = ({tx:.3f}, {ty:.3f}, {tz:.3f}) m, omega {omega_deg:.4f} deg, "
                "phi {phi_deg:.4f} deg, kappa {kappa_deg:.4f} deg, scale {scale_ppm:.1f} ppm".format(
                    **h)
            )
            lines.append(f"RMS 3D after Helmert {self.rms_3d_after_helmert:.3f} m")
        for model in self.covariances:
            table = self.delta_sigma(model)
            if table is not None:
                lines.append(format_delta_sigma(
                    table, f"Delta/sigma of {table['num_checkpoints']} check points, {model} "
                           f"stochastic model (Unger Tables 12/13; "
                           f"{table['sigma_note'] or 'sigma from the adjustment'}):").rstrip())
        if self.accuracy is not None:
            lines.append(accuracy_markdown(self.accuracy).strip())
        return "\n".join(lines)


def evaluate_checkpoints(
    reconstruction,
    checkpoints: dict[str, np.ndarray],
    observations,
    origin=None,
    *,
    frame: str = "auto",
    min_views: int = MIN_VIEWS,
) -> CheckpointEvaluation:
    """Triangulate the check points in `reconstruction` and compare with `checkpoints` (model CRS).

    `frame`: "crs" (the model is in CRS coordinates), "local" (CRS minus `origin`) or "auto"
    (without an origin: crs; with one: whichever of the two puts the triangulated points closer
    to the known ones, by the median distance).
    """
    if frame not in ("auto", "crs", "local"):
        raise ValueError("frame must be auto, crs or local")
    origin = None if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    if frame == "local" and origin is None:
        raise InputError("the evaluated model is in a local frame but no origin was given")
    info = TriangulationInfo()
    triangulated = triangulate_checkpoints(reconstruction, observations, min_views=min_views,
                                           info=info)
    ids = [pid for pid in sorted(triangulated) if pid in checkpoints]
    unknown_ids = sorted(set(triangulated) - set(checkpoints))
    if unknown_ids:
        logger.warning("%d observed check point id(s) have no known coordinates, e.g. %s",
                       len(unknown_ids), unknown_ids[:5])
    known = np.array([checkpoints[pid] for pid in ids]).reshape(-1, 3)
    raw = np.array([triangulated[pid] for pid in ids]).reshape(-1, 3)
    offset = np.zeros(3)
    chosen = "crs"
    if frame == "local" or (frame == "auto" and origin is not None and len(ids)):
        if frame == "local":
            chosen, offset = "local", origin
        else:
            d_crs = np.median(np.linalg.norm(known - raw, axis=1))
            d_local = np.median(np.linalg.norm(known - raw - origin, axis=1))
            if d_local < d_crs:
                chosen, offset = "local", origin
    estimated = raw + offset
    errors = known - estimated
    helmert = None
    if len(ids) >= 3:
        try:
            helmert = helmert_transform(known, estimated)
        except ValueError as error:
            logger.warning("no Helmert transform: %s", error)
    missing = sorted(pid for pid in info.failed if pid in checkpoints)
    return CheckpointEvaluation(
        ids=ids,
        known=known,
        estimated=estimated,
        errors=errors,
        helmert=helmert,
        num_views=dict(info.num_views),
        missing=missing,
        frame=chosen,
        rms_px=dict(info.rms_px),
    )


def evaluate_with_precision(reconstruction, checkpoints: dict[str, np.ndarray], observations,
                            origin, precision) -> CheckpointEvaluation:
    """refine's check point evaluation: Delta in its local frame (CRS minus `origin`) and the
    check points' joint covariance from `precision` (precision.PrecisionResult), if it has one."""
    evaluation = evaluate_checkpoints(reconstruction, checkpoints, observations, origin,
                                      frame="local")
    if precision is not None and len(precision.checkpoint_ids):
        if precision.generalisation != "estimated":
            evaluation.attach_covariance(precision.checkpoint_ids, precision.checkpoint_cov,
                                         CHECKPOINT_SIGMA_NOTE, "classical")
        if precision.generalisation != "none":
            evaluation.attach_covariance(
                precision.checkpoint_ids, precision.aware("checkpoint_cov"),
                GENERALISATION_NOTE[precision.generalisation].format(
                    sigma=precision.generalisation_sigma), "generalisation_aware")
    return evaluation


#: What the check point sigmas of refine are.
CHECKPOINT_SIGMA_NOTE = (
    "marginal a posteriori sigma (all poses, planes, vertices and the datum uncertain; the "
    "check points' image observations in the normal system, never on planes, never control), "
    "scaled by s0^2 of the adjustment")
GENERALISATION_NOTE = {
    "consider": "the classical sigma plus per-plane generalisation offsets "
                "o_p ~ N(0, {sigma:.3f}^2 m^2) and tilts (vertices that far off) shared by "
                "each plane's f_dTP, propagated into the estimate (consider parameters)",
    "estimated": "per-plane generalisation offsets estimated with the prior "
                 "N(0, {sigma:.3f}^2 m^2); marginal sigma scaled by s0^2",
}


def write_checkpoint_precision(path, evaluation: CheckpointEvaluation) -> None:
    """`checkpoint_precision.json`: ids, estimated points (model CRS), the joint covariance
    (3N x 3N, m^2; null where unknown) and what it is."""
    if not evaluation.covariances:
        raise ValueError("the evaluation has no check point covariance")
    Path(path).write_text(json.dumps({
        "ids": list(evaluation.ids),
        "points": evaluation.estimated.tolist(),
        "covariance": {m: np.where(np.isfinite(c), c, None).tolist()
                       for m, c in evaluation.covariances.items()},
        "note": dict(evaluation.sigma_notes), "units": "m (model CRS), m^2"}))


def read_checkpoint_precision(path) -> tuple[list[str], dict[str, np.ndarray], dict[str, str]]:
    """ids, joint covariances per stochastic model ((3N, 3N) each) and notes from
    `checkpoint_precision.json`."""
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        ids = [str(i) for i in data["ids"]]
        given = data["covariance"]
        if not isinstance(given, dict):  # one matrix: a single (classical) model
            given = {"classical": given}
        covariances = {
            str(m): np.array([[np.nan if v is None else v for v in row] for row in rows],
                             dtype=np.float64).reshape(3 * len(ids), 3 * len(ids))
            for m, rows in given.items()}
        notes = data.get("note") or {}
        if not isinstance(notes, dict):
            notes = {m: notes for m in covariances}
        notes = {str(m): str(n) for m, n in notes.items()}
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, KeyError, TypeError,
            ValueError, AttributeError) as error:
        raise InputError(f"not a usable check point precision file: {error}", path) from None
    return ids, covariances, notes


# --------------------------------------------------------------------------------------------
# Entry point


def _read_reconstruction(path: Path):
    from ..block.colmap_files import read_model

    if not path.is_dir():
        raise InputError("COLMAP model directory does not exist", path)
    if not any((path / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
        raise InputError("not a COLMAP model directory (no cameras.bin or cameras.txt)", path)
    return read_model(path)  # checks the files first: damage gets a message naming the file


def _read_origin(path: Path) -> tuple[np.ndarray, str | None]:
    """Origin (and the recorded output frame) from georeference.json or a text '<x> <y> <z>'."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as error:
        raise InputError(f"cannot read origin file: {error}", path) from None
    if text.lstrip().startswith("{"):
        try:
            data = json.loads(text)
            origin = np.asarray(data["origin"], dtype=np.float64).reshape(3)
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as error:
            raise InputError(f"no usable 'origin' in JSON: {error}", path) from None
        return origin, data.get("output_frame")
    try:
        # '#' starts a comment on any line (simulate writes truth/origin.txt with a header).
        values = [float(v) for line in text.splitlines() for v in line.split("#", 1)[0].split()]
    except ValueError:
        raise InputError("origin file must hold three numbers", path) from None
    if len(values) != 3:
        raise InputError("origin file must hold three numbers", path)
    return np.array(values), None


def _find_truth(input_path: Path) -> Path | None:
    for truth in (input_path.parent / "truth", input_path.parent.parent / "truth"):
        if not truth.is_dir():
            continue
        for candidate in (truth, truth / "sparse", truth / "0", truth / "sparse" / "0"):
            if any((candidate / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
                return candidate
    return None


def main(
    input_path,
    checkpoints,
    observations=None,
    *,
    origin_file=None,
    frame: str = "auto",
    as_json: bool = False,
    truth_path=None,
    precision_file=None,
    crs=None,
    sigma=None,
) -> dict:
    """Evaluate the COLMAP model in `input_path` on check points; print a summary (or JSON).

    The model may be in CRS coordinates (georeferenced output) or local (CRS minus an origin
    from `origin_file` or `input_path/georeference.json`). When a simulated workspace's `truth/`
    is found next to the model (DIR/../truth or DIR/../../truth, or `truth_path`), the truth
    poses are evaluated the same way. With the check points' covariance (`precision_file`, or
    `input_path/checkpoint_precision.json` written by refine --checkpoints) the Delta/sigma
    table of Unger Tables 12/13 is added. Without `observations`, `checkpoints` is a
    gcp_list.txt of check marks (block.marks) in any CRS, converted into the model's (`crs`,
    else the one georeference.json records) with `sigma` (H, V m) where its lines give none,
    and the marks' accuracy figures are added (precision.accuracy).
    Returns {"evaluated": {...}, "truth": {...} | None}.
    """
    input_path = Path(input_path)
    reconstruction = _read_reconstruction(input_path)
    origin, recorded_frame = None, None
    if origin_file is None and (input_path / "georeference.json").is_file():
        origin_file = input_path / "georeference.json"
    if origin_file is not None:
        origin, recorded_frame = _read_origin(Path(origin_file))
    marks = (read_check_marks(checkpoints, crs, origin_file, sigma) if observations is None
             else None)
    known, obs = (marks.checkpoints() if marks is not None else
                  (read_checkpoints(checkpoints), read_checkpoint_observations(observations)))
    if frame == "auto" and recorded_frame in ("crs", "local"):
        frame = recorded_frame
    evaluation = evaluate_checkpoints(reconstruction, known, obs, origin, frame=frame)
    if not evaluation.ids:
        raise InputError("no check point could be triangulated in the model (no shared ids, "
                         "unknown image names or fewer than 2 views each)",
                         Path(observations if observations is not None else checkpoints))
    if precision_file is None and (input_path / CHECKPOINT_PRECISION_FILE).is_file():
        precision_file = input_path / CHECKPOINT_PRECISION_FILE
    if precision_file is not None:
        # Sigmas of the adjustment that produced the model (refine --checkpoints ...); they
        # belong to the same triangulation with the same poses as the Delta computed here.
        ids, covariances, notes = read_checkpoint_precision(precision_file)
        for model, covariance in covariances.items():
            evaluation.attach_covariance(ids, covariance, notes.get(model, ""), model)
    if marks is not None:  # the check marks' accuracy figures, and their coordinates to plot
        evaluation.accuracy = check_accuracy(evaluation, marks, QualityThresholds().alpha,
                                             reconstruction=reconstruction)
    out = {"evaluated": evaluation.todict(), "truth": None,
           **({"known": {k: v.tolist() for k, v in known.items()}} if marks else {})}
    truth_dir = Path(truth_path) if truth_path is not None else _find_truth(input_path)
    truth_eval = None
    if truth_dir is not None:
        truth_rec = _read_reconstruction(truth_dir)
        truth_origin = origin
        if (truth_dir / "georeference.json").is_file():
            truth_origin, _ = _read_origin(truth_dir / "georeference.json")
        truth_eval = evaluate_checkpoints(truth_rec, known, obs, truth_origin, frame="auto")
        out["truth"] = truth_eval.todict()
        out["truth_path"] = str(truth_dir)
    if as_json:
        print(json.dumps(out, indent=2))
    else:
        print(f"model: {input_path}")
        print(evaluation.summary())
        if truth_eval is not None:
            print(f"truth poses: {truth_dir}")
            print(truth_eval.summary())
    return out
