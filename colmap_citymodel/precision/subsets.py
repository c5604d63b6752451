"""Theoretical precision of image subsets of one block (Mulder 2023, 4.2 and 5.2; method.md 9).

Mulder adjusts the same block three times, with the nadir images, the oblique images and both,
and compares the a posteriori standard deviations of tie points (Table 5.2, Fig. 5.5, 5.8) and
camera positions (Table 5.4). `colmap-citymodel precision` does that for any named image
subsets of a COLMAP model (``NAME=GLOB[,GLOB...]``, matched against the image names):

1. restrict the block to the subset: frames without a selected image are de-registered (COLMAP
   removes their observations and every point left with fewer than 2), observations of
   unselected images in a selected rig frame are deleted, points whose largest triangulation
   angle is below `min_triangulation_angle` are dropped, images with fewer than
   `min_image_points` tie points are de-registered (repeated until stable);
2. a plain bundle adjustment of the subset (`HybridProblem` without a model = COLMAP's own BA,
   least squares, interior orientation fixed, image sigma 1 px);
3. covariances with `precision.estimate_precision` (scaled by the subset's s0^2): marginal tie
   point covariances, projection centre X0, Y0, Z0 of every image.

Gauge (datum) of the solve:
- "gnss" (with --database or --gnss): the block is first moved into a local metric frame (CRS
  minus a rounded origin) by a similarity to the GNSS positions of all its images; each subset
  then has the GNSS priors of its images (stated sigmas, e.g. 3, 3, 5 m) as a weak datum. The
  sigmas then include the datum's uncertainty: with metre-level GNSS they are dominated by it
  (the whole block can shift and, for a straight strip, roll about the flight line). GNSS in a
  geographic CRS goes to `target_crs` or the UTM zone of its mean position; a COLMAP database
  is read from a temporary copy (opening it with pycolmap rewrites the file).
- "fixed" (no GNSS): COLMAP's TWO_CAMS_FROM_WORLD gauge, as COLMAP's own BA fixes it: the pose
  of the subset's first image (lowest image id) and the largest baseline component of a second
  image are held. Sigmas are relative to those two images and grow away from them; the two
  images get no covariance. Units are those of the input model (metres when the input holds a
  `georeference.json`, i.e. a refine output; otherwise SfM's arbitrary scale).

Besides the sigmas in the solve datum, every subset gets the *inner* precision: the point and
projection-centre covariances S-transformed to the inner constraints of its tie points (Baarda's
S-transformation; the minimum-trace datum of the tie points, as in free-network adjustment).
These no longer depend on the gauge and compare the geometry of subsets (intersection angles,
number of rays), which is what Mulder's comparison is about; `--datum inner` puts them in the
table. The conditional point sigmas (poses held fixed: forward intersection only) are in the
JSON too.

Covariances need a dense reduced normal matrix of 6 x images unknowns; `max_images` bounds the
subset size (see `SubsetOptions`).
"""

from __future__ import annotations

import dataclasses
import fnmatch
import json
import logging
import re
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
from tqdm import tqdm

from ..adjust.problem import HybridProblem, SolveReport
from ..block.priors import GNSSPriors
from ..errors import InputError
from ..options import AdjustmentOptions
from .estimate import Cofactors, PrecisionResult, cofactors, estimate_precision, image_jacobian

logger = logging.getLogger(__name__)

#: Subset names become file names: letters, digits and ._+- only.
NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+-]*$")
#: Rounding (m) of the local origin subtracted from GNSS / CRS coordinates.
ORIGIN_ROUNDING = 100.0
#: Percentile of all subsets' sigmas that ends the shared colour scale of the sigma maps.
COLOUR_PERCENTILE = 98.0


@dataclass
class SubsetOptions:
    """Restriction and adjustment of each subset (defaults as refine's step 2)."""

    min_images: int = 3
    """A subset with fewer usable images is an input error."""
    min_image_points: int = 10
    """Images keeping fewer tie points than this after the restriction are de-registered."""
    min_triangulation_angle: float = AdjustmentOptions.min_triangulation_angle
    """Degrees; tie points whose largest ray intersection angle is smaller are dropped."""
    max_images: int = 500
    """Largest subset whose covariances are computed. The reduced normal matrix is dense
    (6 x images)^2 (500 images: 3000^2, 72 MB) and the marginal point covariances cost
    points x that (timings in docs/defaults.md)."""
    sigma_image: float = 1.0
    """A priori sigma of image coordinates (px)."""
    alpha: float = 0.05
    """Significance level of the global test reported per subset."""
    num_threads: int = -1


@dataclass
class SubsetSpec:
    name: str
    patterns: tuple[str, ...]

    def matches(self, image_name: str) -> bool:
        return any(fnmatch.fnmatchcase(image_name, p) for p in self.patterns)


