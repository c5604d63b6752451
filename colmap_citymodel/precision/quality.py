"""Whether a refine result can be trusted: a verdict from the stated sigmas and from tests with
stated false-alarm rates (docs/verdict.md gives each rule in one sentence).

failed (refine hands back the GNSS-only block):
- the model does not fit the block: fewer than `min_support` of the tie points lie near its
  buildings (those only the terrain carries left out), or
  the faces' generalisation sigma estimated from their offsets, or the tie points' scatter on
  their faces, is significantly above its tolerance band (chi-square, level `alpha`);
- model and GNSS contradict each other: the shift between the GNSS-only and the refined block,
  against the covariance of both (GNSS with a bias as large as its stated sigma, planes with
  their generalisation), is significant (chi-square, level `alpha`);
- the placement is ambiguous: a distinct placement that GNSS admits fits the tie points nearly
  as well as the best one (ratio below `ambiguity_ratio`), on the city model's faces (the
  terrain, level round the block, fits every shift alike);
- the block lands on another height: a height GNSS admits fits the tie points significantly
  better than the refined one (paired test, level `alpha`).
weak: a direction rests on GNSS alone, the radius that holds the stated position error with
`tolerance_confidence` exceeds the user's tolerance, or the
assign/adjust loop stopped moving the block by more than that sigma (diverged or unsettled),
or would still have moved it along E, N or U by more than that direction's sigma
(adjust.record.remaining_move; the stated sigma includes that move,
adjust.observability.unsettled_observability), or weighting the faces as units moved it
further from where every tie point alike placed it than that sigma
(adjust.observability.weighting_observability).
ok: otherwise.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pycolmap
from scipy import stats

from ..adjust.observability import (DATUM, REGULARISATION, FaceFit, common_shift_eliminated,
                                    face_fit, face_tilts,
                                    plane_information, planes_fix, rests_on_one_plane)
from ..assign.assignment import Assignment
from ..block.priors import GNSSPriors
from ..block.reconstruction import tie_points
from ..options import GENERALISATION_SIGMA, RefineOptions
from .ambiguity import height_fit, placement_fit

logger = logging.getLogger(__name__)


@dataclass
class QualityThresholds:
    """The verdict's constants (one place): a significance level, a tolerance band and a
    ratio; the user's position tolerance is `PrecisionOptions.tolerance`."""

    alpha: float = 0.001
    """Significance level of each test (model fit, model against GNSS, another height): a block
    whose model and GNSS are as their error models state fails a test with this probability."""
    fit_band: float = 2.5
    """Tolerance band of the model's fit: the faces' generalisation sigma may be this many
    times the a priori one (0.2 m, or sigma_generalisation) and the tie points' scatter on their
    faces this many times sigma_dtp before the model counts as not fitting the block."""
    ambiguity_ratio: float = 1.1
    """The best placement must fit the tie points (share within NEAR_DISTANCE of the model's
    faces, the terrain left out) this many times better than the best distinct placement GNSS
    admits; else the pose is ambiguous. A block slid along a facade row that only walls
    parallel to the slide hold scores about 1; one that cross walls and corners confirm, well
    above."""
    tolerance_confidence: float = 0.95
    """Probability with which an "ok" block lies within the user's tolerance: the radius that
    holds the position error with this probability (from the stated E, N, U sigmas) must not
    exceed the tolerance."""
    min_support: float = 0.25
    """Share of the block's tie points (those only the terrain carries left out) within
    NEAR_DISTANCE of the model's buildings below which the model does not fit the block: the
    model of the buildings the images see carries most of their tie points, clutter aside; a
    model of another street only the few that happen to lie near one of its faces."""


#: Distance (m) within which a tie point counts as near the model: 2.5 sigma_dTP of a LOD2
#: model (0.2 m).
NEAR_DISTANCE = 0.5
#: Metres from the best placement beyond which another counts as distinct (a neighbouring
#: house, the next facade bay): four times NEAR_DISTANCE, beyond the best one's own peak.
DISTINCT = 4 * NEAR_DISTANCE


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


# -- the tests -------------------------------------------------------------------------------

def chi2_exceeds(value: float, dof: int, alpha: float) -> bool:
    """value beyond the (1 - alpha) quantile of chi-square with `dof` degrees of freedom."""
    return dof > 0 and value > float(stats.chi2.ppf(1.0 - alpha, dof))


