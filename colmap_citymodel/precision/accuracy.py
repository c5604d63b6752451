"""The accuracy of a block on check marks: surveyed points measured in the images, never in the
adjustment (block.marks), triangulated from the block's cameras (precision.checkpoints).

Per mark: its error E, N, U (where the block puts it minus where it was surveyed), its
surveyed sigma and its sigma from the cameras' covariance (the precision stage's, propagated
into the triangulation). For the block:

- RMSE per axis, RMSE_H = sqrt(RMSE_E^2 + RMSE_N^2), RMSE_V = RMSE_U,
  RMSE_3D = sqrt(RMSE_H^2 + RMSE_V^2);
- the ASPRS Positional Accuracy Standards for Digital Geospatial Data, Edition 2, Version 1.0
  (ASPRS 2023): the product's accuracy includes the check points' own survey accuracy,
  RMSE_H = sqrt(RMSE_H1^2 + RMSE_H2^2) and RMSE_V = sqrt(RMSE_V1^2 + RMSE_V2^2) (section 7:
  1 the data against the check points, 2 the survey of the check points, here the root of
  their mean stated variance), RMSE_3D = sqrt(RMSE_H^2 + RMSE_V^2); the accuracy at the 95 %
  confidence level that the NSSDA and Edition 1 report (Edition 2 keeps it as an informative
  conversion): horizontal 1.7308 RMSE_H (RMSE_E about equal to RMSE_N; 2.4477 RMSE_E is
  the same bound per axis), vertical (non-vegetated) 1.96 RMSE_V. The standard asks for at
  least 30 check points (20 in Edition 1) for a product's accuracy; fewer are reported, with a
  note;
- an independent test of the block: the errors against their sigmas, e^T (C_survey +
  C_cameras)^-1 e with the cameras' joint covariance of the check points, chi-square with 3n
  degrees of freedom at the verdict's level (precision.quality.checkpoint_verdict uses it).

Blunders: a check mark whose error stands out of the others' (its error minus their mean,
against both their sigmas, chi-square with 3 degrees of freedom at `MarkOptions.
blunder_alpha`) is named, the worst first, one at a time while three or more remain, and left
out of the statistics and the test with its reason. A block off by a common shift moves every
mark alike: none stands out, the test fails instead.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy import stats

from ..block.marks import GroundMarks
from ..options import MarkOptions

logger = logging.getLogger(__name__)

#: NSSDA / ASPRS factor from the radial RMSE_H to the horizontal accuracy at the 95 %
#: confidence level (circular error, RMSE_E about equal to RMSE_N): 2.4477 / sqrt(2).
HORIZONTAL_95 = 1.7308
#: Factor from RMSE_V to the vertical accuracy at the 95 % level (normal errors, 1.96 sigma).
VERTICAL_95 = 1.96
#: Check points the ASPRS standard (Edition 2) asks for to state a product's accuracy.
ASPRS_MIN_CHECKPOINTS = 30
#: Check marks the blunder test needs: one tested against the mean of at least two others.
MIN_BLUNDER_TEST = 3


def _rms(values: np.ndarray, axis=0) -> np.ndarray:
    return np.sqrt(np.mean(np.square(values), axis=axis))


def asprs_figures(errors: np.ndarray, survey_sigmas: np.ndarray) -> dict:
    """The ASPRS Edition 2 figures of check point `errors` (N, 3 m, E N U) whose surveyed
    positions have `survey_sigmas` (N, 3 m): see the module docstring."""
    rmse = _rms(errors)
    h1, v1 = float(np.hypot(rmse[0], rmse[1])), float(rmse[2])
    h2 = float(np.sqrt(np.mean(survey_sigmas[:, 0] ** 2 + survey_sigmas[:, 1] ** 2)))
    v2 = float(np.sqrt(np.mean(survey_sigmas[:, 2] ** 2)))
    h, v = float(np.hypot(h1, h2)), float(np.hypot(v1, v2))
    out = {"standard": "ASPRS Positional Accuracy Standards for Digital Geospatial Data, "
                       "Edition 2 (2023)",
           "num_checkpoints": int(len(errors)),
           "rmse_h1_m": h1, "rmse_v1_m": v1, "survey_rmse_h_m": h2, "survey_rmse_v_m": v2,
           "rmse_h_m": h, "rmse_v_m": v, "rmse_3d_m": float(np.hypot(h, v)),
           "horizontal_accuracy_95_m": HORIZONTAL_95 * h,
           "vertical_accuracy_95_m": VERTICAL_95 * v}
    if len(errors) < ASPRS_MIN_CHECKPOINTS:
        out["note"] = (f"{len(errors)} check points: the standard asks for at least "
                       f"{ASPRS_MIN_CHECKPOINTS} to state a product's accuracy")
    return out


def _camera_covariance(evaluation) -> np.ndarray | None:
    """(3N, 3N) the cameras' joint covariance of the evaluated check points (the primary
    stochastic model's), or None without one."""
    model = evaluation.primary_model
    return None if model is None else evaluation.covariances[model]


