"""Variance component estimation (Foerstner): the sigmas of the observation groups estimated
from the data, and the final solve of refine that uses them."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
import pycolmap

from ..adjust.problem import GROUPS, HybridProblem
from .estimate import PrecisionResult, cofactors, estimate_precision, variance_factors

logger = logging.getLogger(__name__)


#: Groups whose sigma VCE estimates by default. f_VT / f_dVT are design choices ("the model is
#: almost fixed") with little redundancy; estimating them drives them to zero on a good model.
VCE_GROUPS = ("image", "gnss", "dTP")


@dataclass
class VarianceComponents:
    """Result of iterated variance component estimation (Foerstner 1979 / Helmert type).

    `factors[g]` multiplies group g's a priori sigmas (image: sigma_image; gnss: each prior's
    sigmas; dTP/dVT/VT: sigma_dtp/dvt/vt); `sigmas` are the resulting absolute values for the
    scalar groups."""

    factors: dict[str, float]
    sigmas: dict[str, float]
    history: list[dict[str, float]]  # per iteration: the factors estimated from that solve
    converged: bool
    precision: PrecisionResult  # of the last solve, with the estimated sigmas
    seconds: float
    problem: HybridProblem | None = None  # the last (re-weighted) solve

    def todict(self) -> dict:
        return {"factors": self.factors, "sigmas": self.sigmas, "history": self.history,
                "converged": self.converged, "seconds": self.seconds,
                "sigma0_by_group": self.precision.variance.sigma0_by_group}


def estimate_variance_components(build, initial_sigmas: dict[str, float],
                                 groups: tuple[str, ...] = VCE_GROUPS, *,
                                 max_iterations: int = 15, tolerance: float = 0.01,
                                 alpha: float = 0.05, covariances: bool = True
                                 ) -> VarianceComponents:
    """Iterate: solve with the current sigmas, s_g^2 = v_g^T P v_g / r_g (redundancy numbers
    from the hat matrix), sigma_g <- sigma_g * s_g, until no factor changes by more than
    `tolerance` (relative). The iteration converges linearly (on the synthetic street the
    f_dTP factor shrinks its step by ~0.6 per iteration), so a loose tolerance stops early.

    `build(factors) -> HybridProblem` returns a fresh, unsolved problem whose group sigmas are
    the a priori ones times `factors[g]`. COLMAP's reprojection residuals are always weighted
    with 1 px, so the solve uses factors relative to the image group (only ratios change the
    estimate) and the image component is carried along outside the problem. The redundancy
    numbers need the cofactor matrix in every iteration; `covariances=False` skips the image
    and point covariances of the returned precision (they are computed again by the caller)."""
    start = time.perf_counter()
    factors = {g: 1.0 for g in GROUPS}
    history: list[dict[str, float]] = []
    converged = False
    precision = None
    for _ in range(max_iterations):
        # Sigmas of the solve relative to the image component (its weight is fixed at 1 px).
        relative = {g: f / factors["image"] for g, f in factors.items()}
        relative["image"] = 1.0
        problem = build(relative)
        problem.solve()
        precision = _variance_with_hat_matrix(problem, alpha) if not covariances \
            else estimate_precision(problem, alpha=alpha)
        s0 = precision.variance.sigma0_by_group
        step = {g: s0[g] for g in groups if s0.get(g)}
        history.append({g: float(relative[g] * s) for g, s in step.items()})
        # The residuals are absolute: group g's sigma is sigma_g0 * relative_g * s_g.
        updated = {g: relative[g] * s for g, s in step.items()}
        change = max(abs(updated[g] / factors[g] - 1.0) for g in updated)
        factors.update(updated)
        if change < tolerance:
            converged = True
            break
    sigmas = {g: initial_sigmas[g] * factors[g] for g in initial_sigmas}
    logger.info("variance components: %s after %d iterations%s", ", ".join(
        f"{g} x{factors[g]:.3f}" for g in groups), len(history),
        "" if converged else " (not converged)")
    return VarianceComponents(dict(factors), sigmas, history, converged, precision,
                              time.perf_counter() - start, problem)


def _variance_with_hat_matrix(problem: HybridProblem, alpha: float) -> PrecisionResult:
    """s0 per group with the exact (hat matrix) redundancies, no image/point covariances."""
    cof = cofactors(problem)
    variance = variance_factors(problem.group_residuals(), problem.num_unknowns(),
                                cof.redundancy_by_group, alpha=alpha)
    return PrecisionResult(variance, datum_defect=cof.datum_defect,
                           seconds={"cofactors": cof.seconds})


def _scaled_options(options, factors: dict[str, float]):
    """AdjustmentOptions with the model groups' sigmas multiplied by `factors`."""
    import dataclasses

    generalisation = options.sigma_generalisation
    if generalisation is not None:
        generalisation = generalisation * factors.get("gen", 1.0)
    vt = factors.get("VT", 1.0)
    return dataclasses.replace(options, sigma_dtp=options.sigma_dtp * factors.get("dTP", 1.0),
                               sigma_dvt=options.sigma_dvt * factors.get("dVT", 1.0),
                               sigma_vt=options.sigma_vt * vt,
                               sigma_vt_corrected=options.sigma_vt_corrected * vt,
                               sigma_correction_datum=options.sigma_correction_datum * vt,
                               sigma_generalisation=generalisation)