def fit_statistics(fit: FaceFit, prior_generalisation: float, sigma_dtp: float,
                   band: float) -> dict:
    """The model-fit test's figures: the faces' offsets (outlier faces left out, and named)
    against a generalisation sigma `band` x `prior_generalisation` (chi-square, faces - 7
    degrees of freedom); the tie points' robust scatter on their faces against `band` x
    `sigma_dtp` (chi-square, points - faces degrees of freedom). Terrain faces left out."""
    keep = ~np.isin(fit.faces, fit.outlier_faces)
    if fit.terrain is not None:  # the terrain's own error is not the model's generalisation
        keep &= ~fit.terrain
    noise = fit.sigma_point ** 2 / np.maximum(fit.counts, 1)
    limit = band * prior_generalisation
    faces_dof = int(keep.sum()) - 7
    points_dof = int(np.sum(fit.counts)) - fit.num_faces
    return {
        **fit.todict(),
        "faces_chi2": float(np.sum(fit.offsets[keep] ** 2 / (limit ** 2 + noise[keep]))),
        "faces_dof": faces_dof,
        "sigma_generalisation_limit_m": limit,
        "points_chi2": float(points_dof * (fit.sigma_point / (band * sigma_dtp)) ** 2),
        "points_dof": points_dof, "sigma_point_limit_m": band * sigma_dtp,
    }


def fit_reasons(fit: dict, alpha: float) -> list[str]:
    """Why the model does not fit the block (empty: it does, at level alpha)."""
    out = []
    if fit["faces_dof"] > 0 and chi2_exceeds(fit["faces_chi2"], fit["faces_dof"], alpha):
        out.append(f"the model does not fit the block: its faces are off by "
                   f"{fit['sigma_generalisation_m']:.2f} m (sigma of {fit['num_faces']} faces), "
                   f"beyond the {fit['sigma_generalisation_limit_m']:.2f} m a generalised model "
                   f"may be (test at {alpha:g})")
    if fit["points_dof"] > 0 and chi2_exceeds(fit["points_chi2"], fit["points_dof"], alpha):
        out.append(f"the model does not fit the block: the tie points scatter "
                   f"{fit['sigma_point_m']:.2f} m about their faces, beyond "
                   f"{fit['sigma_point_limit_m']:.2f} m")
    return out


def contradiction(shift: np.ndarray, covariance: np.ndarray, alpha: float) -> dict:
    """The shift (3,) between the GNSS-only and the refined block against its covariance
    (3x3; infinite variance along what neither fixes): chi-square statistic, degrees of
    freedom (the directions with finite variance), p-value."""
    finite = np.isfinite(np.diag(covariance)) & (np.diag(covariance) > 0)
    d = np.asarray(shift, float)[finite]
    c = covariance[np.ix_(finite, finite)]
    value = float(d @ np.linalg.solve(c, d)) if len(d) else 0.0
    dof = int(finite.sum())
    return {"chi2": value, "dof": dof,
            "p": float(stats.chi2.sf(value, dof)) if dof else 1.0,
            "significant": chi2_exceeds(value, dof, alpha)}


def shift_test(shift: np.ndarray, gnss: np.ndarray, planes: np.ndarray, alpha: float) -> dict:
    """No move without evidence: the datum difference (`datum_difference`, (7,); or its
    shifts alone, (3,)) between the GNSS-only and the refined block, tested along every
    parameter GNSS holds. Where the planes and terrain fix it (`planes` finite there) the two
    blocks may differ by both errors (covariance gnss + planes); where they leave it free, the
    refined block has no evidence to move by, and the difference there is tested against
    GNSS's own covariance: a move GNSS does not explain is a contradiction, never a test with
    fewer degrees of freedom. `unfixed`: those parameters."""
    free = ~(np.isfinite(np.diag(planes)))
    held = np.where(np.outer(free, free) | free[:, None] | free[None, :], 0.0, planes)
    out = contradiction(shift, gnss + held, alpha)
    out["unfixed"] = [name for name, f in zip(DATUM, free) if f]
    return out


def confidence_radius(sigmas, probability: float) -> float:
    """The radius (m) that holds a 3D position error with independent normal components of
    `sigmas` (E, N, U) with `probability`: the quantile of their squared sum, a weighted sum
    of chi-square variables, by Satterthwaite's scaled chi-square of the same mean and
    variance (exact where the sigmas are equal or one dominates)."""
    variances = np.square(np.asarray(sigmas, dtype=np.float64))
    total = float(np.sum(variances))
    if total <= 0:
        return 0.0
    scale = float(np.sum(variances ** 2)) / total
    dof = total / scale
    return float(np.sqrt(scale * stats.chi2.ppf(probability, dof)))