def _blunders(errors: np.ndarray, covariances: np.ndarray, names: list[str], alpha: float
              ) -> tuple[np.ndarray, dict[str, str], np.ndarray]:
    """(which marks are kept, {name: reason} of the blunders, each mark's statistic): the
    worst mark whose error minus the others' mean exceeds chi-square(3) at 1 - alpha, one at a
    time while MIN_BLUNDER_TEST remain. `covariances`: (N, 3, 3) each error's."""
    bound = float(stats.chi2.ppf(1.0 - alpha, 3))
    keep = np.ones(len(errors), bool)
    statistic = np.full(len(errors), np.nan)
    reasons = {}
    while keep.sum() >= MIN_BLUNDER_TEST:
        kept = np.flatnonzero(keep)
        for i in kept:
            others = kept[kept != i]
            d = errors[i] - errors[others].mean(axis=0)
            c = covariances[i] + covariances[others].sum(axis=0) / len(others) ** 2
            statistic[i] = float(d @ np.linalg.solve(c, d))
        worst = kept[np.argmax(statistic[kept])]
        if statistic[worst] <= bound:
            break
        d = errors[worst] - errors[kept[kept != worst]].mean(axis=0)
        reasons[names[worst]] = (
            f"blunder: its error stands {np.linalg.norm(d):.3f} m out of the other check "
            f"points' (E N U {np.round(d, 3).tolist()} m; test {statistic[worst]:.1f} > "
            f"{bound:.1f}, chi-square(3) at {alpha:g}); left out of the check statistics")
        logger.warning("check mark %s: %s", names[worst], reasons[names[worst]])
        keep[worst] = False
    return keep, reasons, statistic


def block_test(errors: np.ndarray, survey: np.ndarray, cameras: np.ndarray | None,
               alpha: float) -> dict:
    """The check points' independent test of the block: e^T (C_survey + C_cameras)^-1 e
    against chi-square with 3n degrees of freedom at 1 - alpha. `survey`: (n, 3) sigmas;
    `cameras`: their (3n, 3n) joint covariance (None: the survey's alone, stated as such)."""
    e = errors.reshape(-1)
    covariance = np.diag(survey.reshape(-1) ** 2)
    if cameras is not None:
        covariance = covariance + cameras
    value = float(e @ np.linalg.solve(covariance, e))
    dof = len(e)
    bound = float(stats.chi2.ppf(1.0 - alpha, dof))
    return {"statistic": value, "dof": dof, "bound": bound, "alpha": alpha,
            "p_value": float(stats.chi2.sf(value, dof)), "passed": bool(value <= bound)}