def _initial_sigmas(options, priors) -> dict[str, float]:
    initial = {"image": options.sigma_image, "dTP": options.sigma_dtp,
               "dVT": options.sigma_dvt, "VT": options.sigma_vt}
    if options.sigma_generalisation is not None:
        initial["gen"] = options.sigma_generalisation
    if priors is not None and len(priors):
        initial["gnss"] = float(np.median(priors.sigmas))
    return initial


def _usable_groups(groups, initial: dict[str, float]) -> tuple[str, ...]:
    """Drop groups without observations in this problem (no GNSS, classical model)."""
    return tuple(g for g in groups if g in initial)


def final_solve_in_refine(reconstruction: pycolmap.Reconstruction, store, assignment, priors,
                          options, current, last: HybridProblem
                          ) -> tuple[HybridProblem, VarianceComponents | None]:
    """refine()'s optional last step on the final assignment, solving in place on
    `reconstruction` (the result and its covariances are those of this solve):

    - PrecisionOptions.variance_components: iterated VCE of `variance_component_groups`
      (each iteration continues from the previous solution);
    - else AdjustmentOptions.estimate_generalisation (with sigma_generalisation): one re-solve
      with the per-plane offsets as unknowns;
    - else nothing: `last` is returned."""
    import dataclasses

    adjustment, p = options.adjustment, options.precision
    offsets = bool(adjustment.estimate_generalisation
                   and adjustment.sigma_generalisation is not None)
    if not p.variance_components:
        if not offsets:
            return last, None
        problem = HybridProblem(reconstruction, store, assignment, priors, adjustment,
                                robust_images=False, robust_planes=False, current=current,
                                generalisation_offsets=True)
        problem.solve()
        return problem, None
    initial = _initial_sigmas(adjustment, priors)
    # "gen" is not iterated here: as the prior of estimated offsets it diverged (the block's
    # shrinking feeds it); its component comes from the planes' mean residuals in
    # estimate_precision (generalisation_effects).
    initial.pop("gen", None)
    groups = _usable_groups(p.variance_component_groups, initial)

    def build(factors: dict[str, float]) -> HybridProblem:
        scaled = None
        if priors is not None:
            scaled = dataclasses.replace(priors, sigmas=priors.sigmas * factors["gnss"])
        scaled_options = _scaled_options(adjustment, factors)
        if not offsets:  # a consider parameter: absolute, not a weight relative to the images
            scaled_options.sigma_generalisation = adjustment.sigma_generalisation
        return HybridProblem(reconstruction, store, assignment, scaled,
                             scaled_options, robust_images=False,
                             robust_planes=False, current=current,
                             generalisation_offsets=offsets)

    vce = estimate_variance_components(build, initial, groups,
                                       max_iterations=p.variance_component_iterations,
                                       tolerance=p.variance_component_tolerance,
                                       alpha=p.alpha, covariances=False)
    return vce.problem, vce


def variance_components_after_refine(result, groups: tuple[str, ...] = VCE_GROUPS,
                                     **kwargs) -> VarianceComponents:
    """VCE on refine's final assignment: re-solves copies of the refined reconstruction with
    the final assignment and model (the RefineResult itself is not changed)."""
    import dataclasses

    options = result.options.adjustment
    priors = result.gnss_priors
    initial = _initial_sigmas(options, priors)
    groups = _usable_groups(groups, initial)

    def build(factors: dict[str, float]) -> HybridProblem:
        adjusted = _scaled_options(options, factors)
        scaled = None
        if priors is not None:
            scaled = dataclasses.replace(priors, sigmas=priors.sigmas * factors["gnss"])
        return HybridProblem(pycolmap.Reconstruction(result.reconstruction), result.store,
                             result.assignment, scaled, adjusted, robust_images=False,
                             robust_planes=False, current=result.adjusted_store)

    return estimate_variance_components(build, initial, groups, **kwargs)