def quality_verdict(metrics: dict, thresholds: QualityThresholds | None = None,
                    tolerance: float = 0.25) -> QualityReport:
    """Verdict from the figures refine measured (keys as written by measure_quality); each
    test runs only where its figures are present."""
    t = thresholds or QualityThresholds()
    failed, weak = [], []
    support = metrics.get("near_share")
    if support is not None and support < t.min_support:
        failed.append(f"the model does not fit the block: only {100 * support:.0f} % of the tie "
                      f"points off the ground lie within {NEAR_DISTANCE:g} m of its buildings")
    if metrics.get("fit"):
        failed += fit_reasons(metrics["fit"], t.alpha)
    test = metrics.get("gnss_test")
    if test and test["significant"]:
        unfixed = test.get("unfixed") or []
        along = (f"; along {', '.join(unfixed)} no model plane fixes the block, so there "
                 "nothing explains a move" if unfixed else "")
        failed.append(f"the model moved the block {np.linalg.norm(metrics['shift_enu_m']):.1f} m "
                      f"from where GNSS puts it, more than both error models allow "
                      f"(chi-square {test['chi2']:.1f}, {test['dof']} dof, p {test['p']:.1e}"
                      f"{along}): the model is not the one of these images, or the GNSS is "
                      "further off than its stated sigma (then give its sigmas in the GNSS "
                      "file, or --gnss_bias auto where the planes fix the position)")
    placement = metrics.get("placement")
    if placement and placement.get("ratio") is not None \
            and placement["ratio"] < t.ambiguity_ratio:
        shift = placement["alternative_shift_m"]
        failed.append(f"the placement is ambiguous: shifted by {shift[0]:+.1f} / {shift[1]:+.1f} "
                      f"m (E / N) the tie points fit the model nearly as well (ratio "
                      f"{placement['ratio']:.2f} < {t.ambiguity_ratio:g})")
    height = metrics.get("height_placement")
    if height and height["p"] < t.alpha:
        up = height["other_shift_m"]
        failed.append(f"the block lands on another height: moved {abs(up):.1f} m "
                      f"{'up' if up > 0 else 'down'}, the tie points fit the model's faces "
                      f"significantly better (share "
                      f"{height['other_share']:.2f} against {height['here_share']:.2f}, "
                      f"p {height['p']:.1e})")
    weak += moved_reasons(metrics)
    free = [axis for axis in metrics.get("gnss_alone") or []
            if axis not in (metrics.get("unsettled_axes") or {})]
    if free:
        weak.append(f"only GNSS fixes {', '.join(free)}: there the position is as good as "
                    "GNSS's")
    sigma = metrics.get("position_sigma_m")
    axes = metrics.get("position_sigmas_m")
    radius = (confidence_radius(axes, t.tolerance_confidence) if axes is not None
              else sigma)
    if radius is not None and radius > tolerance:
        # Centimetres, or millimetres where centimetres would round to the tolerance itself.
        shown = f"{radius:.2f}" if round(radius, 2) > tolerance else f"{radius:.3f}"
        weak.append(f"the block lies within {shown} m of its stated position with "
                    f"{100 * t.tolerance_confidence:g} % probability (3D sigma {sigma:.2f} m), "
                    f"more than the tolerance {tolerance:g} m")
    if metrics.get("diverged"):
        weak.append(f"the assignment loop diverged ({metrics['diverged']}); its best iterate "
                    "is kept")
    unsettled = metrics.get("unsettled_shift_m")
    if unsettled is not None and sigma is not None and unsettled > sigma:
        weak.append(f"the assignment loop had not settled after {metrics['loop_iterations']} "
                    f"iterations: the last moved the cameras by up to {unsettled:.2f} m, more "
                    "than the stated sigma")
    verdict = "failed" if failed else "weak" if weak else "ok"
    return QualityReport(verdict, failed + weak, metrics)