def check_accuracy(evaluation, marks: GroundMarks, alpha: float, *,
                   options: MarkOptions | None = None, reconstruction=None) -> dict:
    """report.json `checkpoints` figures of the check `marks` evaluated in `evaluation` (a
    precision.checkpoints.CheckpointEvaluation: errors, the cameras' covariances if attached):
    per mark, RMSE, ASPRS, the block test at `alpha` and the blunders (module docstring). Without the cameras'
    covariances, the rays' own (the cameras taken as exact, `options.sigma_pixel`) from the
    evaluated `reconstruction`, else the survey's alone."""
    options = options or MarkOptions()
    by_name = {m.name: m for m in marks.marks}
    names = [n for n in evaluation.ids if n in by_name]
    rows = [evaluation.ids.index(n) for n in names]
    errors = -np.asarray(evaluation.errors, float)[rows]  # the block minus the survey
    survey = np.array([by_name[n].sigma for n in names]).reshape(-1, 3)
    joint = _camera_covariance(evaluation)
    cameras, source = None, "survey only (no covariances of the block)"
    if joint is not None:
        index = np.concatenate([3 * r + np.arange(3) for r in rows]) if rows else []
        cameras = joint[np.ix_(index, index)]
        cameras, source = ((cameras, "survey and cameras") if np.all(np.isfinite(cameras))
                           else (None, source))
    if cameras is None and reconstruction is not None:
        cameras = _ray_covariance(reconstruction, [by_name[n] for n in names],
                                  options.sigma_pixel)
        source = ("survey and rays (the cameras taken as exact: no covariances of the "
                  "block)")
    blocks = np.array([np.diag(s ** 2) + (cameras[3 * i:3 * i + 3, 3 * i:3 * i + 3]
                                          if cameras is not None else 0.0)
                       for i, s in enumerate(survey)]).reshape(-1, 3, 3)
    keep, blunders, statistic = _blunders(errors, blocks, names, options.blunder_alpha)
    out = {"marks": _mark_rows(names, errors, survey, blocks, statistic, blunders, by_name,
                               evaluation),
           "blunders": blunders,
           "not_triangulated": {n: ("measured in fewer than two registered images of the block"
                                    if by_name[n].has_height else
                                    "surveyed without a height (NaN): no check in 3D")
                                for n in by_name if n not in names}}
    if keep.any():
        used = errors[keep]
        rmse = _rms(used)
        kept = np.repeat(keep, 3)
        out.update({
            "num_used": int(keep.sum()), "rmse_m": rmse.tolist(),
            "mean_error_m": used.mean(axis=0).tolist(),
            "rmse_h_m": float(np.hypot(rmse[0], rmse[1])), "rmse_v_m": float(rmse[2]),
            "rmse_3d_m": float(np.linalg.norm(rmse)),
            "asprs": asprs_figures(used, survey[keep]),
            "test": {**block_test(used, survey[keep], None if cameras is None
                                  else cameras[np.ix_(kept, kept)], alpha), "sigmas": source}})
    return out


def _ray_covariance(reconstruction, marks: list, sigma_pixel: float) -> np.ndarray | None:
    """(3N, 3N) block diagonal: each mark's rays' intersection covariance in `reconstruction`
    (block.marks.triangulate_mark); None where one cannot be intersected."""
    from ..block.marks import measurements_in, triangulate_mark

    out = np.zeros((3 * len(marks), 3 * len(marks)))
    for i, mark in enumerate(marks):
        found = triangulate_mark(reconstruction, measurements_in(reconstruction, mark)[0],
                                 sigma_pixel)
        if found is None:
            return None
        out[3 * i:3 * i + 3, 3 * i:3 * i + 3] = found[1]
    return out


def _mark_rows(names, errors, survey, blocks, statistic, blunders, by_name, evaluation
               ) -> dict:
    """Per check mark: its images, error E N U (m), surveyed sigma, sigma from the cameras
    (where known), blunder statistic, and whether it counts."""
    out = {}
    for i, name in enumerate(names):
        cameras = np.sqrt(np.maximum(np.diag(blocks[i]) - survey[i] ** 2, 0.0))
        out[name] = {
            "images": [image for image, _, _ in by_name[name].observations],
            "num_views": int(evaluation.num_views.get(name, 0)),
            "error_enu_m": errors[i].tolist(),
            "survey_sigma_enu_m": survey[i].tolist(),
            "sigma_enu_m": cameras.tolist() if np.any(cameras > 0) else None,
            "blunder_statistic": None if np.isnan(statistic[i]) else float(statistic[i]),
            "used": name not in blunders, "reason": blunders.get(name)}
    return out


