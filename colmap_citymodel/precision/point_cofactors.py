"""Tie point cofactors from a selected inverse of the reduced normal matrix.

With B_i = W_i^-1 E_i (point i's rows of W^-1 E; non-zero only in the columns of the unknowns
that observe it) the marginal cofactor is Q_pp,i = W_i^-1 + B_i Q_cc B_i^T (method.md 9). The
columns of one point are mutually coupled, so Q_cc on them lies within two consecutive levels
of `selected.SelectedInverse` and its border: per level the dense window of Q_cc is formed
once; the points starting at that level, sorted along their unknowns, are taken in chunks of
neighbours, and each chunk's B (3 rows per point, dense over the union of the chunk's
unknowns) is multiplied with Q_cc on that union.

The same gather gives the group redundancies' point terms (sum of E_g,i * B_i Q_cc) and,
under the generalisation-aware model, the points' consider part D_i D_i^T with
D_i = h_i - B_i d_c (h_i = W_i^-1 g_p,i, non-zero in the columns of the point's plane only):
D_i D_i^T = B_i (d_c d_c^T) B_i^T + h_i h_i^T - h_i u_i^T - u_i h_i^T, u_i = B_i d_c[:, those
columns], with d_c d_c^T formed per window like Q_cc.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .selected import Levels, SelectedInverse, WindowProducts, order_levels, window_columns

logger = logging.getLogger(__name__)

#: Tie points per chunk: sorted along their unknowns, so that a chunk's union of unknowns stays
#: near one point's (dense products over that union).
CHUNK_POINTS = 64


@dataclass
class Consider:
    """The consider parameters' response: d_c (nc, F3) and per point h_i (P, 3, 3) in the
    columns `columns` (P, 3) of d_c (h zero where a point has fewer)."""

    d_c: np.ndarray
    h: np.ndarray
    columns: np.ndarray
    products: WindowProducts | None = None  # d_c d_c^T per level window (point_terms)


def consider_rows(w_g: sp.csr_matrix, num_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(h (P, 3, 3), columns (P, 3)) of W^-1 g_p, whose rows of a point share <= 3 columns."""
    h = np.zeros((num_points, 3, 3))
    columns = np.zeros((num_points, 3), np.int64)
    pattern = _point_pattern(w_g, num_points)
    counts = np.diff(pattern.indptr)
    if counts.max(initial=0) > 3:
        raise ValueError("a tie point with more than three consider columns")
    slot = np.arange(pattern.nnz) - np.repeat(pattern.indptr[:-1], counts)
    point = np.repeat(np.arange(num_points), counts)
    columns[point, slot] = pattern.indices
    coo = w_g.tocoo()
    key_pattern = point * w_g.shape[1] + pattern.indices
    key = (coo.row // 3) * w_g.shape[1] + coo.col
    position = np.searchsorted(key_pattern, key)
    h[coo.row // 3, coo.row % 3, slot[position]] = coo.data
    return h, columns


def _point_pattern(b: sp.csr_matrix, num_points: int) -> sp.csr_matrix:
    """(P, nc): the columns any of a point's three rows touches, sorted per row (a point's
    three rows are consecutive in `b`, so its entries are one run of b's arrays). Kept on
    `b` for the next pass over the same matrix (`b` is not changed in place)."""
    cached = getattr(b, "_point_pattern_of", None)
    if cached is not None and cached.shape[0] == num_points:
        return cached
    matrix = sp.csr_matrix(b)
    if matrix.shape[0] != 3 * num_points:
        raise ValueError(f"{matrix.shape[0]} rows for {num_points} points")
    pattern = sp.csr_matrix((np.abs(matrix.data), matrix.indices.copy(),
                             matrix.indptr[0::3].copy()), shape=(num_points, matrix.shape[1]))
    pattern.sum_duplicates()
    pattern.eliminate_zeros()
    b._point_pattern_of = pattern
    return pattern


def _rows_of(matrix: sp.csr_matrix, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row slot, column, value) of the entries of `rows` (in that order)."""
    counts = matrix.indptr[rows + 1] - matrix.indptr[rows]
    first = np.repeat(matrix.indptr[rows] - np.concatenate([[0], np.cumsum(counts)[:-1]]),
                      counts)
    flat = first + np.arange(int(counts.sum()))
    return np.repeat(np.arange(len(rows)), counts), matrix.indices[flat], matrix.data[flat]


def _level_chunks(levels: Levels, pattern: sp.csr_matrix):
    """(level, window columns, where: column -> window index, chunk of points) over the points
    by the first level of their unknowns, sorted along them and cut in CHUNK_POINTS."""
    nc = len(levels.level_of)
    for lv, points in _points_by_level(levels, pattern):
        columns = window_columns(levels, lv)
        where = np.full(nc, len(columns), np.int64)
        where[columns] = np.arange(len(columns))
        for lo in range(0, len(points), CHUNK_POINTS):
            yield lv, columns, where, points[lo:lo + CHUNK_POINTS]


def _points_by_level(levels: Levels, pattern: sp.csr_matrix):
    """(level, points) with the points (those with unknowns) grouped by the first level of
    their unknowns, within a level sorted by their first unknown in the window's order (one
    sort: a column's window index grows with its position in `levels.perm`)."""
    nc = len(levels.level_of)
    nonempty = np.flatnonzero(np.diff(pattern.indptr) > 0)
    if not len(nonempty):
        return
    big = np.iinfo(np.int64).max
    starts = pattern.indptr[:-1][nonempty]
    level = levels.level_of[pattern.indices]
    base = np.minimum.reduceat(np.where(level < 0, big, level), starts)
    base[base == big] = 0
    position = np.empty(nc, np.int64)
    position[levels.perm] = np.arange(nc)
    first = np.minimum.reduceat(position[pattern.indices], starts)
    order = np.lexsort((first, base))  # stable: ties keep the points' order
    points, base = nonempty[order], base[order]
    bounds = np.flatnonzero(np.diff(base)) + 1
    for chunk in np.split(np.arange(len(points)), bounds):
        yield int(base[chunk[0]]), points[chunk]


def _union(pattern: sp.csr_matrix, chunk: np.ndarray, where: np.ndarray, width: int
           ) -> tuple[np.ndarray, np.ndarray]:
    """(union, slot): the window indices of the chunk's unknowns, sorted, and each window
    index's position in `union` (-1 where none)."""
    _, columns, _ = _rows_of(pattern, chunk)
    mark = np.zeros(width + 1, bool)
    mark[where[columns]] = True
    if mark[width]:
        raise RuntimeError("a tie point's unknowns outside its level window")
    union = np.flatnonzero(mark)
    slot = np.full(width + 1, -1, np.int64)
    slot[union] = np.arange(len(union))
    return union, slot


def _dense_rows(matrix: sp.csr_matrix, chunk: np.ndarray, where: np.ndarray,
                union: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(c, 3, u) the chunk's rows of `matrix` (3P rows) in the window columns of `union`
    (`_union`)."""
    union, slot = union
    rows = (3 * chunk[:, None] + np.arange(3)).ravel()
    row, columns, values = _rows_of(matrix, rows)
    out = np.zeros((len(chunk), 3, len(union)))
    out[row // 3, row % 3, slot[where[columns]]] = values
    return out


def reduced_normal(u: sp.csr_matrix, e: sp.csr_matrix, b: sp.csr_matrix, starts: np.ndarray,
                   sizes: np.ndarray, w_inv: np.ndarray | None = None
                   ) -> tuple[sp.csr_matrix, Levels]:
    """S = U - E^T W^-1 E (b = W^-1 E) and its levels: the levels from the coupling of the
    parameter blocks (U's and the tie points'), then E^T B per chunk of neighbouring points as
    dense products, summed in dense level windows. `w_inv` ((P, 3, 3), W^-1): B's dense rows
    as W_i^-1 E_i instead of gathered from `b`."""
    num_points = b.shape[0] // 3
    n_blocks = len(starts)
    block_of = np.repeat(np.arange(n_blocks), sizes)
    pattern = _point_pattern(b, num_points)
    incidence = sp.csr_matrix((np.ones(pattern.nnz), block_of[pattern.indices],
                               pattern.indptr.copy()), shape=(num_points, n_blocks))
    incidence.sum_duplicates()
    incidence.data[:] = 1.0
    coo = u.tocoo()
    graph = (incidence.T @ incidence + sp.csr_matrix(
        (np.ones(coo.nnz), (block_of[coo.row], block_of[coo.col])), shape=(n_blocks,) * 2))
    levels = order_levels(None, starts, sizes, graph=graph)
    rows, cols, values = [], [], []
    buffer = current = None
    for lv, columns, where, chunk in _level_chunks(levels, pattern):
        if buffer is None or lv != current[0]:
            _emit(buffer, current, rows, cols, values)
            buffer, current = np.zeros((len(columns),) * 2), (lv, columns)
        union = _union(pattern, chunk, where, len(columns))
        e_dense = _dense_rows(e, chunk, where, union)
        b_dense = (_dense_rows(b, chunk, where, union) if w_inv is None
                   else w_inv[chunk] @ e_dense)
        e_flat, b_flat = e_dense.reshape(-1, len(union[0])), b_dense.reshape(-1, len(union[0]))
        buffer[np.ix_(union[0], union[0])] += e_flat.T @ b_flat
    _emit(buffer, current, rows, cols, values)
    nc = len(levels.level_of)
    reduction = sp.csr_matrix((np.concatenate(values) if values else np.zeros(0),
                               (np.concatenate(rows) if rows else np.zeros(0, np.int64),
                                np.concatenate(cols) if cols else np.zeros(0, np.int64))),
                              shape=(nc, nc))
    return (u - reduction).tocsr(), levels


def _emit(buffer, current, rows, cols, values) -> None:
    """The non-zeros of a level window's sum, in original columns."""
    if buffer is None:
        return
    columns = current[1]
    r, c = np.nonzero(buffer)
    rows.append(columns[r])
    cols.append(columns[c])
    values.append(buffer[r, c])


def point_terms(selected: SelectedInverse, b: sp.csr_matrix, w_inv: np.ndarray,
                e_groups: dict[str, sp.csr_matrix], consider: Consider | None = None,
                marginal: bool = True
                ) -> tuple[np.ndarray, dict[str, float], np.ndarray | None]:
    """(marginal Q_pp (P, 3, 3), per group -2 sum E_g * B Q_cc, consider D D^T (P, 3, 3)).
    `marginal` False (with no `e_groups`): the consider part alone, without Q_cc's windows
    (Q_pp is then W^-1)."""
    num_points = len(w_inv)
    q_points = np.array(w_inv, float, copy=True)
    traces = {g: 0.0 for g in e_groups}
    consider_cov = np.zeros((num_points, 3, 3)) if consider is not None else None
    if not num_points:
        return q_points, traces, consider_cov
    if not marginal and e_groups:
        raise ValueError("the groups' traces need the marginal cofactors")
    pattern = _point_pattern(b, num_points)
    if consider is not None:
        consider.products = WindowProducts(selected.levels, consider.d_c)
    window, current = None, None
    for lv, _, where, chunk in _level_chunks(selected.levels, pattern):
        if lv != current:
            window, current = _Window(selected, lv, consider, marginal), lv
        window.terms(chunk, pattern, b, e_groups, q_points, traces, consider_cov)
    return q_points, traces, consider_cov


class _Window:
    """Q_cc (and d_c d_c^T) on one level window, and the chunks of points it serves."""

    def __init__(self, selected: SelectedInverse, level: int, consider: Consider | None,
                 marginal: bool = True):
        if marginal:
            self.columns, self.q = selected.full_window(level)
        else:
            self.columns, self.q = window_columns(selected.levels, level), None
        self.where = np.full(selected.nc, len(self.columns), np.int64)
        self.where[self.columns] = np.arange(len(self.columns))
        self.consider = consider
        self.p = None
        if consider is not None:
            self.p = consider.products.window(level)

    def _dense(self, matrix: sp.csr_matrix, chunk: np.ndarray, union) -> np.ndarray:
        return _dense_rows(matrix, chunk, self.where, union)

    def terms(self, chunk, pattern, b, e_groups, q_points, traces, consider_cov) -> None:
        union_slot = _union(pattern, chunk, self.where, len(self.columns))
        union = union_slot[0]
        b_dense = self._dense(b, chunk, union_slot)
        flat = b_dense.reshape(-1, len(union))
        if self.q is not None:
            bq = (flat @ self.q[np.ix_(union, union)]).reshape(b_dense.shape)
            q_points[chunk] += np.einsum("kax,kbx->kab", bq, b_dense)
            for g, e_g in e_groups.items():
                traces[g] -= 2.0 * float(np.sum(self._dense(e_g, chunk, union_slot) * bq))
        if self.consider is None:
            return
        bp = (flat @ self.p[np.ix_(union, union)]).reshape(b_dense.shape)
        own = np.einsum("kax,kbx->kab", bp, b_dense)
        h = self.consider.h[chunk]
        d = self.consider.d_c[self.columns[union][:, None, None],
                              self.consider.columns[chunk][None]]  # (u, c, 3)
        u = np.einsum("kax,xkj->kaj", b_dense, d)
        cross = h @ u.transpose(0, 2, 1)
        consider_cov[chunk] = own + h @ h.transpose(0, 2, 1) - cross - cross.transpose(0, 2, 1)