def moved_reasons(metrics: dict) -> list[str]:
    """The directions whose stated sigma holds a move of the block the error model does not
    (measure_quality's `unsettled_axes`, `weighting_axes`), each a reason for "weak"."""
    reasons = []
    unsettled_axes = metrics.get("unsettled_axes") or {}
    if unsettled_axes:
        moves = ", ".join(f"{row['move_m']:.2f} m along {axis} (its sigma without that "
                          f"{row['sigma_settled_m']:.2f} m)"
                          for axis, row in unsettled_axes.items())
        reasons.append(f"the assignment loop had not settled after "
                       f"{metrics['loop_iterations']} iterations: it would still have moved "
                       f"the block by about {moves}; the stated sigma there includes that move")
    weighting_axes = metrics.get("weighting_axes") or {}
    if weighting_axes:
        moves = ", ".join(f"{row['move_m']:.2f} m along {axis} (its sigma {row['sigma_m']:.2f} m)"
                          for axis, row in weighting_axes.items())
        reasons.append("the faces' errors as unknowns moved the block by "
                       f"{moves} from where every tie point alike placed it: the model's faces "
                       "err there in a way their error model does not describe, and the stated "
                       "sigma is at least that move")
    return reasons


# -- the figures -----------------------------------------------------------------------------

def gnss_alone(observability_dict: dict) -> list[str]:
    """E, N, U that only GNSS fixes: source "gnss" and no single plane holding them."""
    return [axis for axis in ("E", "N", "U")
            if observability_dict.get(axis, {}).get("source") in ("gnss", "none")
            and not observability_dict.get(axis, {}).get("one_plane")]


def datum_covariances(points: np.ndarray, faces: np.ndarray, store, fit: FaceFit,
                      priors: GNSSPriors, rec: pycolmap.Reconstruction,
                      options: RefineOptions) -> tuple[np.ndarray, np.ndarray]:
    """7x7 covariances of the block's datum (E, N, U shifts, log scale, rotations about the
    cameras' centroid) from GNSS alone, under its error model (white noise, the bias common to
    the block, the slowly varying part: errormodel.gnss), and from the planes alone (each face
    with the estimated generalisation, outlier faces out, the model's common error); inf on the
    diagonal where one leaves a parameter free."""
    from ..errormodel.model import gnss_model

    positions = priors.observed_points(rec)
    centre = positions.mean(0)
    gnss = gnss_model(priors, positions, options.adjustment).datum_information(positions,
                                                                               centre)
    keep = ~np.isin(faces, fit.outlier_faces)
    planes = np.zeros((7, 7))
    if keep.any():
        planes = sum(plane_information(
            points[keep], store.normals[faces[keep]], faces[keep], centre,
            options.adjustment.sigma_dtp, fit.sigma_generalisation,
            face_tilts(store, faces[keep], fit.sigma_generalisation)), np.zeros((7, 7)))
    planes = common_shift_eliminated(planes, options.adjustment.sigma_model_datum)
    return _covariance(gnss), _covariance(planes)


def _covariance(info: np.ndarray) -> np.ndarray:
    """The covariance of a 7x7 datum information (inverted as adjust.observability's sigmas
    are, with its weak regularising priors); inf where the information leaves a parameter
    (nearly) free."""
    regularised = info + np.diag(1.0 / REGULARISATION ** 2)
    scale = np.sqrt(np.diag(regularised))
    values, vectors = np.linalg.eigh(regularised / np.outer(scale, scale))
    covariance = ((vectors / np.maximum(values, 1e-300)) @ vectors.T
                  / np.outer(scale, scale))
    free = np.diag(covariance) > (0.5 * REGULARISATION) ** 2
    covariance[free, :] = covariance[:, free] = 0.0
    covariance[free, free] = np.inf
    return covariance


def datum_difference(gnss_only: pycolmap.Reconstruction, rec: pycolmap.Reconstruction,
                     priors: GNSSPriors) -> np.ndarray:
    """(7,) how the refined block's datum differs from the GNSS-only block's: the similarity
    between their cameras with GNSS about its centroid (shift m, log scale, rotation vector
    rad), less an estimated GNSS offset the user asked for (another height system, a bias); a
    bias estimated as a random effect is what the test's GNSS covariance allows for."""
    from scipy.spatial.transform import Rotation

    ids = [int(i) for i in priors.image_ids]
    a = np.array([gnss_only.image(i).projection_center() for i in ids])
    b = np.array([rec.image(i).projection_center() for i in ids])
    out = np.zeros(7)
    out[:3] = (b - a).mean(0) - (0.0 if priors.bias_is_random else priors.offset)
    found = pycolmap.estimate_sim3d(a - a.mean(0), b - b.mean(0)) if len(ids) >= 3 else None
    if found is not None:
        out[3] = float(np.log(found.scale))
        out[4:] = Rotation.from_matrix(np.asarray(found.rotation.matrix())).as_rotvec()
    return out


