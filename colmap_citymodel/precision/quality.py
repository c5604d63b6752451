"""Whether a refine result can be trusted.

`quality_verdict`: compares the refined block with the GNSS-only adjustment of the same block.
"ok": the model fitted and moved the block no further than GNSS allows; "weak": usable but
with a stated doubt; "failed": refine hands back the GNSS-only result.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pycolmap

from ..adjust.observability import planes_fix, rests_on_one_plane
from ..adjust.scale import scale_change
from ..assign.assignment import Assignment
from ..block.priors import GNSSPriors
from ..block.reconstruction import tie_points
from ..options import RefineOptions

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
    gnss_axis_weak: float = 3.0
    """Shift from the GNSS-only result along E, N or U, in units of that direction's GNSS
    sigma (observability's sigma_gnss: the sigma of the block's mean position from GNSS), above
    which a direction the planes leave to GNSS counts as moved by something else: a wrong
    assignment pulling through the other parameters; weak. Nothing but GNSS determines such
    a direction, so refined and GNSS-only blocks agree there to within that sigma."""
    gnss_axis_failed: float = 5.0
    """The same, failed: the block has been moved where GNSS alone decides, further than GNSS can
    have put it; the GNSS-only result is the better one there. Also for a direction that rests
    on a single model plane: nothing checks that plane's assignment."""
    model_evidence_gain: float = 0.25
    """A move beyond `gnss_axis_failed` or `shift_failed` is only weak when it has brought at
    least this share of all tie points near the model (within `near_distance`) that were not
    near it in the GNSS-only block, ending with at least `min_near_share`: the move is then the
    model's evidence (the first assignment's search over metres of GNSS bias, the height held
    there), not a runaway."""
    axis_evidence_share: float = 0.2
    """A move along one axis is the model's evidence only when the tie points, moved back along
    that axis to the GNSS-only level, lose at least this share of the near share the whole move
    gained: the move along that axis, not the rest of the move, brought them onto the model."""
    scale_failed_sigmas: float = 5.0
    """Scale change from the GNSS-only result beyond this many of its GNSS sigmas: failed."""
    scale_gnss_sigmas: float = 3.0
    """The same where the planes do not determine the scale (observability): beyond this the
    model has bent the block against the only observation of its scale, GNSS."""
    unsettled_shift: float = 0.05
    """The assign/adjust loop ran all its iterations and the last one still moved a camera by
    more than this (m): the assignment had not settled, and the result is one state of a loop
    still moving; weak. Loops that settle end with moves of millimetres."""
    min_assigned_share: float = 0.02
    """Fewer tie points than this share on planes: the model does not fit the block."""
    min_near_share: float = 0.35
    """Share of tie points within `near_distance` of the model below which the fit is weak: a
    block that fits has most of its tie points near the model, ground and clutter points
    counted."""
    failed_near_share: float = 0.10
    """Below this share the model does not fit the block at all: failed."""
    near_distance: float = 0.5
    """Distance (m) from the model within which a tie point counts as near it (2.5 x a LOD2
    model's sigma_dTP)."""
    position_sigma_ok: float = 0.20
    """The a posteriori sigma (3D, m) of the block's position from planes and GNSS (each plane
    with its generalisation error, offset and tilt; observability) up to which the result is
    "ok": the block is then placed as well as the model's own generalisation (0.2 m,
    sigma_dTP) allows; above it, "weak" says how well it is."""
    wall_ok: float = 0.75
    """Share of the tie points on vertical planes of the cloud (walls: the model's surest part)
    that lie within `near_distance` of the model, below which the fit is weak: a block that fits
    has nearly all of them there."""
    wall_failed: float = 0.5
    """Below this share most walls the images see are not the model's: it does not describe the
    block well enough to be its control; failed."""
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


def gnss_axis_shifts(mean_shift: np.ndarray, observability_dict: dict, *,
                     one_plane: bool = False) -> dict[str, float]:
    """|shift| / sigma_gnss along each of E, N, U that GNSS alone fixes (source "gnss"), either
    those not resting on a single plane or (`one_plane`) those that do, which a single plane
    may move legitimately (a ground or roof plane against GNSS heights metres off)."""
    out = {}
    for k, axis in enumerate("ENU"):
        row = observability_dict.get(axis, {})
        if row.get("source") == "gnss" and bool(row.get("one_plane")) == one_plane \
                and row.get("sigma_gnss"):
            out[axis] = float(abs(mean_shift[k]) / row["sigma_gnss"])
    return out


