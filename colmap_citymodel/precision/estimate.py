"""A posteriori precision of an adjustment: variance factor, global test, covariances.

Method.md sections 7 and 9 (Unger eq. 12-14, Mulder eq. 2.7). For a (hybrid) bundle adjustment
with whitened residuals v (each divided by its a priori sigma, so P = I):

- variance factor s0^2 = v^T P v / r with the redundancy r = n - u (n observations, u unknowns
  in the tangent space); per observation group g: s0_g^2 = v_g^T P v_g / r_g;
- r_g is either the sum of the redundancy numbers r_i = 1 - (J Q J^T)_ii of the group's
  observations ("hat_matrix", exact at the solution; needs the cofactor matrix Q = N^-1), or
  the share n_g / n * r ("proportional", an approximation used when covariances are skipped;
  it over-states r_g for groups that mostly determine their own unknowns, e.g. f_VT);
- global model test: T = v^T P v ~ chi^2(r) under H0 "the a priori sigmas are right" (sigma0
  a priori = 1); two-sided at level alpha, so both optimistic and pessimistic sigmas fail;
- covariances Sigma = s0^2 Q in the tangent space of every parameter block.

Q is computed by Schur elimination of the tie points from the normal matrix N = J^T J:

    N = [[U, E^T], [E, W]]    c = cameras/poses, planes, vertices, intrinsics; p = points
    S = U - E^T W^-1 E,  Q_cc = S^-1
    Q_pp (point i, marginal)    = W_i^-1 + W_i^-1 E_i Q_cc E_i^T W_i^-1
    Q_pp (point i, conditional) = W_i^-1            (all other unknowns held fixed)

`pycolmap.estimate_ba_covariance_from_problem` does the same elimination (verified equal in
tests/test_precision_estimate.py, also with our plane and vertex blocks in the problem, which keep the
Schur structure: every residual touches at most one point), but its `get_point_cov` is the
*conditional* W_i^-1 and it exposes no camera-plane cross covariances, which the marginal point
covariance needs; so the numbers reported here come from our own sparse normal matrix built from
`problem.evaluate_jacobian`, and both point covariances are kept (`point_cov` marginal,
`point_cov_conditional`). Poses: frame tangent [rotation (left perturbation, camera frame, half
angles as in Ceres' EigenQuaternionManifold), translation] propagated to projection centres
X0, Y0, Z0 and omega, phi, kappa in the model frame (local = CRS minus origin, same axes).

Above DENSE_MAX_UNKNOWNS camera-side unknowns S is assembled per level of its coupling and Q_cc
is held only where the covariances need it (precision.selected, precision.point_cofactors:
selected inversion, exact there), with products Q_cc x for everything else.

The datum (adjust.observability) rests on errors the covariances do not all hold (GNSS's bias,
the model's common shift): `datum_shift` adds a shift common to the block so that no image
centre is stated more precise than the datum's sigma of a shift.

Check points (`checkpoint_cofactors`): triangulated with the adjusted poses and, for their
covariance, eliminated like tie points with their own image observations in the normal system
(never on planes, never control): marginal, i.e. with the pose, plane and datum uncertainty.

Generalisation (`generalisation_effects`, Unger 6.3): the classical model treats f_dTP errors as
independent, so a plane's systematic deviation averages out with its number of points and
check point sigmas come out 3-19x too small (Table 12). With sigma_generalisation, the errors of
a plane's f_dTP share an offset o_p ~ N(0, sigma^2) and a tilt (the tilt of a plane whose
vertices are each off by sigma, adjust.observability.face_tilts), which are not estimated but
propagated (consider parameters): Sigma_aware = s0^2 Q + sigma^2 sum_p sum_k dx_pk dx_pk^T,
dx_pk the estimate's response to o_p = 1 m and to each of the plane's two principal tilts at
sigma = 1 m. Estimating the o_p instead (HybridProblem(generalisation_offsets=True))
lets the block shrink against the model (errors-in-variables: the tie points' real relief
about their planes shrinks with it), hence experimental.

Variance components (variance_components.py, Foerstner): iterated
s_g^2 = v_g^T P v_g / r_g with the hat-matrix redundancies, refine's optional last step.

COLMAP's reprojection residuals are in pixels and unweighted; HybridProblem gives our cost
functions their sigmas divided by sigma_image, so every group is evaluated in units of
sigma_image and is whitened here by dividing by it (as `HybridProblem.group_residuals` does);
solve weights and the stated stochastic model agree for any sigma_image.
"""

from __future__ import annotations

import copy
import logging
import os
import time
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
import pyceres
import pycolmap
import scipy.linalg
import scipy.sparse as sp
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from ..adjust.problem import GROUPS, HybridProblem

logger = logging.getLogger(__name__)

#: Rows of the point-camera block processed at once (memory ~ rows x camera unknowns x 8 B).
CHUNK_ROWS = 6000
#: Camera-side unknowns up to which `cofactors` inverts the reduced normal matrix densely
#: ("auto"); above, by selected inversion (precision.selected), exact on its pattern.
DENSE_MAX_UNKNOWNS = 1000
#: ... and up to which a singular one (a datum defect) falls back to the dense pseudo-inverse.
DENSE_FALLBACK_MAX = 6000
#: BLAS threads of the precision step: its dense blocks are a few hundred unknowns wide, where
#: more threads gain little on an idle machine and lose many times over on a busy one.
BLAS_THREADS = 1
#: Relative eigenvalue below which the reduced normal matrix counts as singular (datum defect).
RANK_TOLERANCE = 1e-12
#: Step of the numerical derivative of X0 and omega/phi/kappa w.r.t. the pose tangent.
POSE_STEP = 1e-6
#: Observation groups reported only when the problem has them (the generalisation priors,
#: the baseline priors that hold the scale, ground control marks).
OPTIONAL_GROUPS = ("gen", "scale", "offset", "pose", "gcp")
#: COLMAP camera axes (x right, y down, z forward) -> photogrammetric (x right, y up, z back).
PHOTOGRAMMETRIC_FLIP = np.diag([1.0, -1.0, -1.0])


# -- variance factor and global test -----------------------------------------------------------

@dataclass
class GlobalTest:
    """Two-sided chi-square test of v^T P v against its redundancy (sigma0 a priori = 1)."""

    statistic: float
    redundancy: float
    p_value: float
    alpha: float
    lower: float  # acceptance interval of the statistic
    upper: float
    accepted: bool

    def todict(self) -> dict:
        return {"statistic": self.statistic, "redundancy": self.redundancy,
                "p_value": self.p_value, "alpha": self.alpha,
                "acceptance_interval": [self.lower, self.upper], "accepted": self.accepted,
                "h0": "a priori sigmas correct (sigma0 = 1); two-sided chi-square test"}


def global_test(vtpv: float, redundancy: float, alpha: float = 0.05) -> GlobalTest:
    """Global model test: T = v^T P v ~ chi^2(r) if the functional and stochastic models hold."""
    if redundancy <= 0:
        raise ValueError(f"the global test needs a positive redundancy, got {redundancy}")
    lower = float(chi2.ppf(alpha / 2, redundancy))
    upper = float(chi2.ppf(1 - alpha / 2, redundancy))
    p_value = float(min(1.0, 2 * min(chi2.cdf(vtpv, redundancy), chi2.sf(vtpv, redundancy))))
    return GlobalTest(float(vtpv), float(redundancy), p_value, alpha, lower, upper,
                      bool(lower <= vtpv <= upper))


@dataclass
class VarianceFactors:
    """s0^2 overall and per observation group, with the redundancy used for each."""

    sigma0_squared: float
    vtpv: float
    redundancy: float
    count: dict[str, int]
    vtpv_by_group: dict[str, float]
    redundancy_by_group: dict[str, float]
    method: str  # "hat_matrix" or "proportional"
    test: GlobalTest | None

    @property
    def sigma0(self) -> float:
        return float(np.sqrt(self.sigma0_squared))

    @property
    def sigma0_by_group(self) -> dict[str, float | None]:
        return {g: (float(np.sqrt(self.vtpv_by_group[g] / r)) if r > 0 else None)
                for g, r in self.redundancy_by_group.items()}

    def todict(self) -> dict:
        return {"sigma0": self.sigma0, "sigma0_by_group": self.sigma0_by_group,
                "vtpv": self.vtpv, "redundancy": self.redundancy,
                "count_by_group": self.count, "vtpv_by_group": self.vtpv_by_group,
                "redundancy_by_group": self.redundancy_by_group,
                "redundancy_method": self.method,
                "global_test": self.test.todict() if self.test else None}


def variance_factors(residuals: dict[str, np.ndarray], num_unknowns: int,
                     redundancy_by_group: dict[str, float] | None = None,
                     alpha: float = 0.05) -> VarianceFactors:
    """s0^2 = v^T P v / (n - u) overall and per group from whitened residuals.

    Without `redundancy_by_group` (redundancy numbers summed per group) the group redundancy is
    the proportional share n_g / n * r, an approximation. Optional groups (`OPTIONAL_GROUPS`)
    without observations are left out."""
    residuals = {g: v for g, v in residuals.items() if len(v) or g not in OPTIONAL_GROUPS}
    count = {g: int(len(v)) for g, v in residuals.items()}
    vtpv_g = {g: float(np.sum(np.square(v))) for g, v in residuals.items()}
    n = sum(count.values())
    vtpv = sum(vtpv_g.values())
    if redundancy_by_group is None:
        r = float(n - num_unknowns)
        method = "proportional"
        redundancy_by_group = {g: (c / n * r if n else 0.0) for g, c in count.items()}
    else:
        method = "hat_matrix"
        redundancy_by_group = {g: float(redundancy_by_group.get(g, 0.0)) for g in count}
        r = float(sum(redundancy_by_group.values()))
    s0sq = vtpv / r if r > 0 else float("nan")
    test = global_test(vtpv, r, alpha) if r > 0 else None
    return VarianceFactors(s0sq, vtpv, r, count, vtpv_g, redundancy_by_group, method, test)