def measure_quality(rec: pycolmap.Reconstruction, gnss_only: pycolmap.Reconstruction | None,
                    surface, priors: GNSSPriors | None, assignment: Assignment, last,
                    observability_dict: dict, points: np.ndarray, options: RefineOptions,
                    diverged: str | None, scale_sigma: float | None,
                    unsettled_shift: float | None = None, *, store=None) -> QualityReport:
    """The figures of the verdict (quality_verdict) and the verdict; `points` are the refined
    tie points that could be assigned (check points left out), `store` the model they were
    assigned to (without it, no model-fit test); `unsettled_shift`: the largest camera move of
    the loop's last iteration when it ran out of iterations (adjust.loop.LoopResult)."""
    t = QualityThresholds()
    metrics: dict = {
        "assigned_share": assignment.num_assigned / max(len(points), 1),
        "num_assigned_points": assignment.num_assigned, "num_planes": assignment.num_faces,
        "near_share": model_support(points, surface, store, options),
        "near_share_gnss_only": None, "diverged": diverged,
        "loop_iterations": (options.workflow.max_iterations if unsettled_shift is not None
                            else None),
        "unsettled_shift_m": float(unsettled_shift) if unsettled_shift is not None else None,
        "planes_fix": planes_fix(observability_dict),
        "one_plane": rests_on_one_plane(observability_dict),
        "gnss_alone": gnss_alone(observability_dict),
        # Where weighting the faces as units moved the block by more than its sigma.
        "weighting_axes": {axis: {"move_m": row["weighting_move_m"],
                                  "sigma_m": row["sigma_one_weighting"]}
                           for axis, row in observability_dict.items()
                           if row.get("weighting_move_m") is not None},
        # Where the loop would still move the block by more than the planes' sigma.
        "unsettled_axes": {axis: {"move_m": row["remaining_move_m"],
                                  "sigma_settled_m": row["sigma_settled"]}
                           for axis, row in observability_dict.items()
                           if row.get("remaining_move_m", 0.0) > row.get("sigma_settled", 0.0)},
    }
    sigmas = [observability_dict.get(k, {}).get("sigma") for k in ("E", "N", "U")]
    if all(v is not None for v in sigmas):
        metrics["position_sigma_m"] = float(np.linalg.norm(sigmas))
        metrics["position_sigmas_m"] = [float(v) for v in sigmas]
    assigned = assignment.assigned
    faces = assignment.face_index[assigned]
    fit = None
    if store is not None and len(faces):
        prior = options.adjustment.sigma_generalisation or GENERALISATION_SIGMA
        fit = face_fit(points[assigned], faces, store, prior)
        metrics["fit"] = fit_statistics(fit, prior, options.adjustment.sigma_dtp, t.fit_band)
    gnss_covariance = None
    if gnss_only is not None and priors is not None:
        _, before = tie_points(gnss_only)
        metrics["near_share_gnss_only"] = (
            float(np.mean(surface(before, NEAR_DISTANCE) < NEAR_DISTANCE)) if len(before)
            else 0.0)
        difference = datum_difference(gnss_only, rec, priors)
        shift = difference[:3]
        metrics["shift_m"] = float(np.linalg.norm(shift))
        metrics["shift_enu_m"] = shift.tolist()
        metrics["datum_difference"] = dict(zip(DATUM, difference.tolist()))
        if fit is not None:
            gnss_datum, planes_datum = datum_covariances(
                points[assigned], faces, store, fit, priors, rec, options)
            gnss_covariance = gnss_datum[:3, :3]
            metrics["gnss_test"] = shift_test(difference, gnss_datum, planes_datum, t.alpha)
    if len(points):
        # Where the faces' effects are estimated, the points as the model's faces see them.
        shifts = getattr(last, "face_effect_shifts", None)
        seen = (points + shifts(assignment.point_ids)
                if shifts is not None and len(assignment.point_ids) == len(points) else points)
        metrics["placement"] = placement_metrics(seen, surface, metrics.get("shift_enu_m"),
                                                 gnss_covariance, t)
        metrics["height_placement"] = height_metrics(seen, surface,
                                                     metrics.get("shift_enu_m"),
                                                     gnss_covariance, t)
    return quality_verdict(metrics, t, options.precision.tolerance)