def quality_verdict(metrics: dict, thresholds: QualityThresholds | None = None
                    ) -> QualityReport:
    """Verdict from the figures refine measured (keys as written by measure_quality)."""
    t = thresholds or QualityThresholds()
    failed, weak = [], []
    fixed = metrics.get("planes_fix")
    unsettled = metrics.get("unsettled_shift_m")
    if unsettled is not None and unsettled > t.unsettled_shift:
        weak.append(f"the assignment loop had not settled after {metrics['loop_iterations']} "
                    f"iterations: the last moved the cameras by up to {unsettled:.2f} m")
    if metrics.get("diverged"):
        weak.append(f"the assignment loop diverged ({metrics['diverged']}); its best iterate "
                    "is kept")
    if metrics["assigned_share"] < t.min_assigned_share:
        failed.append(f"only {100 * metrics['assigned_share']:.1f} % of the tie points lie on "
                      "model planes: the model does not fit the block")
    before, after = metrics.get("near_share_gnss_only"), metrics["near_share"]
    # Tie points the move brought near the model: its evidence for a move GNSS disagrees with.
    evidence = (f" (tie points within {t.near_distance:g} m of the model: "
                f"{100 * before:.0f} % -> {100 * after:.0f} %)"
                if before is not None else "")
    backed = before is not None and after >= t.min_near_share \
        and after - before >= t.model_evidence_gain

    moved_back = metrics.get("near_share_moved_back") or {}

    def moved_where_gnss_checks(axis: str, sigmas: float, text: str) -> None:
        """A move along a direction that only GNSS checks, beyond `gnss_axis_weak` of its
        sigma: failed beyond `gnss_axis_failed` unless the model's evidence backs it, and
        backs this move (`axis_evidence_share`)."""
        beyond = sigmas > t.gnss_axis_failed
        by_axis = (axis not in moved_back or before is None
                   or after - moved_back[axis] >= t.axis_evidence_share * (after - before))
        held = backed and by_axis
        (failed if beyond and not held else weak).append(
            text + (evidence if held and beyond else "")
            + (f" (moved back in {axis}, {100 * moved_back[axis]:.0f} % of the tie points lie "
               f"near the model)" if beyond and backed and not by_axis else ""))

    shift = metrics.get("shift_sigmas")
    if shift is not None:
        if shift > t.shift_failed:
            (weak if backed else failed).append(
                f"the model moved the cameras {metrics['shift_m']:.1f} m ({shift:.1f} GNSS "
                "sigma) from the GNSS-only result" + (evidence if backed else ""))
        elif shift > t.shift_ok:
            weak.append(f"the model moved the cameras {metrics['shift_m']:.1f} m "
                        f"({shift:.1f} GNSS sigma) from the GNSS-only result")
    for axis, sigmas in (metrics.get("gnss_axis_shift_sigmas") or {}).items():
        if sigmas > t.gnss_axis_weak:
            moved_where_gnss_checks(
                axis, sigmas,
                f"the cameras moved {abs(metrics['shift_enu_m']['ENU'.index(axis)]):.2f} m in "
                f"{axis} ({sigmas:.1f} sigma of GNSS there) from the GNSS-only result, although "
                "only GNSS fixes that direction")
    scale = metrics.get("scale_change_sigmas")
    scale_by_gnss = fixed is not None and "scale" not in fixed
    if scale is not None and (scale > t.scale_failed_sigmas
                              or (scale_by_gnss and scale > t.scale_gnss_sigmas)):
        failed.append(f"the block's scale changed by {100 * metrics['scale_change']:.2f} % "
                      f"({scale:.1f} GNSS sigma)"
                      + (" although only GNSS determines it" if scale_by_gnss else ""))
    if before is not None and after < before:
        # As many decimals as it takes for the two shares to differ in print.
        digits = next((d for d in (0, 1) if round(100 * after, d) != round(100 * before, d)),
                      2)
        failed.append(f"fewer tie points near the model after refine ({100 * after:.{digits}f} "
                      f"%) than with GNSS only ({100 * before:.{digits}f} %)")
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
        # A block put on the wrong building of a regular street still has many of its walls
        # on model walls (a regular street's facades line up); its sigmas then say nothing.
        (failed if walls < t.wall_failed else weak).append(
            f"only {100 * walls:.0f} % of the tie points on walls lie on the model's walls"
            + ("" if walls < t.wall_failed else
               ": the block may sit on the wrong buildings, and its sigmas hold only if not"))
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
                        "rests on GNSS and on where the first assignment put the block")
        if single:
            weak.append(f"{', '.join(single)} rest(s) on a single model plane, which nothing "
                        "checks (a wrong assignment there moves the block unseen)")
        moved = metrics.get("one_plane_shift_sigmas") or {}
        for axis in single:
            if moved.get(axis, 0.0) > t.gnss_axis_weak:
                # One plane against GNSS, further than GNSS's own sigma allows: nothing checks
                # the plane, so the GNSS-only result is the safer one.
                moved_where_gnss_checks(
                    axis, moved[axis],
                    f"that plane alone moved the cameras "
                    f"{abs(metrics['shift_enu_m']['ENU'.index(axis)]):.2f} m in {axis} "
                    f"({moved[axis]:.1f} sigma of GNSS there) from the GNSS-only result")
    verdict = "failed" if failed else "weak" if weak else "ok"
    return QualityReport(verdict, failed + weak, metrics)