def parse_subset(text: str) -> SubsetSpec:
    """``NAME=GLOB[,GLOB...]`` -> SubsetSpec; malformed text is an InputError."""
    name, sep, globs = str(text).partition("=")
    name = name.strip()
    patterns = tuple(p.strip() for p in globs.split(",") if p.strip())
    if not sep or not name or not patterns:
        raise InputError(f"malformed subset {text!r}: expected NAME=GLOB[,GLOB...], e.g. "
                         "nadir='nadir/*' or both='*'", "--subset")
    if not NAME_PATTERN.match(name):
        raise InputError(f"subset name {name!r} may only hold letters, digits and ._+- (it "
                         "names the output files)", "--subset")
    return SubsetSpec(name, patterns)


def parse_subsets(texts) -> list[SubsetSpec]:
    specs = [s if isinstance(s, SubsetSpec) else parse_subset(s) for s in texts]
    if not specs:
        raise InputError("give at least one --subset NAME=GLOB", "--subset")
    seen = set()
    for spec in specs:
        if spec.name in seen:
            raise InputError(f"subset {spec.name!r} given twice; join its globs with commas "
                             "(NAME=GLOB1,GLOB2)", "--subset")
        seen.add(spec.name)
    return specs


# -- restriction -----------------------------------------------------------------------------------

def select_images(rec: pycolmap.Reconstruction, spec: SubsetSpec, source=None) -> list[int]:
    """Registered image ids whose name matches one of the subset's globs; every glob must
    match at least one image."""
    images = [rec.image(i) for i in sorted(rec.reg_image_ids())]
    for pattern in spec.patterns:
        if not any(fnmatch.fnmatchcase(im.name, pattern) for im in images):
            examples = ", ".join(im.name for im in images[:3])
            raise InputError(f"subset {spec.name!r}: glob {pattern!r} matches no registered "
                             f"image (names look like {examples}, ...)", source)
    return [im.image_id for im in images if spec.matches(im.name)]


@dataclass
class Restriction:
    """What restricting the block to a subset kept and dropped."""

    num_matched: int  # registered images matching the globs
    image_ids: list[int]  # images adjusted
    dropped_images: list[str]  # matched, but with fewer than min_image_points tie points
    dropped_small_angle: int  # observations removed with points of too small angle


def restrict(rec: pycolmap.Reconstruction, image_ids, options: SubsetOptions
             ) -> tuple[pycolmap.Reconstruction, Restriction]:
    """A copy of `rec` with only `image_ids` registered and only their observations."""
    keep = set(int(i) for i in image_ids)
    sub = pycolmap.Reconstruction(rec)
    for frame_id in list(sub.reg_frame_ids()):
        members = [int(d.id) for d in sub.frame(frame_id).image_ids]
        if not any(i in keep for i in members):
            sub.deregister_frame(frame_id)  # also deletes its observations and short tracks
            continue
        for image_id in members:  # a rig frame with selected and unselected images
            if image_id not in keep and sub.exists_image(image_id):
                image = sub.image(image_id)
                for idx, point2D in enumerate(image.points2D):
                    if point2D.has_point3D():
                        sub.delete_observation(image_id, idx)
    dropped_angle = pycolmap.ObservationManager(sub).filter_points3D_with_small_triangulation_angle(
        options.min_triangulation_angle, set(sub.point3D_ids()))
    dropped: list[str] = []
    while True:  # de-registering weak images can weaken others: repeat until stable
        weak = [i for i in sub.reg_image_ids()
                if i in keep and sub.image(i).num_points3D < options.min_image_points]
        if not weak:
            break
        for image_id in weak:  # drop the image's observations, and its frame if now empty
            image = sub.image(image_id)
            dropped.append(image.name)
            for idx, point2D in enumerate(image.points2D):
                if point2D.has_point3D():
                    sub.delete_observation(image_id, idx)
            keep.discard(image_id)
            frame = sub.frame(image.frame_id)
            if not any(int(d.id) in keep for d in frame.image_ids):
                sub.deregister_frame(frame.frame_id)
    used = [i for i in sorted(sub.reg_image_ids()) if i in keep]
    return sub, Restriction(len(set(int(i) for i in image_ids)), used, sorted(dropped),
                            int(dropped_angle))


# -- inner precision (S-transformation) ----------------------------------------------------------