# -- covariances ---------------------------------------------------------------------------------

@dataclass
class _Layout:
    """Column layout of the Jacobian: camera-side blocks first, then one block per point."""

    blocks: list[np.ndarray]
    names: list[tuple[str, int]]  # ("frame", frame_id), ("camera", id), ("plane_normal", k) ...
    starts: list[int]
    sizes: list[int]
    num_c: int
    point_ids: np.ndarray

    @cached_property
    def _by_name(self) -> dict[tuple[str, int], slice]:
        """Name -> columns, the first of equal names."""
        out: dict[tuple[str, int], slice] = {}
        for name, s, n in zip(self.names, self.starts, self.sizes):
            out.setdefault(name, slice(s, s + n))
        return out

    def columns(self, kind: str, key: int) -> slice | None:
        return self._by_name.get((kind, key))


def _layout(problem: HybridProblem) -> _Layout:
    rec = problem.reconstruction
    ceres = problem.problem
    blocks, names, sizes = [], [], []
    known = 0

    def add(kind: str, key: int, block: np.ndarray) -> None:
        nonlocal known
        if not ceres.has_parameter_block(block):
            return
        known += 1
        if ceres.is_parameter_block_constant(block):
            return
        blocks.append(block)
        names.append((kind, key))
        sizes.append(int(ceres.parameter_block_tangent_size(block)))

    for frame_id in sorted({rec.image(i).frame_id for i in rec.reg_image_ids()}):
        add("frame", frame_id, rec.frame(frame_id).rig_from_world.params)
    for rig_id, rig in rec.rigs.items():
        for sensor_id, sensor_from_rig in rig.non_ref_sensors.items():
            add("sensor", rig_id * 1000 + int(sensor_id.id), sensor_from_rig.params)
    for camera_id, camera in rec.cameras.items():
        add("camera", camera_id, camera.params)
    b = problem.blocks
    for k in range(len(b.faces)):
        add("plane_normal", k, b.normals[k])
        add("plane_offset", k, b.offsets[k])
    for k in range(len(b.generalisation)):
        add("plane_generalisation", k, b.generalisation[k])
    for k in range(len(b.vertex_ids)):
        add("vertex", k, b.vertices[k])
    if problem.gnss_offset is not None:
        add("gnss_offset", 0, problem.gnss_offset)
    for k, point in enumerate(problem.marks.points if problem.marks is not None else []):
        add("mark", k, point)  # ground control marks (adjust.marks)
    for k in range(len(b.held_normals)):  # constant: the given planes that model correction keeps
        add("held_normal", k, b.held_normals[k])
        add("held_offset", k, b.held_offsets[k])
    num_c = int(sum(sizes))
    point_ids = []
    for point_id in rec.point3D_ids():
        before = len(blocks)
        add("point", int(point_id), rec.point3D(point_id).xyz)
        if len(blocks) > before:
            point_ids.append(int(point_id))
    if known != ceres.num_parameter_blocks():
        raise RuntimeError(f"the problem has {ceres.num_parameter_blocks()} parameter blocks, "
                           f"only {known} are known to the precision estimator")
    if any(s != 3 for s in sizes[len(sizes) - len(point_ids):]):
        raise RuntimeError("tie point blocks must have 3 free coordinates")
    starts = list(np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int)) if sizes else []
    return _Layout(blocks, names, starts, sizes, num_c, np.array(point_ids, np.int64))


def whitened_jacobian(problem: HybridProblem, layout: _Layout | None = None, *,
                      relax_holds: bool = True) -> tuple[sp.csr_matrix, _Layout]:
    """The Jacobian of the whitened residuals (rows in `GROUPS` order, loss functions not
    applied) w.r.t. the tangent spaces of the variable blocks, in `layout` column order.
    `relax_holds=False`: the holds weighted as in the solve (the estimator's own weights)."""
    layout = layout or _layout(problem)
    evaluate = pyceres.EvaluateOptions()
    evaluate.apply_loss_function = False
    threads = problem.options.num_threads  # the solve's threads (the same Jacobian)
    evaluate.num_threads = threads if threads > 0 else (os.cpu_count() or 1)
    evaluate.set_parameter_blocks(layout.blocks)
    crs = problem.problem.evaluate_jacobian(evaluate)
    # pyceres hands lists over; a given dtype converts them in one pass
    jacobian = sp.csr_matrix((np.array(crs.values, np.float64), np.array(crs.cols, np.int64),
                              np.array(crs.rows, np.int64)), shape=(crs.num_rows, crs.num_cols))
    # Every group is evaluated in units of sigma_image (see adjust.problem's docstring).
    factors = np.full(jacobian.shape[0], 1.0 / problem.options.sigma_image)
    relaxation = problem.hold_relaxation
    if len(relaxation) and relax_holds:
        # The holds of what the planes do not fix (the scale, the height) count at GNSS's sigma
        # of it, not at the tighter one that keeps the solve there.
        first = sum(problem.counts[g] for g in GROUPS[:GROUPS.index("scale")])
        factors[first:first + len(relaxation)] *= relaxation
    jacobian.data *= np.repeat(factors, np.diff(jacobian.indptr))  # rows scaled in place
    return jacobian, layout


@dataclass
class Cofactors:
    """Unscaled cofactor matrices (Q = N^-1 of the whitened problem) and redundancy numbers."""

    layout: _Layout
    q_cc: np.ndarray  # (num_c, num_c) camera-side unknowns, dense (or a SelectedInverse)
    q_points: np.ndarray  # (P, 3, 3) marginal
    q_points_conditional: np.ndarray  # (P, 3, 3) W_i^-1
    redundancy_by_group: dict[str, float]
    datum_defect: int
    seconds: float
    system: tuple | None = None  # (j_c, j_p, b = W^-1 E, w_inv) when asked to keep them
    normal: sp.csr_matrix | None = None  # the reduced normal matrix S, with `system`
    far_rows: np.ndarray | None = None  # rows of J left out of `normal` (selected: low rank)


def _block_diagonal_3x3(matrix: sp.spmatrix, num: int) -> np.ndarray:
    matrix = matrix.tocsr()
    index = np.arange(num) * 3
    out = np.empty((num, 3, 3))
    for i in range(3):
        for j in range(3):
            out[:, i, j] = np.asarray(matrix[index + i, index + j]).ravel()
    return out


def _bsr_blocks(blocks: np.ndarray) -> sp.bsr_matrix:
    num = len(blocks)
    return sp.bsr_matrix((blocks, np.arange(num), np.arange(num + 1)), shape=(3 * num, 3 * num))


def _inverse(s: np.ndarray) -> tuple[np.ndarray, int]:
    """Inverse of the symmetric reduced normal matrix; a pseudo-inverse with the number of
    zero eigenvalues when it is singular (a datum defect: free network)."""
    try:
        factor = scipy.linalg.cho_factor(s, lower=True)
        q = scipy.linalg.cho_solve(factor, np.eye(len(s)))
        return 0.5 * (q + q.T), 0
    except np.linalg.LinAlgError:
        values, vectors = np.linalg.eigh(s)
        keep = values > RANK_TOLERANCE * max(values.max(), 1.0)
        defect = int(np.count_nonzero(~keep))
        logger.warning("the normal matrix is singular (datum defect %d): covariances of a "
                       "minimum-norm (free network) solution", defect)
        q = (vectors[:, keep] / values[keep]) @ vectors[:, keep].T
        return q, defect