def accuracy_markdown(accuracy: dict | None) -> str:
    """report.md's table of the check marks and their figures."""
    if not accuracy or not accuracy.get("marks"):
        return ""
    lines = ["", "### Check marks", "",
             "| mark | images | error E (m) | error N (m) | error U (m) | survey sigma H / V "
             "(m) | sigma from the cameras E / N / U (m) | counts |",
             "|---|---|---|---|---|---|---|---|"]
    for name, row in accuracy["marks"].items():
        e, s = row["error_enu_m"], row["survey_sigma_enu_m"]
        c = row["sigma_enu_m"]
        lines.append(f"| {name} | {row['num_views']} | {e[0]:+.3f} | {e[1]:+.3f} | {e[2]:+.3f} "
                     f"| {s[0]:.3f} / {s[2]:.3f} | "
                     + (" / ".join(f"{v:.3f}" for v in c) if c else "-") + " | "
                     + ("yes" if row["used"] else "no: blunder") + " |")
    for name, reason in {**accuracy.get("blunders", {}),
                         **accuracy.get("not_triangulated", {})}.items():
        lines.append(f"\n- {name}: {reason}")
    if "rmse_m" in accuracy:
        r, a = accuracy["rmse_m"], accuracy["asprs"]
        lines += ["", f"RMSE E {r[0]:.3f} m, N {r[1]:.3f} m, U {r[2]:.3f} m; RMSE_H "
                  f"{accuracy['rmse_h_m']:.3f} m, RMSE_V {accuracy['rmse_v_m']:.3f} m, 3D "
                  f"{accuracy['rmse_3d_m']:.3f} m ({accuracy['num_used']} check marks).", "",
                  f"{a['standard']}: RMSE_H {a['rmse_h_m']:.3f} m, RMSE_V {a['rmse_v_m']:.3f} m "
                  f"(with the survey's {a['survey_rmse_h_m']:.3f} / {a['survey_rmse_v_m']:.3f} "
                  f"m), RMSE_3D {a['rmse_3d_m']:.3f} m; at 95 % confidence horizontal "
                  f"{a['horizontal_accuracy_95_m']:.3f} m, vertical "
                  f"{a['vertical_accuracy_95_m']:.3f} m" + (f" ({a['note']})" if a.get("note")
                                                            else "") + "."]
        t = accuracy["test"]
        lines += ["", f"Test of the block on the check marks: {t['statistic']:.1f} "
                  f"{'<=' if t['passed'] else '>'} {t['bound']:.1f} (chi-square, {t['dof']} "
                  f"degrees of freedom, level {t['alpha']:g}; sigmas: {t['sigmas']}): "
                  + ("the errors are as large as the sigmas say" if t["passed"]
                     else "the errors are larger than the sigmas say")]
    return "\n".join(lines) + "\n"


def read_check_marks(path, crs: str | None, georeference, sigma=None) -> GroundMarks:
    """The check marks of a gcp_list.txt in the CRS of an evaluated model: `crs` (a user
    string), else the one its `georeference` (georeference.json) records."""
    import json
    from pathlib import Path

    from ..block.marks import read_gcp_list
    from ..citymodel.crs import user_crs
    from ..errors import CRSError, InputError

    if crs is None and georeference is not None and str(georeference).endswith(".json"):
        try:
            record = json.loads(Path(georeference).read_text(encoding="utf-8")).get("crs") or {}
        except (OSError, ValueError) as error:
            raise InputError(f"cannot read the model's CRS: {error}", georeference) from None
        crs = record.get("wkt") or record.get("label")
    if crs is None:
        raise CRSError("check marks in gcp_list format need the model's CRS: give --crs (no "
                       "georeference.json beside the model records it)", path)
    model_crs = user_crs(crs)
    return read_gcp_list(path, model_crs, sigma if sigma is not None else (0.02, 0.03))