def model_support(points: np.ndarray, surface, store, options: RefineOptions) -> float:
    """The share of the tie points (not those only the terrain carries) within NEAR_DISTANCE
    of the model's buildings: the ground fits a level terrain under any model, the right one
    or one of another street, so the points on it say nothing of whether the buildings are
    these images'. Without `store`, the share near `surface` (faces and terrain)."""
    if not len(points):
        return 0.0
    near = surface(points, NEAR_DISTANCE) < NEAR_DISTANCE
    if store is None:
        return float(np.mean(near))
    from ..align.coarse import SurfaceDistance
    from ..citymodel.ground_faces import TERRAIN_CLASS

    buildings = SurfaceDistance(store, (*options.assignment.excluded_classes, TERRAIN_CLASS),
                                options.adjustment.num_threads)
    on_buildings = buildings(points, NEAR_DISTANCE) < NEAR_DISTANCE
    ground_only = near & ~on_buildings
    return float(on_buildings.sum() / max(len(points) - int(ground_only.sum()), 1))


#: Half-width (m) of the placements searched without GNSS, and at most with it.
PLACEMENT_REACH = 30.0


def placement_metrics(points: np.ndarray, surface, shift, covariance, t: QualityThresholds
                      ) -> dict:
    """The ambiguity test's figures (precision.ambiguity): placements within the region GNSS
    admits around the GNSS-only block (`covariance`: GNSS's, with its bias; its chi-square
    bound at `t.alpha`), at most PLACEMENT_REACH from the refined one, or within
    PLACEMENT_REACH without GNSS."""
    if shift is None or covariance is None or not np.all(np.isfinite(covariance[:2, :2])):
        reach = PLACEMENT_REACH

        def admitted(grid):
            return np.ones(len(grid), bool)
    else:
        horizontal = covariance[:2, :2]
        bound = float(stats.chi2.ppf(1.0 - t.alpha, 2))
        inverse = np.linalg.inv(horizontal)
        reach = min(PLACEMENT_REACH, float(np.sqrt(bound * np.max(np.diag(horizontal))))
                    + float(np.linalg.norm(shift[:2])))

        def admitted(grid):
            d = np.asarray(grid) + np.asarray(shift[:2])
            return np.einsum("ij,jk,ik->i", d, inverse, d) <= bound
    placement = placement_fit(points, surface, reach, admitted, radius=NEAR_DISTANCE,
                              distinct=DISTINCT)
    return {**placement.todict(), "reach_m": reach}


def height_metrics(points: np.ndarray, surface, shift, covariance, t: QualityThresholds
                   ) -> dict:
    """The height test's figures (precision.ambiguity.height_fit): heights within the range
    GNSS admits around the GNSS-only block (its U variance in `covariance`, with its bias; the
    chi-square bound at `t.alpha`), at most PLACEMENT_REACH from the refined one; within
    PLACEMENT_REACH where GNSS does not hold the height (its bias estimated)."""
    if shift is None or covariance is None or not np.isfinite(covariance[2, 2]):
        reach = PLACEMENT_REACH

        def admitted(shifts):
            return np.ones(len(shifts), bool)
    else:
        bound = float(stats.chi2.ppf(1.0 - t.alpha, 1)) * float(covariance[2, 2])
        reach = min(PLACEMENT_REACH, float(np.sqrt(bound)) + abs(float(shift[2])))

        def admitted(shifts):
            return (np.asarray(shifts) + float(shift[2])) ** 2 <= bound
    height = height_fit(points, surface, reach, admitted, radius=NEAR_DISTANCE,
                        distinct=DISTINCT)
    return {**height.todict(), "reach_m": reach}


def checkpoint_verdict(quality: QualityReport, accuracy: dict | None) -> QualityReport:
    """The check marks' independent test of the block (precision.accuracy.check_accuracy,
    at the verdict's level alpha) into `quality`, in place: figures in `metrics` ("checkpoints");
    an "ok" block whose check points' errors exceed their sigmas (survey and cameras) becomes
    "weak" with the reason. The test never fails a block: it comes after the choice between
    the refined and the GNSS-only result, on the block handed back."""
    test = (accuracy or {}).get("test")
    if test is None:
        return quality
    quality.metrics["checkpoints"] = {
        "test": test, "rmse_3d_m": accuracy["rmse_3d_m"], "num_used": accuracy["num_used"],
        "blunders": sorted(accuracy.get("blunders", {}))}
    if not test["passed"]:
        quality.reasons.append(
            f"check points: errors beyond their sigmas (chi-square {test['statistic']:.1f} > "
            f"{test['bound']:.1f} on {test['dof']} degrees of freedom at {test['alpha']:g}; "
            f"RMS 3D {accuracy['rmse_3d_m']:.3f} m)")
        if quality.verdict == "ok":
            quality.verdict = "weak"
    return quality