def cofactors(problem: HybridProblem, *, redundancy: bool = True, keep_system: bool = False,
              points: bool = True, relax_holds: bool = True, method: str = "auto"
              ) -> Cofactors:
    """Q_cc, marginal and conditional point cofactors and (optionally) the redundancy numbers
    summed per observation group, all by Schur elimination of the tie points. `keep_system`
    keeps the Jacobian's camera and point columns and W^-1 E for `generalisation_effects`.
    `points=False` (with redundancy=False): Q_cc without the points' marginal cofactors
    (`q_points` then holds the conditional ones). `relax_holds`: see `whitened_jacobian`.
    `method`: "dense" (Q_cc a dense array), "selected" (a `SelectedInverse`: Q_cc where the
    covariances need it, and products with it) or "auto" (dense up to DENSE_MAX_UNKNOWNS)."""
    start = time.perf_counter()
    jacobian, layout = whitened_jacobian(problem, relax_holds=relax_holds)
    nc = layout.num_c
    num_points = len(layout.point_ids)
    jacobian = jacobian.tocsr()
    j_c = jacobian[:, :nc]
    j_p = jacobian[:, nc:]
    e = (j_p.T.tocsr() @ j_c).tocsr()  # (3P, nc)
    w = _block_diagonal_3x3(j_p.T @ j_p, num_points)
    w_inv = np.linalg.inv(w) if num_points else w
    b = (_bsr_blocks(w_inv) @ e).tocsr() if num_points else sp.csr_matrix((0, nc))
    selected = method == "selected" or (method == "auto" and nc > DENSE_MAX_UNKNOWNS)
    bounds, first = {}, 0
    for g in GROUPS:
        bounds[g] = (first, first + problem.counts[g])
        first += problem.counts[g]
    n_blocks = len(layout.sizes) - num_points
    far = _far_rows(j_c, bounds, layout, n_blocks) if selected else np.zeros(0, np.int64)
    near = _other_rows(j_c.shape[0], far) if len(far) else slice(None)
    j_near = j_c[near]
    q_cc = None
    if selected:
        from .point_cofactors import reduced_normal
        from .selected import SelectedInverse

        s, levels = reduced_normal((j_near.T @ j_near).tocsr(), e, b,
                                   np.asarray(layout.starts[:n_blocks], np.int64),
                                   np.asarray(layout.sizes[:n_blocks], np.int64), w_inv)
        try:
            q_cc = SelectedInverse(0.5 * (s + s.T), layout.starts[:n_blocks],
                                   layout.sizes[:n_blocks], low_rank=j_c[far], levels=levels)
        except np.linalg.LinAlgError:  # singular: a datum defect, for the pseudo-inverse
            if method == "selected" or nc > DENSE_FALLBACK_MAX:
                raise
            logger.info("precision: the reduced normal matrix is singular; dense inverse")
    if q_cc is not None:
        defect = 0
        logger.info("precision: selected inverse of %d camera-side unknowns, %d levels (widest "
                    "%d), border %d, %.1f s", nc, q_cc.num_levels, max(q_cc.sizes, default=0),
                    len(q_cc.levels.border), time.perf_counter() - start)
        q_points, trace = _selected_point_terms(q_cc, j_c, j_p, b, e, w_inv, bounds,
                                                redundancy, points, far)
    else:
        s = (j_c.T @ j_c) - e.T @ b
        s = s.toarray()
        q_cc, defect = _inverse(0.5 * (s + s.T))
        q_points, trace = _dense_point_terms(q_cc, j_c, j_p, b, w_inv, bounds, redundancy,
                                             points)
    redundancy_by_group = ({g: (hi - lo) - trace.get(g, 0.0) for g, (lo, hi) in bounds.items()}
                           if redundancy else {})
    return Cofactors(layout, q_cc, q_points, w_inv, redundancy_by_group, defect,
                     time.perf_counter() - start,
                     (j_c, j_p, b, w_inv) if keep_system else None,
                     sp.csr_matrix(s) if keep_system else None,
                     far if q_cc is not None and not isinstance(q_cc, np.ndarray) else None)


def _other_rows(num: int, rows: np.ndarray) -> np.ndarray:
    """The indices below `num` that are not in `rows`, sorted (setdiff1d without a sort)."""
    keep = np.ones(num, bool)
    keep[rows] = False
    return np.flatnonzero(keep)


def _far_rows(j_c: sp.csr_matrix, bounds: dict, layout: _Layout, n_blocks: int) -> np.ndarray:
    """Rows of the holds (group "scale") that couple two parameter blocks (baselines between
    images half the block apart): for the selected inverse, a low-rank term."""
    lo, hi = bounds["scale"]
    if hi == lo:
        return np.zeros(0, np.int64)
    block_of = np.repeat(np.arange(n_blocks), layout.sizes[:n_blocks])
    rows = j_c[lo:hi]
    counts = np.diff(rows.indptr)
    blocks = block_of[rows.indices]
    nonempty = counts > 0
    first = rows.indptr[:-1][nonempty]
    spans = np.zeros(hi - lo, bool)
    spans[nonempty] = (np.minimum.reduceat(blocks, first)
                       != np.maximum.reduceat(blocks, first))
    return lo + np.flatnonzero(spans)


def solve_weighted(problem: HybridProblem, cof: Cofactors) -> Cofactors:
    """`cof` (kept with its system, holds relaxed) re-weighted to the solve's own holds
    (`whitened_jacobian(relax_holds=False)`): the holds' rows touch camera-side unknowns only,
    so S changes by J_h^T (1/f^2 - 1) J_h (f the relaxation factors) and nothing else does;
    with every hold row in the selected inverse's low-rank term, S stays and only that term
    is scaled. Falls back to a new `cofactors` where that does not hold. No point cofactors."""
    relaxation = problem.hold_relaxation
    first = sum(problem.counts[g] for g in GROUPS[:GROUPS.index("scale")])
    rows = slice(first, first + len(relaxation))
    if cof.system is None or cof.normal is None or not np.all(relaxation > 0) \
            or cof.system[1][rows].nnz:
        return cofactors(problem, redundancy=False, keep_system=True, points=False,
                         relax_holds=False)
    start = time.perf_counter()
    j_c = cof.system[0]
    far = np.zeros(0, np.int64) if cof.far_rows is None else cof.far_rows - first
    near = _other_rows(len(relaxation), far)
    layout = cof.layout
    if not len(near) and not isinstance(cof.q_cc, np.ndarray):  # S itself is the same
        return Cofactors(layout, cof.q_cc.with_low_rank_scaled(1.0 / relaxation[far]),
                         cof.q_points_conditional, cof.q_points_conditional, {}, 0,
                         time.perf_counter() - start, cof.system, None)
    held = j_c[first + near]
    s = cof.normal + held.T @ sp.diags(1.0 / relaxation[near] ** 2 - 1.0) @ held
    s = 0.5 * (s + s.T)
    if isinstance(cof.q_cc, np.ndarray):
        q_cc, defect = _inverse(s.toarray())
    else:
        from .selected import SelectedInverse

        n_blocks = len(layout.sizes) - len(layout.point_ids)
        q_cc, defect = SelectedInverse(
            s, layout.starts[:n_blocks], layout.sizes[:n_blocks],
            low_rank=sp.diags(1.0 / relaxation[far]) @ j_c[first + far]), 0
    return Cofactors(layout, q_cc, cof.q_points_conditional, cof.q_points_conditional, {},
                     defect, time.perf_counter() - start, cof.system, None)