def similarity_basis(xyz: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(N, 3, 7) derivative of points under a small similarity about `centre`: translation
    (3), rotation (3, dX = omega x (X - c)) and scale (1, dX = s (X - c))."""
    d = np.asarray(xyz, float).reshape(-1, 3) - centre
    g = np.zeros((len(d), 3, 7))
    g[:, :, :3] = np.eye(3)
    # omega x d = -[d]x omega
    g[:, 0, 4], g[:, 0, 5] = d[:, 2], -d[:, 1]
    g[:, 1, 3], g[:, 1, 5] = -d[:, 2], d[:, 0]
    g[:, 2, 3], g[:, 2, 4] = d[:, 1], -d[:, 0]
    g[:, :, 6] = d
    return g


@dataclass
class InnerPrecision:
    """Covariances in the inner-constraint datum of the tie points (scaled by s0^2)."""

    point_cov: np.ndarray  # (P, 3, 3), rows as PrecisionResult.point_ids
    centre_cov: np.ndarray  # (N, 3, 3), rows as PrecisionResult.image_ids

    @property
    def point_sigmas(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(self.point_cov, axis1=1, axis2=2), 0.0))

    @property
    def centre_sigmas(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(self.centre_cov, axis1=1, axis2=2), 0.0))


def inner_precision(problem: HybridProblem, precision: PrecisionResult,
                    cof: Cofactors | None = None) -> InnerPrecision:
    """S-transform the solve's covariances to the inner constraints of all tie points.

    With the orthogonal projector P = I - G (G^T G)^-1 G^T over the point coordinates (G the
    similarity basis of the tie points), the inner-datum covariance of the points is
    P Sigma_pp P and that of a projection centre C_k is Sigma_CC - G_k A_k - A_k^T G_k^T +
    G_k M G_k^T with A_k = T^-1 sum_j G_j^T Sigma_{j,C_k}. The sums over all points use the
    Schur structure: Sigma_ji = s0^2 (delta_ij W_i^-1 + B_j Q_cc B_i^T), B = W^-1 E,
    Sigma_{j,C_k} = -s0^2 B_j Q_cc[:, k] J_k^T, so nothing bigger than (3P x 7) is formed.
    `cof`: the `cofactors(problem, keep_system=True)` that `precision` was computed from
    (computed here when not given).
    """
    if cof is None:
        cof = cofactors(problem, redundancy=False, keep_system=True)
    layout, q_cc = cof.layout, cof.q_cc
    if cof.system is None or not np.array_equal(layout.point_ids, precision.point_ids):
        raise RuntimeError("the precision result does not belong to these cofactors")
    _, _, b, w_inv = cof.system
    num_points = len(layout.point_ids)
    s0sq = precision.covariance_factor or precision.variance.sigma0_squared

    centre = precision.points.mean(0)
    g = similarity_basis(precision.points, centre)  # (P, 3, 7)
    t_inv = np.linalg.inv(np.einsum("pik,pil->kl", g, g))
    k_mat = np.asarray((b.T @ g.reshape(-1, 7))).T  # (7, nc) = sum_j G_j^T B_j
    l_mat = k_mat @ q_cc  # (7, nc)
    bl = np.asarray(b @ l_mat.T).reshape(num_points, 3, 7)  # B_i L^T
    gw = np.einsum("pik,pij->pkj", g, w_inv)  # G_i^T W_i^-1, (P, 7, 3)
    m = t_inv @ (np.einsum("pkj,pjl->kl", gw, g) + l_mat @ k_mat.T) @ t_inv  # unscaled
    a = np.einsum("kl,plj->pkj", t_inv, gw + bl.transpose(0, 2, 1))  # (P, 7, 3)
    ga = np.einsum("pik,pkj->pij", g, a)
    q_points = precision.point_cov / s0sq
    inner_points = q_points - ga - ga.transpose(0, 2, 1) + np.einsum("pik,kl,pjl->pij", g, m, g)

    rec = problem.reconstruction
    centres = []
    for k, image_id in enumerate(precision.image_ids):
        columns = layout.columns("frame", rec.image(int(image_id)).frame_id)
        jac = image_jacobian(rec, int(image_id))[:3]  # (3, 6)
        g_k = similarity_basis(precision.centres[k], centre)[0]
        a_k = -t_inv @ l_mat[:, columns] @ jac.T  # (7, 3)
        q_kk = precision.image_cov[k, :3, :3] / s0sq
        ga_k = g_k @ a_k
        centres.append(q_kk - ga_k - ga_k.T + g_k @ m @ g_k.T)
    return InnerPrecision(s0sq * inner_points, s0sq * np.array(centres).reshape(-1, 3, 3))


# -- one subset ----------------------------------------------------------------------------------

@dataclass
class SubsetResult:
    spec: SubsetSpec
    restriction: Restriction
    gauge: str  # "gnss" or "fixed"
    num_gnss: int
    solve: SolveReport
    precision: PrecisionResult
    inner: InnerPrecision | None
    reconstruction: pycolmap.Reconstruction
    seconds: float = 0.0

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def num_images(self) -> int:
        return len(self.restriction.image_ids)

    @property
    def num_points(self) -> int:
        return len(self.precision.point_ids)

    def point_sigmas(self, datum: str = "solve") -> np.ndarray:
        return self.inner.point_sigmas if datum == "inner" else self.precision.point_sigmas

    def centre_sigmas(self, datum: str = "solve") -> np.ndarray:
        if datum == "inner":
            return self.inner.centre_sigmas
        return self.precision.image_sigmas[:, :3]

    def summary(self) -> dict:
        p = self.precision

        def median(values: np.ndarray, keys) -> dict | None:
            return dict(zip(keys, np.median(values, 0).tolist())) if len(values) else None

        out = {
            "name": self.name, "globs": list(self.spec.patterns),
            "num_images_matched": self.restriction.num_matched,
            "num_images": self.num_images, "num_points3D": self.num_points,
            "num_observations": int(self.solve.count["image"] // 2),
            "dropped_images": self.restriction.dropped_images,
            "dropped_small_angle_observations": self.restriction.dropped_small_angle,
            "gauge": self.gauge, "num_gnss": self.num_gnss,
            "sigma0": p.variance.sigma0, "global_test": (p.variance.test.todict()
                                                         if p.variance.test else None),
            "datum_defect": p.datum_defect,
            "num_images_with_covariance": int(len(p.image_ids)),
            "median_point_sigma": median(p.point_sigmas, "XYZ"),
            "median_point_sigma_conditional": median(p.point_sigmas_conditional, "XYZ"),
            "median_centre_sigma": median(p.image_sigmas[:, :3], ("X0", "Y0", "Z0")),
            "median_angle_sigma_deg": median(p.image_sigmas[:, 3:], ("omega", "phi", "kappa")),
            "ceres_iterations": self.solve.ceres_iterations, "seconds": self.seconds,
        }
        if self.inner is not None:
            out["median_point_sigma_inner"] = median(self.inner.point_sigmas, "XYZ")
            out["median_centre_sigma_inner"] = median(self.inner.centre_sigmas,
                                                      ("X0", "Y0", "Z0"))
        return out


def adjust_subset(rec: pycolmap.Reconstruction, spec: SubsetSpec, priors: GNSSPriors | None,
                  options: SubsetOptions, *, source=None, inner: bool = True) -> SubsetResult:
    """Restrict, adjust and compute the covariances of one subset (`rec` is not modified)."""
    start = time.perf_counter()
    image_ids = select_images(rec, spec, source)
    if len(image_ids) > options.max_images:
        raise InputError(
            f"subset {spec.name!r} has {len(image_ids)} images, more than --max_images "
            f"{options.max_images}: its covariances need a dense "
            f"{6 * len(image_ids)}x{6 * len(image_ids)} reduced normal matrix "
            f"(~{(6 * len(image_ids)) ** 2 * 8 / 1e6:.0f} MB) and time growing with images^2 x "
            "tie points; raise --max_images or use smaller subsets", source)
    sub, restriction = restrict(rec, image_ids, options)
    if len(restriction.image_ids) < options.min_images or sub.num_points3D() == 0:
        raise InputError(
            f"subset {spec.name!r} is too small to adjust: {len(restriction.image_ids)} of its "
            f"{restriction.num_matched} images keep at least {options.min_image_points} tie "
            f"points ({sub.num_points3D()} tie points with 2+ rays and an intersection angle of "
            f"{options.min_triangulation_angle:g} deg or more); at least {options.min_images} "
            "images are needed", source)
    subset_priors = None
    if priors is not None:
        mask = np.isin(priors.image_ids, restriction.image_ids)
        if np.count_nonzero(mask) < 3:
            raise InputError(
                f"subset {spec.name!r} has GNSS for only {np.count_nonzero(mask)} of its images; "
                "at least 3 are needed for the GNSS datum (or run without GNSS: fixed gauge)",
                source)
        subset_priors = GNSSPriors(priors.image_ids[mask], priors.positions[mask],
                                   priors.sigmas[mask], priors.lever_arm)
    adjustment = AdjustmentOptions(sigma_image=options.sigma_image,
                                   num_threads=options.num_threads)
    problem = HybridProblem(sub, None, None, subset_priors, adjustment, robust_images=False,
                            robust_planes=False)
    solve = problem.solve()
    # Cofactors with their Schur system: estimate_precision and the inner datum share them.
    cof = cofactors(problem, keep_system=inner)
    precision = estimate_precision(problem, alpha=options.alpha, cof=cof)
    if len(precision.image_ids) != len(restriction.image_ids):
        # Unselected images of a selected rig frame, or the gauge images: report only the
        # subset's images that have a full pose covariance.
        mask = np.isin(precision.image_ids, restriction.image_ids)
        precision = _rows(precision, mask)
    inner_result = None
    if inner:
        inner_result = inner_precision(problem, precision, cof)
    result = SubsetResult(spec, restriction, "gnss" if subset_priors is not None else "fixed",
                          0 if subset_priors is None else len(subset_priors), solve, precision,
                          inner_result, sub, time.perf_counter() - start)
    if precision.datum_defect:
        logger.warning("subset %s: the normal matrix has a datum defect of %d (e.g. a block "
                       "split in parts); its sigmas are of a minimum-norm solution", spec.name,
                       precision.datum_defect)
    logger.info("subset %s: %d images, %d tie points, s0 %.3f, %.1f s", spec.name,
                result.num_images, result.num_points, precision.variance.sigma0, result.seconds)
    return result


def _rows(precision: PrecisionResult, mask: np.ndarray) -> PrecisionResult:
    return dataclasses.replace(
        precision, image_ids=precision.image_ids[mask],
        image_names=[n for n, m in zip(precision.image_names, mask) if m],
        centres=precision.centres[mask], angles_deg=precision.angles_deg[mask],
        image_cov=precision.image_cov[mask],
        image_num_observations=precision.image_num_observations[mask])


def precision_subsets(rec: pycolmap.Reconstruction, subsets, priors: GNSSPriors | None = None,
                      options: SubsetOptions | None = None, *, source=None, inner: bool = True,
                      progress: bool = True) -> list[SubsetResult]:
    """Adjust every subset of `rec` (already in a metric frame when `priors` are given)."""
    options = options or SubsetOptions()
    specs = parse_subsets(subsets)
    for spec in specs:  # every glob is checked before the first (slow) adjustment
        select_images(rec, spec, source)
    return [adjust_subset(rec, spec, priors, options, source=source, inner=inner)
            for spec in tqdm(specs, desc="subsets", unit="subset", disable=not progress)]


def shared_points(results: list[SubsetResult]) -> dict[str, dict[str, int]]:
    """Tie points (by id) adjusted in both subsets (Mulder Table 5.3)."""
    ids = {r.name: set(r.precision.point_ids.tolist()) for r in results}
    return {a: {b: len(ids[a] & ids[b]) for b in ids} for a in ids}


# -- tables and plots ----------------------------------------------------------------------------

def _scale(metric: bool) -> tuple[float, str]:
    return (100.0, "cm") if metric else (1.0, "model units")


def table_rows(results: list[SubsetResult], datum: str = "solve", metric: bool = True
               ) -> list[list[str]]:
    """Per subset: name, images, tie points, s0, median sigma X Y Z, X0 Y0 Z0 (cm if metric)."""
    factor, _ = _scale(metric)
    spec = ".2f" if metric else ".4g"
    rows = []
    for r in results:
        point = np.median(r.point_sigmas(datum), 0) * factor
        centre = r.centre_sigmas(datum)
        centre = np.median(centre, 0) * factor if len(centre) else np.full(3, np.nan)
        rows.append([r.name, str(r.num_images), str(r.num_points),
                     f"{r.precision.variance.sigma0:.3f}"]
                    + [format(v, spec) for v in (*point, *centre)])
    return rows


HEADER = ["subset", "images", "tie points", "s0", "sX", "sY", "sZ", "sX0", "sY0", "sZ0"]


def text_table(results: list[SubsetResult], datum: str = "solve", metric: bool = True) -> str:
    """Fixed-width table: median sigmas of tie points and projection centres per subset."""
    rows = [HEADER] + table_rows(results, datum, metric)
    widths = [max(len(row[i]) for row in rows) for i in range(len(HEADER))]
    return "\n".join("  ".join(c.rjust(w) if i else c.ljust(w)
                               for i, (c, w) in enumerate(zip(row, widths))) for row in rows)


def markdown_report(results: list[SubsetResult], *, gauge_note: str, metric: bool,
                    datum: str = "solve") -> str:
    factor, unit = _scale(metric)

    def table(which: str) -> list[str]:
        out = ["| subset | images | tie points | s0 | sigma X | sigma Y | sigma Z | sigma X0 | "
               "sigma Y0 | sigma Z0 |", "|---|---|---|---|---|---|---|---|---|---|"]
        return out + ["| " + " | ".join(row) + " |" for row in table_rows(results, which, metric)]

    lines = ["# Precision of image subsets (Mulder Table 5.2)", "",
             f"Median a posteriori standard deviations ({unit}, scaled by each subset's s0^2) "
             "of the tie points (X, Y, Z) and projection centres (X0, Y0, Z0).", "",
             f"Gauge: {gauge_note}", "", "## Solve datum", ""] + table("solve")
    if all(r.inner is not None for r in results):
        lines += ["", "## Inner precision (S-transformed to the inner constraints of each "
                  "subset's tie points; gauge-free)", ""] + table("inner")
    lines += ["", "## Conditional tie point sigmas (poses held fixed: forward intersection)", "",
              "| subset | sigma X | sigma Y | sigma Z | mean rays per point |",
              "|---|---|---|---|---|"]
    for r in results:
        cond = np.median(r.precision.point_sigmas_conditional, 0) * factor
        rays = r.solve.count["image"] / 2 / max(r.num_points, 1)
        lines.append(f"| {r.name} | " + " | ".join(format(v, ".2f" if metric else ".4g")
                                                   for v in cond) + f" | {rays:.1f} |")
    shared = shared_points(results)
    names = [r.name for r in results]
    lines += ["", "## Shared tie points (Mulder Table 5.3)", "",
              "| | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
    for a in names:
        lines.append(f"| {a} | " + " | ".join(str(shared[a][b]) for b in names) + " |")
    notes = [f"- {r.name}: {len(r.restriction.dropped_images)} matched image(s) dropped with "
             f"fewer than the minimum tie points ({', '.join(r.restriction.dropped_images[:5])})"
             for r in results if r.restriction.dropped_images]
    notes += [f"- {r.name}: datum defect {r.precision.datum_defect} (minimum-norm sigmas)"
              for r in results if r.precision.datum_defect]
    if notes:
        lines += ["", "## Notes", ""] + notes
    lines += ["", f"The table printed by the command uses the {datum} datum."]
    return "\n".join(lines) + "\n"


def plot_sigma_maps(results: list[SubsetResult], datum: str = "solve", metric: bool = True
                    ) -> dict[str, bytes]:
    """Per subset: plan view of its tie points coloured by sigma X, Y, Z (Mulder Fig. 5.5),
    one colour scale per axis shared by all subsets, the same extent and origin for all maps
    (a long strip gets its three panels stacked)."""
    from .figures import new_figure, png_bytes

    factor, unit = _scale(metric)
    xy_all = np.vstack([np.vstack([r.precision.points[:, :2], r.precision.centres[:, :2]])
                        for r in results])
    centre = xy_all.mean(0)
    lo, hi = xy_all.min(0) - centre, xy_all.max(0) - centre
    pad = 0.02 * max(float(np.max(hi - lo)), 1e-9)
    lo, hi = lo - pad, hi + pad
    everything = np.vstack([r.point_sigmas(datum) for r in results]) * factor
    vmax = np.maximum(np.percentile(everything, COLOUR_PERCENTILE, axis=0), 1e-12)
    aspect = float((hi[0] - lo[0]) / max(hi[1] - lo[1], 1e-9))
    stacked = aspect > 2.0
    plots = {}
    for r in results:
        if stacked:  # panels ~8.5 in wide, their height set by the extent's aspect
            panel = min(max(8.5 / aspect, 1.2), 4.0)
            figure = new_figure(10, 4.0 * panel + 0.8)
            figure.subplots_adjust(top=1 - 0.5 / (4.0 * panel + 0.8), bottom=0.04, hspace=0.3)
        else:
            figure = new_figure(15, 4.6)
        xy = r.precision.points[:, :2] - centre
        sigma = r.point_sigmas(datum) * factor
        cams = r.precision.centres[:, :2] - centre
        for i, axis in enumerate("XYZ"):
            ax = figure.add_subplot(3, 1, i + 1) if stacked else figure.add_subplot(1, 3, i + 1)
            scatter = ax.scatter(xy[:, 0], xy[:, 1], c=sigma[:, i], s=2, cmap="viridis", vmin=0,
                                 vmax=vmax[i], rasterized=True)
            ax.plot(cams[:, 0], cams[:, 1], "r.", ms=2)
            ax.set_xlim(lo[0], hi[0])
            ax.set_ylim(lo[1], hi[1])
            ax.set_aspect("equal")
            ax.set_title(f"{r.name}: sigma {axis} ({unit}), median {np.median(sigma[:, i]):.3g}",
                         fontsize=9)
            ax.tick_params(labelsize=7)
            figure.colorbar(scatter, ax=ax, shrink=0.9, pad=0.01)
        figure.suptitle(f"tie point sigmas, {datum} datum ({r.num_images} images; red: "
                        "projection centres; axes: m from the common centre)", fontsize=10)
        plots[r.name] = png_bytes(figure)
    return plots


def plot_sigma_histograms(results: list[SubsetResult], datum: str = "solve",
                          metric: bool = True) -> bytes:
    """Histograms of the tie point sigmas per axis, one line per subset, medians dashed
    (Mulder Fig. 5.8)."""
    from .figures import new_figure, png_bytes

    factor, unit = _scale(metric)
    figure = new_figure(15, 4)
    everything = np.vstack([r.point_sigmas(datum) for r in results]) * factor
    for i, axis in enumerate("XYZ"):
        ax = figure.add_subplot(1, 3, i + 1)
        top = max(float(np.percentile(everything[:, i], COLOUR_PERCENTILE)), 1e-9)
        bins = np.linspace(0.0, top, 41)
        for k, r in enumerate(results):
            sigma = r.point_sigmas(datum)[:, i] * factor
            ax.hist(np.clip(sigma, 0, top), bins=bins, histtype="step", color=f"C{k}",
                    label=f"{r.name} (median {np.median(sigma):.3g})")
            ax.axvline(float(np.median(sigma)), color=f"C{k}", ls="--", lw=0.8)
        ax.set_xlabel(f"sigma {axis} ({unit})", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7)
    return png_bytes(figure)


# -- inputs and the CLI entry --------------------------------------------------------------------

def _utm_crs(lon: float, lat: float):
    from ..citymodel.crs import user_crs

    zone = int((lon + 180.0) // 6.0) % 60 + 1
    return user_crs(f"EPSG:{(32600 if lat >= 0 else 32700) + zone}")


def _read_database_priors(database, target):
    """GNSS from a COLMAP database, read from a temporary copy: opening a database with
    pycolmap rewrites the file (its checksum changes even when only pose priors are read), and
    inputs are never modified. Errors name the user's file."""
    import shutil
    import tempfile

    from ..block import gnss as rg
    from ..citymodel.crs import user_crs
    from ..errors import CityModelError

    source = Path(database)
    if not source.is_file():
        raise InputError("COLMAP database does not exist", source)
    with tempfile.TemporaryDirectory(prefix="colmap_citymodel_db_") as tmp:
        copy = Path(tmp) / source.name
        shutil.copyfile(source, copy)
        try:
            if target is not None:
                return rg.read_gnss_database(copy, target)
            first = rg.read_gnss_database(copy, user_crs("EPSG:4979"))
            if first.vertical_applied is None:  # CARTESIAN priors only: already metric
                return first
            lon, lat = first.positions[:, 0].mean(), first.positions[:, 1].mean()
            return rg.read_gnss_database(copy, _utm_crs(lon, lat))
        except CityModelError as error:
            raise type(error)(error.message, source) from None


def read_priors(rec: pycolmap.Reconstruction, *, database=None, gnss=None, gnss_crs=None,
                target_crs=None) -> tuple[GNSSPriors, np.ndarray, str] | None:
    """GNSS from one source, matched to the images and in a local metric frame; moves `rec`
    into that frame by a similarity (all images with GNSS). Returns (priors, origin, crs label)
    or None without a GNSS source. Geographic GNSS goes to `target_crs` or its UTM zone."""
    from ..align.georegister import estimate_georegistration
    from ..block import gnss as rg
    from ..citymodel.crs import user_crs

    if database and gnss:
        raise InputError("give one GNSS source, not --database and --gnss")
    if not database and not gnss:
        return None
    target = user_crs(target_crs) if target_crs else None
    if gnss:
        if not gnss_crs:
            raise InputError("--gnss needs --gnss_crs (e.g. EPSG:25832 or EPSG:4979)", gnss)
        if target is None:
            source = user_crs(gnss_crs)
            target = source if source.is_projected else None
        if target is None:  # geographic: read once to find the UTM zone
            first = rg.read_gnss_text(gnss, gnss_crs, user_crs(gnss_crs))
            lon, lat = first.positions[:, 0].mean(), first.positions[:, 1].mean()
            target = _utm_crs(lon, lat)
        observations = rg.read_gnss_text(gnss, gnss_crs, target)
    else:
        observations = _read_database_priors(database, target)
    origin = np.round(observations.positions.mean(0) / ORIGIN_ROUNDING) * ORIGIN_ROUNDING
    image_ids, positions, sigmas = rg.match_to_reconstruction(observations, rec, origin)
    registration = estimate_georegistration(rec, positions, image_ids, sigmas=sigmas)
    rec.transform(registration.sim3)
    label = (observations.crs.label if observations.vertical_applied is not None or gnss
             else "the database's CARTESIAN frame")
    logger.info("moved the block to %d GNSS positions (%s minus origin %s): scale %.4f, RMS "
                "%.2f m", len(image_ids), label, origin.tolist(), registration.sim3.scale,
                registration.rms)
    return GNSSPriors(image_ids, positions, sigmas), origin, label


def write_outputs(results: list[SubsetResult], output_path, report: dict, markdown: str,
                  datum: str, metric: bool, offset: np.ndarray) -> Path:
    """precision_subsets.json, precision_subsets.md, per subset <name>_sigma_map.png,
    <name>_images.csv and <name>_points.ply, and sigma_histograms.png, into a new directory."""
    from ..files import atomic_directory
    from .report import write_image_csv, write_point_ply

    output_path = Path(output_path)
    maps = plot_sigma_maps(results, datum, metric)
    with atomic_directory(output_path) as tmp:
        (tmp / "precision_subsets.json").write_text(json.dumps(report, indent=2))
        (tmp / "precision_subsets.md").write_text(markdown)
        for r in results:
            (tmp / f"{r.name}_sigma_map.png").write_bytes(maps[r.name])
            write_image_csv(tmp / f"{r.name}_images.csv", r.precision, offset)
            rec = r.reconstruction
            rays = np.array([rec.point3D(int(i)).track.length() for i in r.precision.point_ids])
            write_point_ply(tmp / f"{r.name}_points.ply", r.precision, offset, rays)
        (tmp / "sigma_histograms.png").write_bytes(plot_sigma_histograms(results, datum, metric))
    return output_path


def main(input_path, subsets: list[str], *, output_path=None, database=None, gnss=None,
         gnss_crs=None, target_crs=None, datum: str = "solve", max_images: int | None = None,
         as_json: bool = False, progress: bool = True) -> dict:
    """`colmap-citymodel precision`: adjust each image subset of the model in `input_path`
    and compare the median sigmas of tie points and projection centres (Mulder Table 5.2).

    Prints a table (or JSON); with `output_path` writes a new directory with the JSON, a
    Markdown table, sigma maps (Mulder Fig. 5.5), histograms (Fig. 5.8), per-image CSVs and
    per-point PLYs. Returns the report dict."""
    from ..block.reconstruction import read_reconstruction

    if datum not in ("solve", "inner"):
        raise InputError(f"--datum must be solve or inner, not {datum!r}")
    specs = parse_subsets(subsets)
    options = SubsetOptions()
    if max_images is not None:
        if max_images < options.min_images:
            raise InputError(f"--max_images must be at least {options.min_images}")
        options.max_images = int(max_images)
    if output_path is not None:  # fail on a taken output directory before the slow part
        from ..files import atomic_directory

        with atomic_directory(output_path):
            pass
        Path(output_path).rmdir()
    input_path = Path(input_path)
    rec = read_reconstruction(input_path)
    for spec in specs:
        select_images(rec, spec, input_path)
    gnss_frame = read_priors(rec, database=database, gnss=gnss, gnss_crs=gnss_crs,
                             target_crs=target_crs)
    if gnss_frame is not None:
        priors, origin, crs_label = gnss_frame
        metric = True
        gauge_note = (f"GNSS priors of each subset's images ({len(priors)} positions in "
                      f"{crs_label}; the block moved to them by a similarity first); sigmas "
                      "include the uncertainty of this GNSS datum")
    else:
        priors = None
        georeference = input_path / "georeference.json"
        metric = georeference.is_file()
        # Keep coordinates small (a refine output is in CRS coordinates): shift only.
        centres = np.array([rec.image(i).projection_center() for i in rec.reg_image_ids()])
        origin = np.round(centres.mean(0) / ORIGIN_ROUNDING) * ORIGIN_ROUNDING
        rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), -origin))
        gauge_note = ("fixed as COLMAP's BA does (TWO_CAMS_FROM_WORLD): the pose of each "
                      "subset's first image and one coordinate of a second image's position "
                      "are held; sigmas are relative to those images, which get none")
        if not metric:
            gauge_note += "; units are the input model's (no GNSS, no georeference.json)"
    results = precision_subsets(rec, specs, priors, options, source=input_path,
                                progress=progress)
    _, unit = _scale(metric)
    markdown = markdown_report(results, gauge_note=gauge_note, metric=metric, datum=datum)
    report = {
        "inputs": {"input_path": str(input_path), "database": str(database) if database else None,
                   "gnss": str(gnss) if gnss else None, "gnss_crs": gnss_crs,
                   "subsets": {s.name: list(s.patterns) for s in specs}},
        "gauge": "gnss" if priors is not None else "fixed", "gauge_note": gauge_note,
        "units": "m" if metric else "model units", "origin": origin.tolist(),
        "table_datum": datum, "options": dataclasses.asdict(options),
        "subsets": [r.summary() for r in results], "shared_points": shared_points(results),
    }
    if output_path is not None:
        write_outputs(results, output_path, report, markdown, datum, metric, origin)
    if as_json:
        print(json.dumps(report, indent=2))
    else:
        print(f"median sigmas ({unit}) of tie points (X Y Z) and projection centres "
              f"(X0 Y0 Z0), {datum} datum; gauge: {report['gauge']}")
        print(text_table(results, datum, metric))
        if output_path is not None:
            print(f"output: {output_path} (precision_subsets.md/.json, sigma maps, histograms)")
    return report
