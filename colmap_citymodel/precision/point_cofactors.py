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

from .selected import SelectedInverse

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
    """(P, nc): the columns any of a point's three rows touches, sorted per row."""
    pattern = (abs(b[0::3]) + abs(b[1::3]) + abs(b[2::3])).tocsr()
    pattern.sort_indices()
    if pattern.shape[0] != num_points:
        raise ValueError(f"{b.shape[0]} rows for {num_points} points")
    return pattern


def _rows_of(matrix: sp.csr_matrix, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row slot, column, value) of the entries of `rows` (in that order)."""
    counts = matrix.indptr[rows + 1] - matrix.indptr[rows]
    first = np.repeat(matrix.indptr[rows] - np.concatenate([[0], np.cumsum(counts)[:-1]]),
                      counts)
    flat = first + np.arange(int(counts.sum()))
    return np.repeat(np.arange(len(rows)), counts), matrix.indices[flat], matrix.data[flat]


def point_terms(selected: SelectedInverse, b: sp.csr_matrix, w_inv: np.ndarray,
                e_groups: dict[str, sp.csr_matrix], consider: Consider | None = None
                ) -> tuple[np.ndarray, dict[str, float], np.ndarray | None]:
    """(marginal Q_pp (P, 3, 3), per group -2 sum E_g * B Q_cc, consider D D^T (P, 3, 3))."""
    num_points = len(w_inv)
    q_points = np.array(w_inv, float, copy=True)
    traces = {g: 0.0 for g in e_groups}
    consider_cov = np.zeros((num_points, 3, 3)) if consider is not None else None
    if not num_points:
        return q_points, traces, consider_cov
    pattern = _point_pattern(b, num_points)
    t = np.diff(pattern.indptr)
    level = selected.levels.level_of[pattern.indices]
    level = np.where(level < 0, np.iinfo(np.int64).max, level)
    base = np.full(num_points, np.iinfo(np.int64).max)
    nonempty = t > 0
    base[nonempty] = np.minimum.reduceat(level, pattern.indptr[:-1][nonempty])
    base[base == np.iinfo(np.int64).max] = 0
    for lv in np.unique(base[nonempty]):
        window = _Window(selected, int(lv), consider)
        points = np.flatnonzero(nonempty & (base == lv))
        first = np.minimum.reduceat(window.where[pattern.indices], pattern.indptr[:-1])[points]
        points = points[np.argsort(first, kind="stable")]  # neighbours share their unknowns
        for lo in range(0, len(points), CHUNK_POINTS):
            chunk = points[lo:lo + CHUNK_POINTS]
            window.terms(chunk, pattern, b, e_groups, q_points, traces, consider_cov)
    return q_points, traces, consider_cov


class _Window:
    """Q_cc (and d_c d_c^T) on one level window, and the chunks of points it serves."""

    def __init__(self, selected: SelectedInverse, level: int, consider: Consider | None):
        self.columns, self.q = selected.full_window(level)
        self.where = np.full(selected.nc, len(self.columns), np.int64)
        self.where[self.columns] = np.arange(len(self.columns))
        self.consider = consider
        self.p = None
        if consider is not None:
            d = consider.d_c[self.columns]
            self.p = d @ d.T

    def _dense(self, matrix: sp.csr_matrix, chunk: np.ndarray, union: np.ndarray) -> np.ndarray:
        """(c, 3, u) the chunk's rows of `matrix` (3P rows) in the columns `union`."""
        rows = (3 * chunk[:, None] + np.arange(3)).ravel()
        slot, columns, values = _rows_of(matrix, rows)
        out = np.zeros((len(chunk), 3, len(union)))
        out[slot // 3, slot % 3, np.searchsorted(union, self.where[columns])] = values
        return out

    def terms(self, chunk, pattern, b, e_groups, q_points, traces, consider_cov) -> None:
        _, columns, _ = _rows_of(pattern, chunk)
        union = np.unique(self.where[columns])
        if union[-1] == len(self.columns):
            raise RuntimeError("a tie point's unknowns outside its level window")
        b_dense = self._dense(b, chunk, union)
        flat = b_dense.reshape(-1, len(union))
        bq = (flat @ self.q[np.ix_(union, union)]).reshape(b_dense.shape)
        q_points[chunk] += np.einsum("kax,kbx->kab", bq, b_dense)
        for g, e_g in e_groups.items():
            traces[g] -= 2.0 * float(np.sum(self._dense(e_g, chunk, union) * bq))
        if self.consider is None:
            return
        bp = (flat @ self.p[np.ix_(union, union)]).reshape(b_dense.shape)
        own = np.einsum("kax,kbx->kab", bp, b_dense)
        h = self.consider.h[chunk]
        d = self.consider.d_c[self.columns[union]][:, self.consider.columns[chunk]]  # (u, c, 3)
        u = np.einsum("kax,xkj->kaj", b_dense, d)
        cross = h @ u.transpose(0, 2, 1)
        consider_cov[chunk] = own + h @ h.transpose(0, 2, 1) - cross - cross.transpose(0, 2, 1)