def _dense_point_terms(q_cc, j_c, j_p, b, w_inv, bounds, redundancy, points
                       ) -> tuple[np.ndarray, dict[str, float]]:
    """Marginal point cofactors and the groups' traces of J Q J^T with a dense Q_cc."""
    num_points = len(w_inv)
    with_points = {}
    trace = {}
    for g, (lo, hi) in bounds.items():
        if not redundancy or hi == lo:
            continue
        jc_g, jp_g = j_c[lo:hi], j_p[lo:hi]
        trace[g] = float((jc_g.T @ jc_g).multiply(q_cc).sum())
        if jp_g.nnz:
            with_points[g] = ((jp_g.T @ jc_g).tocsr(), _block_diagonal_3x3(jp_g.T @ jp_g,
                                                                          num_points))
    q_points = np.zeros((num_points, 3, 3))
    chunk = max(1, CHUNK_ROWS // 3)
    for lo in range(0, num_points if points or with_points else 0, chunk):
        hi = min(num_points, lo + chunk)
        b_chunk = b[3 * lo:3 * hi]
        m = np.asarray(b_chunk @ q_cc)  # = -Q_pc for these points
        for i in range(3):
            for j in range(3):
                q_points[lo:hi, i, j] = np.asarray(b_chunk[j::3].multiply(m[i::3]).sum(1)).ravel()
        for g, (e_g, _) in with_points.items():
            trace[g] -= 2.0 * float(e_g[3 * lo:3 * hi].multiply(m).sum())
    q_points += w_inv
    for g, (_, w_g) in with_points.items():
        trace[g] += float(np.einsum("kij,kji->", q_points, w_g))
    return q_points, trace


def _selected_point_terms(q_cc, j_c, j_p, b, e, w_inv, bounds, redundancy, points, far
                          ) -> tuple[np.ndarray, dict[str, float]]:
    """The same as `_dense_point_terms` from a `SelectedInverse` (point_cofactors); the
    `far` rows' traces from its low-rank term."""
    from .point_cofactors import point_terms

    num_points = len(w_inv)
    trace, e_groups, w_groups = {}, {}, {}
    for g, (lo, hi) in bounds.items():
        if not redundancy or hi == lo:
            continue
        jc_g, jp_g = j_c[lo:hi], j_p[lo:hi]
        inside = far[(far >= lo) & (far < hi)] - lo
        if len(inside):
            jc_g = j_c[lo + _other_rows(hi - lo, inside)]
        trace[g] = q_cc.trace_with(jc_g.T @ jc_g)
        if len(inside):
            trace[g] += q_cc.low_rank_trace()
        if jp_g.nnz:
            e_groups[g] = jp_g
            w_groups[g] = _block_diagonal_3x3(jp_g.T @ jp_g, num_points)
    if e_groups:  # E_g = J_p,g^T J_c,g; the largest group's as E minus the others'
        largest = max(e_groups, key=lambda g: e_groups[g].nnz)
        for g in e_groups:
            if g != largest:
                lo, hi = bounds[g]
                e_groups[g] = (e_groups[g].T @ j_c[lo:hi]).tocsr()
        others = [e_groups[g] for g in e_groups if g != largest]
        e_groups[largest] = (e - sum(others)).tocsr() if others else e
    if not (points or e_groups):
        return np.array(w_inv, copy=True), trace
    q_points, point_traces, _ = point_terms(q_cc, b, w_inv, e_groups)
    for g, w_g in w_groups.items():
        trace[g] += point_traces[g] + float(np.einsum("kij,kji->", q_points, w_g))
    return q_points, trace


# -- generalisation as consider parameters -------------------------------------------------------

@dataclass
class GeneralisationEffects:
    """Effect of a 1 m offset o_p of each assigned plane's true surface (all its f_dTP
    observations off by the same o_p) and of its tilts (at sigma = 1 m) on the estimate;
    `points_cov` already times sigma^2."""

    faces: np.ndarray  # (F,)
    # (nc, 3F) change of the camera-side unknowns: per metre of o_p (columns 0..F-1), then per
    # plane its two principal tilts at sigma = 1 m (columns F + 2p, F + 2p + 1)
    camera: np.ndarray
    points_cov: np.ndarray  # (P, 3, 3) sigma^2 sum_p d_i,p d_i,p^T of the tie points
    sigma: float  # the sigma used: the given one, or the estimate when asked for
    sigma_prior: float | None = None
    sigma_estimated: float | None = None
    num_points: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # per plane
    mean_residuals: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per plane (m)


def generalisation_effects(problem: HybridProblem, cof: Cofactors, sigma: float | None,
                           *, estimate: bool = False, s0_squared: float = 1.0,
                           residuals: dict[str, np.ndarray] | None = None
                           ) -> GeneralisationEffects:
    """The generalisation-aware stochastic model for the classical estimate: the f_dTP errors
    of plane p share an offset o_p ~ N(0, sigma^2) that the adjustment does not estimate
    (a consider parameter). The estimate responds linearly, dx = -N^-1 J^T (o_p / sigma_dTP)
    1_p (1_p: plane p's f_dTP rows, whitened), so its covariance gains
    sigma^2 sum_p dx_p dx_p^T. By Schur elimination: with g = J^T 1_p / sigma_dTP,
    dx_c = Q_cc (g_c - E^T W^-1 g_p) and dx_points = W^-1 g_p - W^-1 E dx_c.
    The plane's tilts are consider parameters the same way, with the f_dTP rows' lever
    (their point's in-plane offset from the face's vertex centroid along each principal tilt
    axis, times that tilt's sigma at sigma = 1 m) in place of 1_p: a facade's thousands of
    points share its azimuth error as they share its offset.

    Independent f_dTP errors average out with the number of points of a plane, a shared
    offset does not: this is what keeps check point sigmas from being 3-19x too small
    (Unger Table 12) while the estimate stays the classical one.

    `estimate`: sigma from the data (a variance component of the offsets, by moments): with
    t_p = 1_p^T v (v the whitened residuals) and M = [1_p^T R 1_q], R = I - J N^-1 J^T,
    E[sum_p t_p^2] = sigma^2 ||M||_F^2 + s0^2 tr M, so
    sigma^2 = max(0, (sum t_p^2 - s0^2 tr M) / ||M||_F^2); `sigma` is then only the fallback
    when there are no planes. `residuals`: `problem.group_residuals()` when known."""
    if cof.system is None:
        raise ValueError("cofactors(problem, keep_system=True) is needed")
    j_c, j_p, b, w_inv = cof.system
    faces = np.asarray(problem.blocks.faces, np.int64)
    num_points = len(cof.layout.point_ids)
    prior = sigma
    if not len(faces) or not problem.counts["dTP"]:
        return GeneralisationEffects(faces, np.zeros((cof.layout.num_c, 0)),
                                     np.zeros((num_points, 3, 3)), float(sigma or 0.0), prior)
    first = sum(problem.counts[g] for g in GROUPS[:GROUPS.index("dTP")])
    slot = {int(f): k for k, f in enumerate(faces)}
    rows = first + np.arange(len(problem.point_faces))
    columns = np.array([slot[int(f)] for f in problem.point_faces], np.int64)
    row_sigma = problem.dtp_sigmas()  # the weight each row was whitened with
    tilt_rows, tilt_columns, tilt_values = _tilt_entries(problem, faces, columns)
    unit = sp.csr_matrix((np.concatenate([1.0 / row_sigma, tilt_values / row_sigma[tilt_rows]]),
                          (np.concatenate([rows, first + tilt_rows]),
                           np.concatenate([columns, len(faces) + tilt_columns]))),
                         shape=(j_c.shape[0], 3 * len(faces)))
    g_c = np.asarray((j_c.T @ unit).todense())  # (nc, 3F)
    g_p = (j_p.T @ unit).tocsr()  # (3P, 3F)
    reduced = g_c - np.asarray((b.T @ g_p).todense())
    w_g = (_bsr_blocks(w_inv) @ g_p).tocsr() if num_points else g_p
    # g^T N^-1 g = (g_c - E^T W^-1 g_p)^T d_c + g_p^T W^-1 g_p, of the offsets' columns
    offsets = slice(0, len(faces))
    d_offsets = cof.q_cc @ reduced[:, offsets]
    cross = (reduced[:, offsets].T @ d_offsets
             + np.asarray((g_p[:, offsets].T @ w_g[:, offsets]).todense()))
    counts = np.bincount(columns, minlength=len(faces))
    if residuals is None:
        residuals = problem.group_residuals()
    metres = residuals["dTP"] * row_sigma  # the f_dTP residuals in metres
    t = np.bincount(columns, weights=metres / row_sigma ** 2, minlength=len(faces))
    # The offsets' variance component (the tilt columns take no part in it).
    m = (np.diag(np.bincount(columns, weights=1.0 / row_sigma ** 2, minlength=len(faces)))
         - 0.5 * (cross + cross.T))
    estimated = float(np.sqrt(max(0.0, (t @ t - s0_squared * np.trace(m)) / np.sum(m * m))))
    if estimate or sigma is None:
        sigma = estimated
    if sigma > 0:  # the responses to all consider parameters (times sigma^2 below)
        d_c = np.hstack([d_offsets, cof.q_cc @ reduced[:, len(faces):]])
        points_cov = _consider_points(cof, b, w_g, d_c, num_points)
    else:  # sigma 0: the consider part is zero
        d_c, points_cov = np.zeros_like(reduced), np.zeros((num_points, 3, 3))
    mean_offsets = np.bincount(columns, weights=metres, minlength=len(faces))
    return GeneralisationEffects(faces, d_c, sigma ** 2 * points_cov, float(sigma), prior,
                                 estimated, counts, mean_offsets / np.maximum(counts, 1))


def _consider_points(cof: Cofactors, b: sp.csr_matrix, w_g: sp.csr_matrix, d_c: np.ndarray,
                     num_points: int) -> np.ndarray:
    """(P, 3, 3) D_i D_i^T of the tie points' response D = W^-1 g_p - W^-1 E d_c."""
    if not isinstance(cof.q_cc, np.ndarray):
        from .point_cofactors import Consider, consider_rows, point_terms

        h, columns = consider_rows(w_g, num_points)
        return point_terms(cof.q_cc, b, cof.system[3], {}, Consider(d_c, h, columns),
                           marginal=False)[2]
    points_cov = np.empty((num_points, 3, 3))
    chunk = max(1, CHUNK_ROWS // 3)
    for lo in range(0, num_points, chunk):
        hi = min(num_points, lo + chunk)
        d_p = np.asarray(w_g[3 * lo:3 * hi].todense()) - b[3 * lo:3 * hi] @ d_c
        d_p = d_p.reshape(hi - lo, 3, -1)
        points_cov[lo:hi] = np.einsum("kif,kjf->kij", d_p, d_p)
    return points_cov


def _tilt_entries(problem: HybridProblem, faces: np.ndarray, columns: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The tilt consider parameters' design entries: per f_dTP row (index among the f_dTP
    rows) its two columns (2 * plane slot + principal tilt) and values, the row's tie point's
    in-plane lever along each principal tilt axis times that tilt's sigma at sigma = 1 m (its
    distance change, in metres, per unit of the tilt)."""
    from ..adjust.observability import face_tilts

    empty = (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0))
    if problem.model is None or not len(problem.point_ids):
        return empty
    rec = problem.reconstruction
    points = np.array([rec.point3D(int(i)).xyz for i in problem.point_ids])
    tilts = face_tilts(problem.model, faces, 1.0)
    values = np.zeros((len(points), 2))
    for slot, face in enumerate(faces):
        selected = columns == slot
        values[selected] = tilts[int(face)].distances(points[selected])
    rows = np.repeat(np.arange(len(points)), 2)
    return rows, (2 * columns[:, None] + np.arange(2)).ravel(), values.ravel()


# -- image quantities ----------------------------------------------------------------------------

def omega_phi_kappa(cam_from_world: pycolmap.Rigid3d) -> np.ndarray:
    """(omega, phi, kappa) in radians of R = Rx(omega) Ry(phi) Rz(kappa), the rotation from
    photogrammetric camera axes (x right, y up, z backwards) to the model frame."""
    rotation = np.asarray(cam_from_world.rotation.matrix()).T @ PHOTOGRAMMETRIC_FLIP
    return Rotation.from_matrix(rotation).as_euler("XYZ")


def _image_quantities(rec: pycolmap.Reconstruction, image: pycolmap.Image,
                      rig_from_world: pycolmap.Rigid3d) -> np.ndarray:
    frame = rec.frame(image.frame_id)
    if image.is_ref_in_frame():
        cam_from_world = rig_from_world
    else:
        sensor_from_rig = rec.rig(frame.rig_id).sensor_from_rig(image.camera.sensor_id)
        cam_from_world = sensor_from_rig * rig_from_world
    centre = np.asarray(cam_from_world.inverse().translation)
    return np.concatenate([centre, omega_phi_kappa(cam_from_world)])


def _perturbed(pose: pycolmap.Rigid3d, delta: np.ndarray) -> pycolmap.Rigid3d:
    """Ceres' product manifold EigenQuaternion x R^3: q <- [sin|d| d/|d|, cos|d|] q (a left
    rotation by the angle 2|d|: the tangent is half the rotation vector), t <- t + delta_t."""
    rotation = pycolmap.Rotation3d(2.0 * np.asarray(delta[:3], float)) * pose.rotation
    return pycolmap.Rigid3d(rotation, np.asarray(pose.translation) + delta[3:])


def image_jacobian(rec: pycolmap.Reconstruction, image_id: int) -> np.ndarray:
    """(6, 6) d(X0, Y0, Z0, omega, phi, kappa) / d(frame pose tangent), central differences."""
    image = rec.image(image_id)
    pose = rec.frame(image.frame_id).rig_from_world
    out = np.empty((6, 6))
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = POSE_STEP
        plus = _image_quantities(rec, image, _perturbed(pose, delta))
        minus = _image_quantities(rec, image, _perturbed(pose, -delta))
        diff = plus - minus
        diff[3:] = (diff[3:] + np.pi) % (2 * np.pi) - np.pi
        out[:, k] = diff / (2 * POSE_STEP)
    return out


def image_jacobians(rec: pycolmap.Reconstruction, image_ids
                    ) -> tuple[np.ndarray, np.ndarray]:
    """`_image_quantities` (N, 6) and `image_jacobian` (N, 6, 6) of many images at once (the
    same central differences, vectorised over the images)."""
    r_f, t_f, r_s, t_s = [], [], [], []
    for image_id in image_ids:
        image = rec.image(image_id)
        frame = rec.frame(image.frame_id)
        r_f.append(np.asarray(frame.rig_from_world.rotation.matrix()))
        t_f.append(np.asarray(frame.rig_from_world.translation))
        sensor = (pycolmap.Rigid3d() if image.is_ref_in_frame()
                  else rec.rig(frame.rig_id).sensor_from_rig(image.camera.sensor_id))
        r_s.append(np.asarray(sensor.rotation.matrix()))
        t_s.append(np.asarray(sensor.translation))
    r_f, t_f = np.array(r_f).reshape(-1, 3, 3), np.array(t_f).reshape(-1, 3)
    r_s, t_s = np.array(r_s).reshape(-1, 3, 3), np.array(t_s).reshape(-1, 3)

    def quantities(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
        r_c = r_s @ rotation
        t_c = np.einsum("kij,kj->ki", r_s, translation) + t_s
        centre = -np.einsum("kji,kj->ki", r_c, t_c)
        if not len(r_c):
            return np.zeros((0, 6))
        angles = Rotation.from_matrix(r_c.transpose(0, 2, 1) @ PHOTOGRAMMETRIC_FLIP)
        return np.hstack([centre, angles.as_euler("XYZ")])

    jacobians = np.empty((len(r_f), 6, 6))
    for k in range(6):
        delta = np.zeros(6)
        delta[k] = POSE_STEP
        moved = []
        for sign in (1.0, -1.0):
            turn = Rotation.from_rotvec(2.0 * sign * delta[:3]).as_matrix()
            moved.append(quantities(turn @ r_f, t_f + sign * delta[3:]))
        diff = moved[0] - moved[1]
        diff[:, 3:] = (diff[:, 3:] + np.pi) % (2 * np.pi) - np.pi
        jacobians[:, :, k] = diff / (2 * POSE_STEP)
    return quantities(r_f, t_f), jacobians


# -- check points --------------------------------------------------------------------------------

#: Step (m) of the numerical derivative of a check point's projection w.r.t. its coordinates.
POINT_STEP = 1e-5


@dataclass
class CheckpointCofactors:
    """Unscaled joint cofactor matrix of the check points (Q = N^-1 block, 3N x 3N)."""

    ids: list[str]
    points: np.ndarray  # (N, 3) in the problem's frame (triangulated with the adjusted poses)
    q: np.ndarray  # (3N, 3N) marginal, with cross terms between check points
    q_conditional: np.ndarray  # (N, 3, 3) W_c^-1: poses and everything else held fixed
    num_observations: dict[str, int]
    joint: bool  # True: the check points' observations are in the normal system (Woodbury)
    b: np.ndarray | None = None  # (3N, nc) W_c^-1 J_p^T J_f: check points from the poses


def _camera_columns(problem: HybridProblem, layout: _Layout, camera) -> tuple[slice, np.ndarray]:
    """Columns of a variable camera block and the parameter indices they refine. COLMAP's BA
    keeps the principal point constant (SubsetManifold) unless asked; the rest is its tangent."""
    columns = layout.columns("camera", camera.camera_id)
    if columns is None:
        return None, np.zeros(0, np.int64)
    fixed = set()
    if not problem.adjuster.options.refine_principal_point:
        fixed |= set(int(i) for i in camera.principal_point_idxs())
    if not problem.adjuster.options.refine_focal_length:
        fixed |= set(int(i) for i in camera.focal_length_idxs())
    if not problem.adjuster.options.refine_extra_params:
        fixed |= set(int(i) for i in camera.extra_params_idxs())
    free = np.array([i for i in range(len(camera.params)) if i not in fixed], np.int64)
    if len(free) != columns.stop - columns.start:
        raise RuntimeError(f"camera {camera.camera_id}: tangent size {columns.stop - columns.start}"
                           f" does not match the {len(free)} refined parameters")
    return columns, free


def _projection_jacobians(rec: pycolmap.Reconstruction, image: pycolmap.Image, xyz: np.ndarray,
                          free_camera: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """d(pixel)/d(point) (2, 3), d(pixel)/d(frame tangent) (2, 6) and d(pixel)/d(refined
    camera parameters) (2, k) by central differences, the frame tangent as Ceres' manifold."""
    frame = rec.frame(image.frame_id)
    camera = image.camera
    sensor_from_rig = (None if image.is_ref_in_frame() else
                       rec.rig(frame.rig_id).sensor_from_rig(camera.sensor_id))

    def project(rig_from_world, point, cam=camera):
        cam_from_world = (rig_from_world if sensor_from_rig is None
                          else sensor_from_rig * rig_from_world)
        return np.asarray(cam.img_from_cam((cam_from_world * point)[None])).reshape(2)

    pose = frame.rig_from_world
    j_point = np.empty((2, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = POINT_STEP
        j_point[:, k] = (project(pose, xyz + d) - project(pose, xyz - d)) / (2 * POINT_STEP)
    j_frame = np.empty((2, 6))
    for k in range(6):
        d = np.zeros(6)
        d[k] = POSE_STEP
        j_frame[:, k] = (project(_perturbed(pose, d), xyz)
                         - project(_perturbed(pose, -d), xyz)) / (2 * POSE_STEP)
    j_camera = np.empty((2, len(free_camera)))
    for col, i in enumerate(free_camera):
        step = 1e-6 * max(1.0, abs(camera.params[i]))
        values = []
        for sign in (1.0, -1.0):
            moved = copy.copy(camera)  # pycolmap 4 has no Camera(camera)
            params = np.array(camera.params, float)
            params[i] += sign * step
            moved.params = params
            values.append(project(pose, xyz, moved))
        j_camera[:, col] = (values[0] - values[1]) / (2 * step)
    return j_point, j_frame, j_camera


def checkpoint_cofactors(problem: HybridProblem, cof: Cofactors, points: dict[str, np.ndarray],
                         observations) -> CheckpointCofactors:
    """Marginal cofactors of check points estimated as free 3D points from their image
    observations (f_CP, sigma_image like f_TP), in the normal system of the adjustment.

    Each check point c adds rows J_c = [J_p (point), J_f (its images' frames, cameras)] to the
    normal system. Eliminating c (as the tie points): the camera-side normal matrix gains
    D = sum_c J_f^T (I - J_p W_c^-1 J_p^T) J_f, W_c = J_p^T J_p, so
    Q_cc' = (S + D)^-1 = Q_cc - Q_cc G^T (I + G Q_cc G^T)^-1 G Q_cc (Woodbury, G stacked
    (I - J_p W_c^-1 J_p^T) J_f), and the joint check point block is
    Q_ij = delta_ij W_i^-1 + B_i Q_cc' B_j^T with B_c = W_c^-1 J_p^T J_f: the pose, plane and
    datum uncertainty enters through Q_cc'. Check points are never assigned to planes and
    never used as control. With a datum defect the check points' own small influence on the
    poses is left out (Q_cc' = Q_cc, the triangulation with the adjusted poses).

    `points`: id -> (3,) in the problem's frame (checkpoints.triangulate_checkpoints on the
    problem's reconstruction); `observations`: [(image_name, id, x, y)] in pixels."""
    rec = problem.reconstruction
    layout = cof.layout
    sigma = problem.options.sigma_image
    by_name = {image.name: image for image in rec.images.values() if image.has_pose}
    grouped: dict[str, list] = {}
    for name, point_id, x, y in observations:
        if point_id in points and name in by_name:
            grouped.setdefault(point_id, []).append((by_name[name], float(x), float(y)))
    ids = [i for i in sorted(points) if len(grouped.get(i, ())) >= 2]
    cameras = {c: _camera_columns(problem, layout, rec.camera(c)) for c in rec.cameras}
    nc = layout.num_c
    w_inv, b_rows, g_rows, counts = [], [], [], {}
    for point_id in ids:
        xyz = np.asarray(points[point_id], float)
        j_p, j_f = [], []
        for image, _, _ in grouped[point_id]:
            columns, free = cameras[image.camera_id]
            jp, jf, jc = _projection_jacobians(rec, image, xyz, free)
            row = np.zeros((2, nc))
            frame_columns = layout.columns("frame", image.frame_id)
            if frame_columns is not None:
                if frame_columns.stop - frame_columns.start != 6:
                    raise RuntimeError("check points on a gauge-reduced frame are not supported")
                row[:, frame_columns] = jf
            if columns is not None:
                row[:, columns] = jc
            j_p.append(jp / sigma)
            j_f.append(row / sigma)
        j_p, j_f = np.vstack(j_p), np.vstack(j_f)
        w_c_inv = np.linalg.inv(j_p.T @ j_p)
        w_inv.append(w_c_inv)
        b_rows.append(w_c_inv @ (j_p.T @ j_f))
        g_rows.append(j_f - j_p @ (w_c_inv @ (j_p.T @ j_f)))
        counts[point_id] = len(grouped[point_id])
    if not ids:
        return CheckpointCofactors([], np.zeros((0, 3)), np.zeros((0, 0)), np.zeros((0, 3, 3)),
                                   {}, False)
    b = np.vstack(b_rows)  # (3N, nc)
    joint = cof.datum_defect == 0
    qb = cof.q_cc @ b.T  # products only: Q_cc may be a SelectedInverse
    q = b @ qb
    if joint:  # B Q_cc' B^T = B Q_cc B^T - (G Q_cc B^T)^T (I + G Q_cc G^T)^-1 G Q_cc B^T
        g = np.vstack(g_rows)
        inner = np.eye(len(g)) + g @ (cof.q_cc @ g.T)
        gqb = g @ qb
        q = q - gqb.T @ np.linalg.solve(0.5 * (inner + inner.T), gqb)
    for k, w in enumerate(w_inv):
        q[3 * k:3 * k + 3, 3 * k:3 * k + 3] += w
    return CheckpointCofactors(ids, np.array([points[i] for i in ids], float), 0.5 * (q + q.T),
                               np.array(w_inv), counts, joint, b)


# -- the result ----------------------------------------------------------------------------------

def _sigmas(covariance: np.ndarray) -> np.ndarray:
    """(N, k) square roots of the diagonals of (N, k, k) blocks or of a joint (3N, 3N)."""
    if covariance.ndim == 2:
        return np.sqrt(np.maximum(np.diagonal(covariance), 0.0)).reshape(-1, 3)
    return np.sqrt(np.maximum(np.diagonal(covariance, axis1=1, axis2=2), 0.0))


@dataclass
class PrecisionResult:
    """Variance factors and, if computed, a posteriori covariances scaled by s0^2.

    Coordinates are in the problem's frame (refine: model CRS minus `origin`; add it back)."""

    variance: VarianceFactors
    datum_defect: int = 0
    image_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    image_names: list[str] = field(default_factory=list)
    centres: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    angles_deg: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    image_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 6, 6)))
    """(N, 6, 6) covariance of X0, Y0, Z0 (m) and omega, phi, kappa (rad)."""
    image_num_observations: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    point_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    """(P, 3, 3) marginal covariance of each tie point (the honest one)."""
    point_cov_conditional: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    """(P, 3, 3) covariance with every other unknown held fixed (pycolmap's get_point_cov x s0^2)."""
    plane_faces: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    plane_offset_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    vertex_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    """Store indices of the model vertices that were unknowns of the solve."""
    vertex_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    """(V, 3, 3) marginal covariance of each vertex (local frame), scaled by s0^2."""
    seconds: dict[str, float] = field(default_factory=dict)
    plane_generalisation: np.ndarray = field(default_factory=lambda: np.zeros(0))
    """(F,) estimated generalisation offsets o_p (m) per plane; empty in the classical model."""
    plane_generalisation_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    checkpoint_ids: list[str] = field(default_factory=list)
    checkpoint_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    """(N, 3) check points triangulated with the adjusted poses (problem frame)."""
    checkpoint_cov: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    """(3N, 3N) joint marginal covariance of the check points, scaled by s0^2."""
    checkpoint_cov_conditional: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    generalisation: str = "none"
    """"none" (classical stochastic model only), "consider" (per-plane offsets of
    `generalisation_sigma` propagated, `*_cov_generalisation` hold the added covariance, not
    scaled by s0^2: sigma_generalisation is absolute) or "estimated" (the offsets were unknowns
    of the solve: the covariances above already include them)."""
    generalisation_sigma: float | None = None
    covariance_factor: float | None = None
    """The factor the covariances above are their cofactors times: s0^2, or at least 1 with
    the offsets estimated ("estimated"). None: no covariances."""
    generalisation_estimate: dict = field(default_factory=dict)
    """Consider mode: the a priori and the data's sigma of the offsets (moments of the planes'
    mean f_dTP residuals, `generalisation_effects`) and which one was used."""
    image_cov_generalisation: np.ndarray = field(default_factory=lambda: np.zeros((0, 6, 6)))
    point_cov_generalisation: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    checkpoint_cov_generalisation: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))
    vertex_cov_generalisation: np.ndarray = field(default_factory=lambda: np.zeros((0, 3, 3)))
    datum_shift_variance: np.ndarray = field(default_factory=lambda: np.zeros(3))
    """(3,) m^2 per axis: a shift common to the whole block (the datum's errors that the
    covariances above do not hold: GNSS's bias, the model's common shift), added so that no
    image centre is stated more precise than the datum (`datum_shift`)."""

    def aware(self, covariance: str) -> np.ndarray:
        """`covariance` ("image_cov", "point_cov", "checkpoint_cov") under the full stochastic
        model: the classical one plus the consider part and the datum's common shift."""
        base = getattr(self, covariance)
        if self.generalisation == "consider":
            base = base + getattr(self, f"{covariance}_generalisation")
        if not np.any(self.datum_shift_variance > 0) or not len(base):
            return base
        shift = np.diag(self.datum_shift_variance)
        out = np.array(base, copy=True)
        if out.ndim == 2:  # joint (3N, 3N): the shift is common, so fully correlated
            return out + np.kron(np.ones((len(out) // 3, len(out) // 3)), shift)
        out[:, :3, :3] += shift
        return out

    def aware_sigmas(self, covariance: str) -> np.ndarray | None:
        """Square roots of the diagonal blocks of `aware(covariance)` ((N, k), m; radians for
        image angles); None when there is no generalisation-aware model to state."""
        consider = self.generalisation == "consider" \
            and len(getattr(self, f"{covariance}_generalisation"))
        if not (consider or np.any(self.datum_shift_variance > 0)) \
                or not len(getattr(self, covariance)):
            return None
        return _sigmas(self.aware(covariance))

    @property
    def has_covariances(self) -> bool:
        return len(self.image_cov) > 0 or len(self.point_cov) > 0

    @property
    def image_sigmas(self) -> np.ndarray:
        """(N, 6) sigma X0, Y0, Z0 (m), omega, phi, kappa (deg)."""
        sigma = np.sqrt(np.maximum(np.diagonal(self.image_cov, axis1=1, axis2=2), 0.0))
        sigma[:, 3:] = np.degrees(sigma[:, 3:])
        return sigma

    @property
    def point_sigmas(self) -> np.ndarray:
        """(P, 3) marginal sigma X, Y, Z (m)."""
        return np.sqrt(np.maximum(np.diagonal(self.point_cov, axis1=1, axis2=2), 0.0))

    @property
    def point_sigmas_conditional(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(self.point_cov_conditional, axis1=1, axis2=2),
                                  0.0))

    @property
    def checkpoint_sigmas(self) -> np.ndarray:
        """(N, 3) marginal sigma X, Y, Z (m) of the check points, scaled by s0^2."""
        diagonal = np.diagonal(self.checkpoint_cov).reshape(-1, 3)
        return np.sqrt(np.maximum(diagonal, 0.0))

    @property
    def checkpoint_sigmas_conditional(self) -> np.ndarray:
        return np.sqrt(np.maximum(np.diagonal(self.checkpoint_cov_conditional, axis1=1,
                                              axis2=2), 0.0))

    def point_covariance(self, point_id: int) -> np.ndarray:
        index = np.flatnonzero(self.point_ids == point_id)
        if not len(index):
            raise KeyError(f"no covariance for point3D {point_id}")
        return self.point_cov[index[0]]

    def summary(self) -> dict:
        """Medians for the report (Mulder Table 5.2 style)."""
        out = {**self.variance.todict(), "datum_defect": self.datum_defect,
               "covariances": self.has_covariances, "seconds": self.seconds}
        if self.has_covariances:
            out["scaled_by"] = "s0^2"
            out["median_image_sigma"] = dict(zip(
                ("X0_m", "Y0_m", "Z0_m", "omega_deg", "phi_deg", "kappa_deg"),
                np.median(self.image_sigmas, axis=0).tolist()))
            out["median_point_sigma_m"] = dict(zip("XYZ", np.median(self.point_sigmas, 0)
                                                   .tolist()))
            out["median_point_sigma_conditional_m"] = dict(zip(
                "XYZ", np.median(self.point_sigmas_conditional, 0).tolist()))
            out["point_covariance_note"] = (
                "point sigmas are marginal (all other unknowns uncertain too); the conditional "
                "ones hold poses, planes and vertices fixed, as pycolmap's get_point_cov")
        if len(self.checkpoint_ids):
            out["num_checkpoints_with_covariance"] = len(self.checkpoint_ids)
            out["median_checkpoint_sigma_m"] = dict(zip("XYZ", np.median(
                self.checkpoint_sigmas, 0).tolist()))
            out["median_checkpoint_sigma_conditional_m"] = dict(zip("XYZ", np.median(
                self.checkpoint_sigmas_conditional, 0).tolist()))
        out["generalisation"] = {"mode": self.generalisation,
                                 "sigma_m": self.generalisation_sigma}
        if self.generalisation_estimate:
            e = self.generalisation_estimate
            out["generalisation"].update(
                sigma_prior_m=e["sigma_prior_m"], sigma_estimated_m=e["sigma_estimated_m"],
                sigma_from_data=e["estimated"])
        if self.generalisation == "consider" and self.has_covariances:
            aware = {"image": _sigmas(self.aware("image_cov")),
                     "point": _sigmas(self.aware("point_cov"))}
            g = out["generalisation"]
            g["note"] = ("per-plane offsets o_p ~ N(0, sigma^2) and the tilts of planes "
                         "whose vertices are sigma off, shared by the plane's f_dTP, "
                         "propagated into the classical estimate's covariance (not scaled "
                         "by s0^2)")
            if len(aware["image"]):
                g["median_image_sigma_m"] = dict(zip(("X0", "Y0", "Z0"), np.median(
                    aware["image"][:, :3], 0).tolist()))
            if len(aware["point"]):
                g["median_point_sigma_m"] = dict(zip("XYZ", np.median(aware["point"], 0)
                                                     .tolist()))
            if len(self.checkpoint_ids):
                g["median_checkpoint_sigma_m"] = dict(zip("XYZ", np.median(
                    _sigmas(self.aware("checkpoint_cov")), 0).tolist()))
        if np.any(self.datum_shift_variance > 0) and self.has_covariances:
            centres = _sigmas(self.aware("image_cov"))[:, :3]
            out["datum_shift"] = {
                "sigma_m": dict(zip("ENU", np.sqrt(self.datum_shift_variance).tolist())),
                "median_image_sigma_m": dict(zip(("X0", "Y0", "Z0"),
                                                 np.median(centres, 0).tolist())),
                "note": "a shift common to the block, added to the image and point "
                        "covariances so that none is stated more precise than the datum "
                        "(observability: GNSS's bias, the model's common shift)"}
        if len(self.plane_generalisation):
            out["generalisation_offsets"] = {
                "num_planes": int(len(self.plane_generalisation)),
                "rms_m": float(np.sqrt(np.mean(self.plane_generalisation ** 2))),
                "max_abs_m": float(np.max(np.abs(self.plane_generalisation))),
                "median_sigma_m": float(np.nanmedian(self.plane_generalisation_sigma))
                if len(self.plane_generalisation_sigma) else None}
        return out


def estimate_precision(problem: HybridProblem, **options) -> PrecisionResult:
    """`_estimate_precision` with BLAS on BLAS_THREADS threads (see there)."""
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=BLAS_THREADS, user_api="blas"):
        return _estimate_precision(problem, **options)


def _image_blocks(rec: pycolmap.Reconstruction, cof: Cofactors, s0sq: float, effects):
    """Per registered image with a 6-parameter frame in the cofactors: id, name, centre,
    angles (deg), the 6x6 covariance of centre and angles, its number of tie points, and (with
    `effects`) the generalisation-aware part of that covariance."""
    layout = cof.layout
    image_ids, names, centres, angles, image_cov, num_obs = [], [], [], [], [], []
    image_cov_generalisation = []
    frame_columns = {key: slice(start, start + size) for (kind, key), start, size
                     in zip(layout.names, layout.starts, layout.sizes) if kind == "frame"}
    wanted = [i for i in rec.reg_image_ids()
              if (c := frame_columns.get(rec.image(i).frame_id)) is not None
              and c.stop - c.start == 6]  # a constant or gauge-reduced frame has none
    all_values, jacobians = image_jacobians(rec, wanted)
    for image_id, values, g in zip(wanted, all_values, jacobians):
        image = rec.image(image_id)
        columns = frame_columns[image.frame_id]
        image_ids.append(image_id)
        names.append(image.name)
        centres.append(values[:3])
        angles.append(np.degrees(values[3:]))
        image_cov.append(s0sq * g @ cof.q_cc[columns, columns] @ g.T)
        if effects is not None:
            d = g @ effects.camera[columns]
            image_cov_generalisation.append(effects.sigma ** 2 * d @ d.T)
        num_obs.append(image.num_points3D)
    return image_ids, names, centres, angles, image_cov, num_obs, image_cov_generalisation


def _scalar_sigmas(cof: Cofactors, s0sq: float, kind: str, count: int) -> list[float]:
    """The sigma of each of `count` one-parameter blocks of `kind` in the cofactors (nan where
    a block has no columns)."""
    out = []
    for k in range(count):
        columns = cof.layout.columns(kind, k)
        out.append(np.sqrt(s0sq * cof.q_cc[columns, columns][0, 0])
                   if columns is not None else np.nan)
    return out


def _generalisation_extra(effects, estimate_generalisation: bool, image_cov_generalisation,
                          vertex_cov_generalisation, checkpoints) -> dict:
    """PrecisionResult's generalisation-aware fields: the estimate's record and the
    covariances' generalisation parts of images, vertices, tie points and check points."""
    extra = {"generalisation_estimate": {
        "sigma_prior_m": effects.sigma_prior, "sigma_estimated_m": effects.sigma_estimated,
        "sigma_used_m": effects.sigma, "estimated": bool(estimate_generalisation),
        "plane_faces": effects.faces.tolist(), "plane_num_points": effects.num_points.tolist(),
        "plane_mean_residual_m": effects.mean_residuals.tolist()}}
    extra["image_cov_generalisation"] = np.array(image_cov_generalisation).reshape(-1, 6, 6)
    extra["vertex_cov_generalisation"] = vertex_cov_generalisation
    extra["point_cov_generalisation"] = effects.points_cov
    if checkpoints is not None and checkpoints.b is not None:
        d = checkpoints.b @ effects.camera  # (3N, F): check points follow the poses
        extra["checkpoint_cov_generalisation"] = effects.sigma ** 2 * d @ d.T
    return extra


def _consider_generalisation(problem: HybridProblem, cof: Cofactors,
                             sigma_generalisation: float | None, estimate: bool, variance,
                             *, held: bool, free_system: bool, residuals=None):
    """The planes' generalisation errors as consider parameters (`generalisation_effects`).
    The response to them is the estimator's own: with the holds of what the planes do not fix
    (the height, the scale) as tight as in the solve (`held`). At GNSS's sigma, the walls'
    tilts would seem to move a block's height by metres, which the hold does not let them.
    `free_system`: drop `cof`'s Jacobian, W^-1 E and S afterwards."""
    t0 = time.perf_counter()
    solve_cof = solve_weighted(problem, cof) if held else cof
    effects = generalisation_effects(problem, solve_cof, sigma_generalisation,
                                     estimate=estimate, s0_squared=variance.sigma0_squared,
                                     residuals=residuals)
    if held:
        solve_cof.system = None
    if free_system:
        cof.system = cof.normal = None
    logger.info("precision: generalisation-aware covariances for %d planes (sigma %.3f m%s,"
                " %.1f s)", len(effects.faces), effects.sigma,
                " estimated" if estimate else f"; the data say {effects.sigma_estimated:.3f} m",
                time.perf_counter() - t0)
    return effects


def _estimate_precision(problem: HybridProblem, *, covariances: bool = True,
                       alpha: float = 0.05, checkpoint_observations=None,
                       sigma_generalisation: float | None = None,
                       estimate_generalisation: bool = False,
                       cof: Cofactors | None = None,
                       datum_sigmas: np.ndarray | None = None) -> PrecisionResult:
    """Variance factors, global test and (optionally) covariances at the current state of a
    solved `HybridProblem` (refine's last hybrid solve, or a plain step-2 problem).

    `checkpoint_observations` ([(image_name, id, x, y)], checkpoints.read_checkpoint_observations):
    check points are triangulated with the adjusted poses and get their marginal covariance
    (`checkpoint_cofactors`); needs `covariances`. `sigma_generalisation` (m; default the
    problem's AdjustmentOptions.sigma_generalisation): also the generalisation-aware
    covariances (`generalisation_effects`), unless the offsets were estimated in the solve.
    `estimate_generalisation`: that sigma estimated from the planes' mean residuals (a
    variance component; also without an a priori sigma_generalisation). `cof`: the
    `cofactors(problem)` of this state when the caller has them already (e.g. kept with their
    Schur system for a datum transformation). `datum_sigmas` ((3,) m, E N U; nan where not
    stated): the datum's shift sigmas (adjust.observability); see `datum_shift`."""
    start = time.perf_counter()
    residuals = problem.group_residuals()
    if not covariances:
        variance = variance_factors(residuals, problem.num_unknowns(), alpha=alpha)
        return PrecisionResult(variance, seconds={"variance": time.perf_counter() - start})

    if sigma_generalisation is None:
        sigma_generalisation = problem.options.sigma_generalisation
    mode = "none"
    if len(problem.blocks.generalisation):
        mode = "estimated"
        sigma_generalisation = problem.offset_prior_sigma
    elif (sigma_generalisation is not None or estimate_generalisation) \
            and problem.counts["dTP"]:
        mode = "consider"
    # Where refine held what the planes do not fix, the planes' errors act through the solve's
    # own weights (below), from a second system; else through this one.
    held = mode == "consider" and len(problem.hold_relaxation) > 0
    needs_system = mode == "consider"
    own_cofactors = cof is None or (needs_system and cof.system is None)
    if own_cofactors:
        cof = cofactors(problem, keep_system=needs_system)
    variance = variance_factors(residuals, problem.num_unknowns(), cof.redundancy_by_group,
                                alpha=alpha)
    effects = None
    if mode == "consider":
        effects = _consider_generalisation(problem, cof, sigma_generalisation,
                                           estimate_generalisation, variance, held=held,
                                           free_system=own_cofactors, residuals=residuals)
        sigma_generalisation = effects.sigma
    s0sq = variance.sigma0_squared
    if mode == "estimated":
        # s0 < 1 says the observations fit better than stated; the faces' offsets and the GNSS
        # bias rest on their priors, whose fit s0 does not measure: their sigmas are not
        # scaled below the a priori ones (the consider model adds their part unscaled too).
        s0sq = max(s0sq, 1.0)
    rec = problem.reconstruction
    layout = cof.layout
    t1 = time.perf_counter()
    (image_ids, names, centres, angles, image_cov, num_obs,
     image_cov_generalisation) = _image_blocks(rec, cof, s0sq, effects)
    plane_sigma = _scalar_sigmas(cof, s0sq, "plane_offset", len(problem.blocks.faces))
    vertex_cov, vertex_cov_generalisation = _vertex_blocks(problem, cof, s0sq, effects)
    generalisation_sigma = _scalar_sigmas(cof, s0sq, "plane_generalisation",
                                          len(problem.blocks.generalisation))
    checkpoints = None
    if checkpoint_observations is not None:
        from .checkpoints import triangulate_checkpoints

        t2 = time.perf_counter()
        checkpoints = checkpoint_cofactors(
            problem, cof, triangulate_checkpoints(rec, checkpoint_observations),
            checkpoint_observations)
        logger.info("precision: %d check points with covariances (%.1f s)",
                    len(checkpoints.ids), time.perf_counter() - t2)
    extra = {"generalisation": mode, "generalisation_sigma": sigma_generalisation,
             "covariance_factor": s0sq}
    if effects is not None:
        extra.update(_generalisation_extra(effects, estimate_generalisation,
                                           image_cov_generalisation, vertex_cov_generalisation,
                                           checkpoints))
    extra["datum_shift_variance"] = datum_shift(
        np.array(image_cov).reshape(-1, 6, 6)[:, :3, :3]
        + (extra["image_cov_generalisation"][:, :3, :3] if effects is not None else 0.0),
        datum_sigmas)
    points = np.array([rec.point3D(int(i)).xyz for i in layout.point_ids]).reshape(-1, 3)
    seconds = {"cofactors": cof.seconds, "images": time.perf_counter() - t1,
               "total": time.perf_counter() - start}
    logger.info("precision: s0 %.3f (%s), global test %s (T %.0f, r %.0f, p %.3g); "
                "covariances in %.1f s", variance.sigma0, ", ".join(
                    f"{g} {s:.3f}" for g, s in variance.sigma0_by_group.items() if s),
                "accepted" if variance.test and variance.test.accepted else "rejected",
                variance.vtpv, variance.redundancy,
                variance.test.p_value if variance.test else float("nan"), seconds["total"])
    return PrecisionResult(
        variance=variance, datum_defect=cof.datum_defect,
        image_ids=np.array(image_ids, np.int64), image_names=names,
        centres=np.array(centres).reshape(-1, 3), angles_deg=np.array(angles).reshape(-1, 3),
        image_cov=np.array(image_cov).reshape(-1, 6, 6),
        image_num_observations=np.array(num_obs, np.int64),
        point_ids=layout.point_ids, points=points, point_cov=s0sq * cof.q_points,
        point_cov_conditional=s0sq * cof.q_points_conditional,
        plane_faces=np.asarray(problem.blocks.faces), plane_offset_sigma=np.array(plane_sigma),
        vertex_ids=np.asarray(problem.blocks.vertex_ids, np.int64), vertex_cov=vertex_cov,
        seconds=seconds,
        plane_generalisation=problem.blocks.generalisation_array,
        plane_generalisation_sigma=np.array(generalisation_sigma),
        **({} if checkpoints is None else {
            "checkpoint_ids": checkpoints.ids, "checkpoint_points": checkpoints.points,
            "checkpoint_cov": s0sq * checkpoints.q,
            "checkpoint_cov_conditional": s0sq * checkpoints.q_conditional}), **extra)


def datum_shift(centre_cov: np.ndarray, datum_sigmas: np.ndarray | None) -> np.ndarray:
    """(3,) m^2: the variance of a shift common to the block that lifts every image centre's
    variance along E, N, U to at least the datum's (`datum_sigmas`, adjust.observability):
    what the datum's stochastic model holds (GNSS's bias, the model's common shift) and the
    covariances do not. Zero where they already state the datum or more."""
    out = np.zeros(3)
    if datum_sigmas is None or not len(centre_cov):
        return out
    least = np.min(np.diagonal(centre_cov, axis1=1, axis2=2), axis=0)
    for axis, sigma in enumerate(np.asarray(datum_sigmas, float)):
        if np.isfinite(sigma):
            out[axis] = max(0.0, sigma ** 2 - least[axis])
    return out


def _vertex_blocks(problem: HybridProblem, cof: Cofactors, s0sq: float,
                   effects: GeneralisationEffects | None) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3, 3) s0^2-scaled marginal covariances of the vertex blocks (nan for a constant
    one) and, with `effects`, what the generalisation offsets add (not scaled)."""
    num = len(problem.blocks.vertex_ids)
    cov = np.full((num, 3, 3), np.nan)
    added = np.full((num, 3, 3), np.nan) if effects is not None else np.zeros((0, 3, 3))
    for k in range(num):
        columns = cof.layout.columns("vertex", k)
        if columns is None:
            continue
        cov[k] = s0sq * cof.q_cc[columns, columns]
        if effects is not None:
            d = effects.camera[columns]
            added[k] = effects.sigma ** 2 * d @ d.T
    return cov, added


def vertex_covariances(problem: HybridProblem, precision: PrecisionResult | None
                       ) -> tuple[np.ndarray, np.ndarray, str]:
    """(vertex ids, (V, 3, 3) covariances, how they were obtained) of the model vertices of
    a solved problem: those of `precision` when it computed covariances, else from the
    cofactors of the camera-side unknowns alone (poses, planes, vertices; the tie points are
    eliminated but their covariances not formed), scaled by s0^2 of `precision` (or of the
    solve). Generalisation-aware ones when `precision` has them."""
    ids = np.asarray(problem.blocks.vertex_ids, np.int64)
    if precision is not None and len(precision.vertex_ids) == len(ids) and len(ids):
        note = "marginal covariance of the vertex block, scaled by s0^2"
        if precision.generalisation == "consider" and len(precision.vertex_cov_generalisation):
            return (ids, precision.vertex_cov + precision.vertex_cov_generalisation,
                    note + ", plus the planes' generalisation offsets (consider parameters)")
        return ids, precision.vertex_cov, note
    start = time.perf_counter()
    if precision is not None:
        s0sq = precision.covariance_factor or precision.variance.sigma0_squared
    else:
        s0sq = variance_factors(problem.group_residuals(), problem.num_unknowns()).sigma0_squared
    cof = cofactors(problem, redundancy=False, points=False)
    cov, _ = _vertex_blocks(problem, cof, s0sq, None)
    logger.info("precision: covariances of %d model vertices (%.1f s)", len(ids),
                time.perf_counter() - start)
    return ids, cov, "marginal covariance of the vertex block, scaled by s0^2"


def wants_covariances(options, num_images: int) -> bool:
    """`PrecisionOptions.covariances`: "on", "off", or "auto" (fewer than max_images_auto)."""
    mode = str(options.covariances).lower()
    if mode not in ("on", "off", "auto"):
        from ..errors import InputError

        raise InputError(f"precision.covariances must be on, off or auto, not {mode!r}")
    return mode == "on" or (mode == "auto" and num_images < options.max_images_auto)


def precision_after_refine(problem: HybridProblem | None, options,
                           checkpoint_observations=None, observability: dict | None = None
                           ) -> PrecisionResult | None:
    """What refine() keeps: the precision of its last hybrid solve (with check point
    covariances when their observations are given; with the datum's shift sigmas of
    `observability`, adjust.observability, as the least an image centre states). A failure of the covariance step (e.g. an
    unexpected parameter block) costs the covariances, not the refine result."""
    if problem is None:
        return None
    covariances = wants_covariances(options, problem.reconstruction.num_reg_images())
    if not covariances:
        logger.info("precision: covariances skipped (%d images; precision.covariances=%s)%s",
                    problem.reconstruction.num_reg_images(), options.covariances,
                    "; check points get no sigma" if checkpoint_observations else "")
    try:
        return estimate_precision(
            problem, covariances=covariances, alpha=options.alpha,
            checkpoint_observations=checkpoint_observations,
            estimate_generalisation=bool(options.variance_components
                                         and "gen" in options.variance_component_groups)
            or (options.generalisation_from_data
                and problem.options.sigma_generalisation is None),
            datum_sigmas=_datum_sigmas(observability))
    except (RuntimeError, np.linalg.LinAlgError, MemoryError) as error:
        logger.warning("precision: covariances failed (%s); reporting s0 only", error)
        return estimate_precision(problem, covariances=False, alpha=options.alpha)


def _datum_sigmas(observability: dict | None) -> np.ndarray | None:
    """(3,) E N U shift sigmas (m) of an observability dict; nan where it states none."""
    if not observability:
        return None
    return np.array([observability.get(axis, {}).get("sigma") or np.nan
                     for axis in ("E", "N", "U")], float)


# -- variance component estimation ---------------------------------------------------------------