def measure_quality(rec: pycolmap.Reconstruction, gnss_only: pycolmap.Reconstruction | None,
                    surface, priors: GNSSPriors | None, assignment: Assignment, last,
                    observability_dict: dict, points: np.ndarray, options: RefineOptions,
                    diverged: str | None, scale_sigma: float | None,
                    unsettled_shift: float | None = None):
    """The figures of the quality gate (quality.quality_verdict) and the verdict; `points`
    are the refined tie points that could be assigned (check points left out);
    `unsettled_shift`: the largest camera move of the loop's last iteration when it ran out
    of iterations (adjust.loop.LoopResult)."""

    thresholds = QualityThresholds()
    near = thresholds.near_distance
    metrics: dict = {
        "assigned_share": assignment.num_assigned / max(len(points), 1),
        "num_assigned_points": assignment.num_assigned, "num_planes": assignment.num_faces,
        "near_share": float(np.mean(surface(points, near) < near))
        if len(points) else 0.0,
        "near_share_gnss_only": None, "diverged": diverged,
        "loop_iterations": (options.workflow.max_iterations if unsettled_shift is not None
                            else None),
        "unsettled_shift_m": float(unsettled_shift) if unsettled_shift is not None else None,
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

    walls = (wall_points(points, options.adjustment.num_threads) if len(points)
             else np.zeros((0, 3)))
    metrics["num_wall_points"] = len(walls)
    if len(walls) >= options.assignment.min_points_per_plane:
        metrics["wall_near_share"] = float(np.mean(surface(walls, near) < near))
    if gnss_only is not None and priors is not None:
        _, before = tie_points(gnss_only)
        metrics["near_share_gnss_only"] = (float(np.mean(surface(before, near) < near))
                                           if len(before) else 0.0)
        # Where GNSS observed: elsewhere (GNSS for part of the block) the GNSS-only result is
        # an extrapolation that the model is there to correct.
        ids = [int(i) for i in priors.image_ids]
        a = np.array([gnss_only.image(i).projection_center() for i in ids])
        b = np.array([rec.image(i).projection_center() for i in ids])
        sigma = np.median(priors.sigmas, axis=0)
        # The GNSS-only block sits on the GNSS as read; an estimated GNSS offset (another
        # height system, a bias) explains that much of the move.
        mean_shift = (b - a).mean(0) - priors.offset
        metrics["shift_m"] = float(np.linalg.norm(mean_shift))
        metrics["shift_enu_m"] = mean_shift.tolist()
        metrics["shift_sigmas"] = float(np.linalg.norm(mean_shift / sigma))
        metrics["gnss_axis_shift_sigmas"] = gnss_axis_shifts(mean_shift, observability_dict)
        metrics["one_plane_shift_sigmas"] = gnss_axis_shifts(mean_shift, observability_dict,
                                                             one_plane=True)
        # The model's evidence for each of those moves on its own: the near share with the
        # refined tie points moved back along that axis to the GNSS-only level.
        moved_axes = {**metrics["gnss_axis_shift_sigmas"], **metrics["one_plane_shift_sigmas"]}
        metrics["near_share_moved_back"] = {}
        for axis in sorted(moved_axes):
            back = np.array(points, float)
            back[:, "ENU".index(axis)] -= mean_shift["ENU".index(axis)]
            metrics["near_share_moved_back"][axis] = (
                float(np.mean(surface(back, near) < near)) if len(back) else 0.0)
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
