"""What the model planes determine, and whether a refine result can be trusted.

`observability`: which of the 7 datum parameters (E, N, U shifts, scale, rotations about E, N,
U) the assigned planes fix, which GNSS fixes, and the a posteriori sigma of each. A plane's tie
points share its generalisation error (Unger 6.3: systematic, about 0.2 m), so a plane adds at
most about one observation of that size in its normal direction, however many points it holds;
the information of plane p is J^T (s^2 I + g^2 1 1^T)^-1 J (Sherman-Morrison below).

`quality_verdict`: compares the refined block with the GNSS-only adjustment of the same block.
"ok": the model fitted and moved the block no further than GNSS allows; "weak": usable but
with a stated doubt; "failed": refine hands back the GNSS-only result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..adjust.scale import scale_change
from ..assign.assignment import Assignment
from ..block.priors import GNSSPriors
from ..block.reconstruction import tie_points
from ..citymodel.store import PlaneStore
from ..options import RefineOptions

#: The datum parameters, in the order of the information matrices below.
DATUM = ("E", "N", "U", "scale", "rotation_E", "rotation_N", "rotation_U")
#: A datum direction counts as fixed by a source whose sigma alone is below this many times
#: the other's (else "both").
DOMINANCE = 3.0
#: Without either source, a sigma above these counts as "none": metres for shifts, relative
#: scale, radians.
UNDETERMINED = {"shift": 10.0, "scale": 0.1, "rotation": 0.1}


def _datum_jacobian(points: np.ndarray, directions: np.ndarray, centre: np.ndarray
                    ) -> np.ndarray:
    """d (direction . X') / d (shift, log scale, rotation) for X' = X + t + s y + w x y."""
    y = points - centre
    return np.hstack([directions, np.einsum("ij,ij->i", directions, y)[:, None],
                      np.cross(y, directions)])


def plane_information(points: np.ndarray, normals: np.ndarray, groups: np.ndarray,
                      centre: np.ndarray, sigma: float, sigma_generalisation: float
                      ) -> list[np.ndarray]:
    """7x7 information of the datum from the tie points of each plane (one group per plane)."""
    jac = _datum_jacobian(points, normals, centre)
    g2, s2 = sigma_generalisation ** 2, sigma ** 2
    out = []
    for group in np.unique(groups):
        j = jac[groups == group]
        total = j.sum(0)
        out.append(j.T @ j / s2 - np.outer(total, total) * g2 / (s2 * (s2 + len(j) * g2)))
    return out


def gnss_information(positions: np.ndarray, sigmas: np.ndarray, centre: np.ndarray
                     ) -> np.ndarray:
    info = np.zeros((7, 7))
    for axis in range(3):
        directions = np.zeros_like(positions)
        directions[:, axis] = 1.0
        jac = _datum_jacobian(positions, directions, centre) / sigmas[:, axis:axis + 1]
        info += jac.T @ jac
    return info


def _sigmas(info: np.ndarray) -> np.ndarray:
    """Marginal sigma per datum parameter; inf where the information leaves it free."""
    scale = np.sqrt(np.maximum(np.diag(info), 1e-30))
    normalised = info / np.outer(scale, scale)
    values, vectors = np.linalg.eigh(normalised)
    keep = values > 1e-9 * max(values.max(), 1e-30)
    inverse = (vectors[:, keep] / values[keep]) @ vectors[:, keep].T
    sigma = np.sqrt(np.maximum(np.diag(inverse), 0.0)) / scale
    # A direction with (almost) no information is free, whatever the pseudo-inverse says.
    free = vectors[:, ~keep]
    if free.size:
        sigma[np.abs(free).max(axis=1) > 0.1] = np.inf
    return sigma


def observability(points: np.ndarray, normals: np.ndarray, groups: np.ndarray,
                  gnss_positions: np.ndarray | None, gnss_sigmas: np.ndarray | None,
                  sigma_dtp: float, sigma_generalisation: float) -> dict:
    """Per datum parameter: the source that fixes it (planes, gnss, both, none) and its sigma
    (metres; relative for scale; degrees for rotations) from planes, GNSS and both."""
    # Shifts and their sigmas refer to the cameras' centroid (where GNSS observes), else to
    # the tie points': the position users care about, and rotations then do not leak into it.
    centre = (gnss_positions.mean(0) if gnss_positions is not None and len(gnss_positions)
              else points.mean(0))
    per_plane = (plane_information(points, normals, groups, centre, sigma_dtp,
                                   sigma_generalisation) if len(points) else [])
    planes = sum(per_plane, np.zeros((7, 7)))
    gnss = (gnss_information(gnss_positions, gnss_sigmas, centre)
            if gnss_positions is not None and len(gnss_positions) else np.zeros((7, 7)))
    # Our order is (shift, log scale, rotation); DATUM's is the same.
    s_planes, s_gnss, s_both = _sigmas(planes), _sigmas(gnss), _sigmas(planes + gnss)
    # A direction that only one plane fixes rests on that plane's assignment being right (one
    # roof among facades): it counts for the planes only if it survives leaving any one out
    # (judged with the other parameters held, so that two parallel facades, which together
    # also fix the scale, still count for their normal direction).
    diagonals = np.array([np.diag(planes - info) for info in per_plane]).reshape(-1, 7)
    s_robust = (1.0 / np.sqrt(np.maximum(diagonals.min(axis=0), 1e-30)) if len(per_plane) > 1
                else np.full(7, np.inf))
    out = {}
    for k, name in enumerate(DATUM):
        kind = "shift" if k < 3 else "scale" if k == 3 else "rotation"
        limit = UNDETERMINED[kind]
        g_ok = s_gnss[k] < limit
        p_ok = s_planes[k] < limit and s_robust[k] < (s_gnss[k] if g_ok else limit)
        if p_ok and (not g_ok or s_planes[k] * DOMINANCE < s_gnss[k]):
            source = "planes"
        elif g_ok and (not p_ok or s_gnss[k] * DOMINANCE < s_planes[k]):
            source = "gnss"
        elif p_ok and g_ok:
            source = "both"
        else:
            source = "none"
        factor = np.degrees(1.0) if kind == "rotation" else 1.0
        out[name] = {"source": source,
                     "one_plane": bool(s_planes[k] < limit and not p_ok),
                     "sigma": _finite(s_both[k] * factor),
                     "sigma_planes": _finite(s_planes[k] * factor),
                     "sigma_gnss": _finite(s_gnss[k] * factor)}
    return out


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def rests_on_one_plane(observability_dict: dict) -> list[str]:
    """The datum parameters that only a single plane fixes."""
    return [k for k, v in observability_dict.items() if v.get("one_plane")]


def planes_fix(observability_dict: dict) -> list[str]:
    """The datum parameters the planes fix alone or together with GNSS."""
    return [k for k, v in observability_dict.items() if v["source"] in ("planes", "both")]


# -- verdict ---------------------------------------------------------------------------------


@dataclass
class QualityThresholds:
    """Limits of the quality gate (one place)."""

    shift_ok: float = 3.0
    """Mean camera shift from the GNSS-only result, in GNSS sigmas (Mahalanobis over E, N, U),
    up to which the result is "ok": GNSS errors are mostly a bias common to the block, so its
    position is not known better than one GNSS sigma."""
    shift_failed: float = 4.5
    """Above this the model has pulled the block further than any plausible GNSS error."""
    scale_failed_sigmas: float = 5.0
    """Scale change from the GNSS-only result beyond this many of its GNSS sigmas: failed."""
    scale_gnss_sigmas: float = 3.0
    """The same where the planes do not determine the scale (observability): beyond this the
    model has bent the block against the only observation of its scale (a real drive past
    arcades: -5.6 %, 4.8 sigma, camera centres 0.24 -> 1.12 m)."""
    min_assigned_share: float = 0.02
    """Fewer tie points than this share on planes: the model does not fit the block."""
    min_near_share: float = 0.35
    """Share of tie points within `near_distance` of the model below which the fit is weak
    (simulated streets, drives, strips and orbits that fit: 0.6-0.9, with ground and clutter
    points; part of a model that fits only where it overlaps: 0.27)."""
    failed_near_share: float = 0.10
    """Below this share the model does not fit the block at all: failed."""
    near_distance: float = 0.5
    position_sigma_ok: float = 0.15
    """The a posteriori sigma (3D, m) of the block's position from planes and GNSS (each plane
    with its generalisation error, observability) up to which the result is "ok": the block
    is then on the model to the decimetre; above it, "weak" says how well it is."""
    wall_ok: float = 0.75
    """Share of the tie points on vertical planes of the cloud (walls: the model's surest part)
    that lie within `near_distance` of the model, below which the fit is weak (every simulated
    block that fits: 0.90-0.97)."""
    wall_failed: float = 0.5
    """Below this share most walls the images see are not the model's: it does not describe the
    block well enough to be its control; failed (a street model moved 30 m along the street:
    0.41; a real drive whose model holds the buildings of one side only, and arcades where
    the model has a facade: 0.38, refined 0.4-1.6 m against GNSS-only 0.24-0.47 m)."""
    dtp_rms_weak: float = 2.0
    """RMS point-to-plane distance above this many sigma_dTP: weak."""
    gnss_scatter_weak: float = 1.5
    """GNSS residuals (after removing their mean) that scatter more than this many of their
    stated sigmas and more than with GNSS only: the block was bent to the model against its
    GNSS; weak. (A scatter that only grows, within the stated sigmas, is normal: GNSS-only
    blocks follow their GNSS's slow bias, the model's corrected block exposes it.)"""


@dataclass
class QualityReport:
    verdict: str  # "ok" | "weak" | "failed"
    reasons: list[str] = field(default_factory=list)
    metrics: dict = field(default_factory=dict)

    def todict(self) -> dict:
        return {"verdict": self.verdict, "reasons": list(self.reasons), "metrics": self.metrics}

    def line(self) -> str:
        return f"quality: {self.verdict}" + (f" ({'; '.join(self.reasons)})" if self.reasons
                                             else "")


def gnss_scatter(observed: np.ndarray, positions: np.ndarray, sigmas: np.ndarray) -> float:
    """RMS of the normalised GNSS residuals after removing their mean (the block's shape
    against GNSS, free of the common bias)."""
    v = (observed - positions) / sigmas
    return float(np.sqrt(np.mean((v - v.mean(0)) ** 2)))


def quality_verdict(metrics: dict, thresholds: QualityThresholds | None = None
                    ) -> QualityReport:
    """Verdict from the figures refine measured (keys as written by workflow.measure_quality)."""
    t = thresholds or QualityThresholds()
    failed, weak = [], []
    fixed = metrics.get("planes_fix")
    if metrics.get("diverged"):
        weak.append(f"the assignment loop diverged ({metrics['diverged']}); its best iterate "
                    "is kept")
    if metrics["assigned_share"] < t.min_assigned_share:
        failed.append(f"only {100 * metrics['assigned_share']:.1f} % of the tie points lie on "
                      "model planes: the model does not fit the block")
    shift = metrics.get("shift_sigmas")
    if shift is not None:
        if shift > t.shift_failed:
            failed.append(f"the model moved the cameras {metrics['shift_m']:.1f} m "
                          f"({shift:.1f} GNSS sigma) from the GNSS-only result")
        elif shift > t.shift_ok:
            weak.append(f"the model moved the cameras {metrics['shift_m']:.1f} m "
                        f"({shift:.1f} GNSS sigma) from the GNSS-only result")
    scale = metrics.get("scale_change_sigmas")
    scale_by_gnss = fixed is not None and "scale" not in fixed
    if scale is not None and (scale > t.scale_failed_sigmas
                              or (scale_by_gnss and scale > t.scale_gnss_sigmas)):
        failed.append(f"the block's scale changed by {100 * metrics['scale_change']:.2f} % "
                      f"({scale:.1f} GNSS sigma)"
                      + (" although only GNSS determines it" if scale_by_gnss else ""))
    before, after = metrics.get("near_share_gnss_only"), metrics["near_share"]
    if before is not None and after < before:
        failed.append(f"fewer tie points near the model after refine ({100 * after:.0f} %) "
                      f"than with GNSS only ({100 * before:.0f} %)")
    elif after < t.failed_near_share:
        failed.append(f"only {100 * after:.0f} % of the tie points lie within "
                      f"{t.near_distance:g} m of the model: it does not fit the block")
    elif after < t.min_near_share:
        weak.append(f"only {100 * after:.0f} % of the tie points lie within "
                    f"{t.near_distance:g} m of the model")
    position = metrics.get("position_sigma_m")
    if position is not None and position > t.position_sigma_ok:
        weak.append(f"the planes and GNSS fix the block's position only to {position:.2f} m "
                    "(3D sigma, with the model's generalisation error)")
    walls = metrics.get("wall_near_share")
    if walls is not None and walls < t.wall_ok:
        (failed if walls < t.wall_failed else weak).append(
            f"only {100 * walls:.0f} % of the tie points on walls lie on the model's walls")
    if metrics.get("dtp_rms_sigmas", 0.0) > t.dtp_rms_weak:
        weak.append(f"tie points lie {metrics['dtp_rms_m']:.2f} m (RMS) from their planes")
    ratio, scatter = metrics.get("gnss_scatter_ratio"), metrics.get("gnss_scatter")
    if ratio is not None and ratio > 1.0 and scatter is not None \
            and scatter > t.gnss_scatter_weak:
        weak.append(f"the GNSS residuals scatter {scatter:.1f} of their sigmas, {ratio:.1f}x "
                    "more than with GNSS only")
    if fixed is not None:
        single = [k for k in metrics.get("one_plane", []) if k in ("E", "N", "U")]
        free = [k for k in ("E", "N", "U") if k not in fixed and k not in single]
        if free:
            weak.append(f"the model planes do not fix {', '.join(free)}: there the position "
                        "is GNSS's alone")
        if single:
            weak.append(f"{', '.join(single)} rest(s) on a single model plane, which nothing "
                        "checks (a wrong assignment there moves the block unseen)")
    verdict = "failed" if failed else "weak" if weak else "ok"
    return QualityReport(verdict, failed + weak, metrics)


def datum_line(observability_dict: dict) -> str:
    """'E planes (0.09 m), ..., U gnss (0.79 m), ...' for the log and the console."""
    parts = []
    for name, row in observability_dict.items():
        unit = " deg" if name.startswith("rotation") else "" if name == "scale" else " m"
        sigma = f" ({row['sigma']:.3g}{unit})" if row["sigma"] is not None else ""
        parts.append(f"{name} {row['source']}{sigma}")
    return ", ".join(parts)


def assigned_observability(points: np.ndarray, assignment: Assignment, store: PlaneStore,
                           priors: GNSSPriors | None, rec: pycolmap.Reconstruction,
                           options: RefineOptions) -> dict:
    """quality.observability for the assigned tie points and the GNSS of `rec`."""
    from ..options import GENERALISATION_SIGMA

    assigned = assignment.assigned
    faces = assignment.face_index[assigned]
    sigma_gen = options.adjustment.sigma_generalisation or GENERALISATION_SIGMA
    return observability(points[assigned], store.normals[faces], faces,
                         priors.observed_points(rec) if priors is not None else None,
                         priors.sigmas if priors is not None else None,
                         options.adjustment.sigma_dtp, sigma_gen)


def measure_quality(rec: pycolmap.Reconstruction, gnss_only: pycolmap.Reconstruction | None,
                    surface, priors: GNSSPriors | None, assignment: Assignment, last,
                    observability_dict: dict, points: np.ndarray, options: RefineOptions,
                    diverged: str | None, scale_sigma: float | None):
    """The figures of the quality gate (quality.quality_verdict) and the verdict; `points`
    are the refined tie points that could be assigned (check points left out)."""

    thresholds = QualityThresholds()
    metrics: dict = {
        "assigned_share": assignment.num_assigned / max(len(points), 1),
        "num_assigned_points": assignment.num_assigned, "num_planes": assignment.num_faces,
        "near_share": float(np.mean(surface(points) < thresholds.near_distance))
        if len(points) else 0.0,
        "near_share_gnss_only": None, "diverged": diverged,
        "planes_fix": planes_fix(observability_dict),
        "one_plane": rests_on_one_plane(observability_dict),
    }
    shift_sigmas = [observability_dict.get(k, {}).get("sigma") for k in ("E", "N", "U")]
    if all(v is not None for v in shift_sigmas):
        metrics["position_sigma_m"] = float(np.linalg.norm(shift_sigmas))
    normalised = last.residuals.get("dTP", np.zeros(0))
    if len(normalised):
        dtp = float(np.sqrt(np.mean(normalised ** 2)))
        metrics["dtp_rms_sigmas"] = float(dtp)
        metrics["dtp_rms_m"] = float(dtp) * options.adjustment.sigma_dtp
    from ..align.coarse import wall_points

    walls = wall_points(points) if len(points) else np.zeros((0, 3))
    metrics["num_wall_points"] = len(walls)
    if len(walls) >= options.assignment.min_points_per_plane:
        metrics["wall_near_share"] = float(np.mean(surface(walls) < thresholds.near_distance))
    if gnss_only is not None and priors is not None:
        _, before = tie_points(gnss_only)
        metrics["near_share_gnss_only"] = (float(np.mean(surface(before)
                                                         < thresholds.near_distance))
                                           if len(before) else 0.0)
        # Where GNSS observed: elsewhere (GNSS for part of the block) the GNSS-only result is
        # an extrapolation that the model is there to correct.
        ids = [int(i) for i in priors.image_ids]
        a = np.array([gnss_only.image(i).projection_center() for i in ids])
        b = np.array([rec.image(i).projection_center() for i in ids])
        sigma = np.median(priors.sigmas, axis=0)
        mean_shift = (b - a).mean(0)
        metrics["shift_m"] = float(np.linalg.norm(mean_shift))
        metrics["shift_enu_m"] = mean_shift.tolist()
        metrics["shift_sigmas"] = float(np.linalg.norm(mean_shift / sigma))
        if scale_sigma:
            change = scale_change(gnss_only, rec, ids)
            metrics["scale_change"] = change
            metrics["scale_change_sigmas"] = abs(np.log1p(change)) / scale_sigma
        before_scatter = gnss_scatter(priors.observed_points(gnss_only), priors.positions,
                                      priors.sigmas)
        after_scatter = gnss_scatter(priors.observed_points(rec), priors.positions,
                                     priors.sigmas)
        metrics["gnss_scatter"] = after_scatter
        metrics["gnss_scatter_ratio"] = after_scatter / max(before_scatter, 1e-9)
    return quality_verdict(metrics, thresholds)
