"""Selected inversion of the reduced normal matrix: its inverse where the covariances need it.

The reduced (camera-side) normal matrix S of a block is sparse: two unknowns are coupled only
when they observe a common tie point. The covariances of images, planes and vertices are
diagonal blocks of Q = S^-1, and a tie point's marginal covariance needs Q only between the
unknowns that observe it (method.md 9: Q_pp = W^-1 + B Q_cc B^T), i.e. on the non-zero pattern
of S. A dense inverse costs (6 x images)^3; this one costs about images x front^2.

1. Global unknowns (coupled to a large share of the others: intrinsics shared by all images,
   a GNSS offset) form a border of k columns.
2. The rest is ordered in levels of a breadth-first search of its coupling graph (from a
   pseudo-peripheral unknown): an unknown is coupled only within its level and the two next
   to it, so S (without the border) is block tridiagonal; consecutive small levels are merged.
3. Block Cholesky A = L L^T (diagonal blocks L_k, below them M_k), and the selected inverse
   by Takahashi's recursion, from the last level back:
   Z_{k+1,k} = -Z_{k+1,k+1} M_k L_k^-1,  Z_kk = (L_k L_k^T)^-1 - Z_{k+1,k}^T M_k L_k^-1.
   Z equals A^-1 on the block tridiagonal pattern, which holds every coupled pair.
4. The border by its Schur complement: with Y = A^-1 C and K = (D - C^T Y)^-1,
   Q_AA = A^-1 + Y K Y^T, Q_AB = -Y K, Q_BB = K.

Exact (no approximation) within the pattern; products Q x by block forward and back
substitution. A singular S (a datum defect) raises numpy.linalg.LinAlgError.
"""

from __future__ import annotations

import copy
import logging
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components, shortest_path

logger = logging.getLogger(__name__)

#: An unknown coupled to more than this share of all unknowns goes to the border.
BORDER_SHARE = 0.25
#: Consecutive levels are merged while their columns stay below this many.
MERGE_COLUMNS = 400
#: ... and has more than this many neighbours (small blocks stay without a border).
MIN_BORDER_DEGREE = 64


@dataclass
class Levels:
    """The ordering: `perm` (new -> old column), level bounds in the permuted order of the
    non-border columns, and the border's old columns (last in `perm`)."""

    perm: np.ndarray
    bounds: np.ndarray  # (K + 1,) starts of the levels, last = number of non-border columns
    border: np.ndarray  # old column indices of the border
    level_of: np.ndarray  # (nc,) level of each old column; -1 for the border
    local_of: np.ndarray  # (nc,) position within its level (within the border for -1)


def _block_graph(s: sp.csr_matrix, block_of: np.ndarray, num_blocks: int) -> sp.csr_matrix:
    coo = s.tocoo()
    graph = sp.csr_matrix((np.ones(len(coo.row)), (block_of[coo.row], block_of[coo.col])),
                          shape=(num_blocks, num_blocks))
    graph.data[:] = 1.0
    return graph


def _bfs_levels(graph: sp.csr_matrix) -> np.ndarray:
    """Level of each node: BFS distance from a pseudo-peripheral node, per connected
    component, components one after the other."""
    num, labels = connected_components(graph, directed=False)
    level = np.zeros(graph.shape[0], np.int64)
    offset = 0
    for c in range(num):
        nodes = np.flatnonzero(labels == c)
        sub = graph[nodes][:, nodes]
        start = 0
        for _ in range(2):  # two sweeps: the farthest node from the farthest node
            dist = shortest_path(sub, unweighted=True, directed=False, indices=start)
            start = int(np.argmax(dist))
        dist = shortest_path(sub, unweighted=True, directed=False, indices=start)
        level[nodes] = dist.astype(np.int64) + offset
        offset += int(dist.max()) + 1
    return level


def order_levels(s: sp.csr_matrix | None, starts: np.ndarray, sizes: np.ndarray,
                 graph: sp.csr_matrix | None = None) -> Levels:
    """Levels of the parameter blocks (`starts`, `sizes`: their columns in `s`), from the
    coupling of `s` or a given block coupling `graph` (num_blocks x num_blocks)."""
    num_blocks = len(starts)
    nc = int(np.sum(sizes))
    if graph is None:
        graph = _block_graph(s, np.repeat(np.arange(num_blocks), sizes), num_blocks)
    graph = sp.csr_matrix(graph)
    degree = np.diff(graph.indptr)
    is_border = degree > max(BORDER_SHARE * num_blocks, MIN_BORDER_DEGREE)
    inner = np.flatnonzero(~is_border)
    level = np.full(num_blocks, -1, np.int64)
    if len(inner):
        level[inner] = _bfs_levels(graph[inner][:, inner])
    # merge consecutive levels up to MERGE_COLUMNS columns
    width = np.bincount(level[inner], weights=sizes[inner]) if len(inner) else np.zeros(0)
    merged, group, filled = np.zeros(len(width), np.int64), 0, 0.0
    for k, w in enumerate(width):
        if filled and filled + w > MERGE_COLUMNS:
            group, filled = group + 1, 0.0
        merged[k] = group
        filled += w
    level[inner] = merged[level[inner]]
    order = np.concatenate([inner[np.argsort(level[inner], kind="stable")],
                            np.flatnonzero(is_border)])
    perm = np.concatenate([np.arange(starts[b], starts[b] + sizes[b]) for b in order]
                          ) if num_blocks else np.zeros(0, np.int64)
    column_level = np.repeat(level, sizes)
    counts = np.bincount(column_level[column_level >= 0], minlength=int(level.max(initial=-1)) + 1)
    bounds = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    local = np.empty(nc, np.int64)
    position = np.empty(nc, np.int64)
    position[perm] = np.arange(nc)
    starts_of_level = np.append(bounds[:-1], bounds[-1])  # border starts at bounds[-1]
    local[perm] = position[perm] - starts_of_level[column_level[perm]]
    return Levels(perm.astype(np.int64), bounds, perm[bounds[-1]:], column_level, local)


def window_columns(levels: Levels, level: int) -> np.ndarray:
    """Original columns of levels `level`, `level + 1` and the border, in that order."""
    b = levels.bounds
    hi = b[min(level + 2, len(b) - 1)]
    return np.concatenate([levels.perm[b[level]:hi], levels.border])


class WindowProducts:
    """left[cols] right[cols]^T on the columns of each level window (`window_columns`),
    assembled from per-level blocks. Consecutive windows share a level, whose own block is
    kept from one window to the next (windows asked for in ascending order); the blocks
    across levels are taken as symmetric."""

    def __init__(self, levels: Levels, left: np.ndarray, right: np.ndarray | None = None):
        self.levels, self.left = levels, left
        self.right = left if right is None else right
        self._kept: tuple[int, np.ndarray | None] = (-1, None)

    def _own(self, level: int, columns: np.ndarray) -> np.ndarray:
        if self._kept[0] != level:
            left = self.left[columns]
            right = left if self.right is self.left else self.right[columns]
            self._kept = (level, left @ right.T)
        return self._kept[1]

    def window(self, level: int) -> np.ndarray:
        b, perm = self.levels.bounds, self.levels.perm
        parts = [perm[b[level]:b[level + 1]]]
        if level + 2 < len(b):
            parts.append(perm[b[level + 1]:b[level + 2]])
        inner = len(parts)
        parts.append(self.levels.border)
        offsets = np.concatenate([[0], np.cumsum([len(p) for p in parts])])
        out = np.empty((offsets[-1], offsets[-1]))
        for i, rows in enumerate(parts):
            for j in range(i + 1):
                block = (self._own(level + i, rows) if i == j and i < inner
                         else self.left[rows] @ self.right[parts[j]].T)
                out[offsets[i]:offsets[i + 1], offsets[j]:offsets[j + 1]] = block
                if i != j:
                    out[offsets[j]:offsets[j + 1], offsets[i]:offsets[i + 1]] = block.T
        return out


class SelectedInverse:
    """Q = S^-1 on the coupling pattern of S, and products Q x (see the module docstring)."""

    def __init__(self, s: sp.spmatrix, starts, sizes, low_rank: sp.spmatrix | None = None,
                 levels: Levels | None = None):
        """`s` (sparse, symmetric positive definite), the parameter blocks' column `starts` and
        `sizes`; `low_rank`: rows H whose H^T H is added to `s` by Woodbury instead (rows
        coupling unknowns far apart, which would merge the levels); `levels`: the ordering
        when known (`order_levels` of the same coupling)."""
        s = sp.csr_matrix(s)
        self.nc = s.shape[0]
        self.levels = levels if levels is not None else order_levels(
            s, np.asarray(starts, np.int64), np.asarray(sizes, np.int64))
        p = self.levels.perm
        sp_ = s[p][:, p].tocsr()
        bounds = self.levels.bounds
        self.num_levels = len(bounds) - 1
        n_a = int(bounds[-1])
        self._factor(sp_, bounds)
        c = sp_[:n_a, n_a:].toarray()
        d = sp_[n_a:, n_a:].toarray()
        self.y = self._solve_a(c) if c.size else np.zeros((n_a, 0))
        schur = d - c.T @ self.y
        self.k = scipy.linalg.cho_solve(scipy.linalg.cho_factor(schur, lower=True),
                                        np.eye(len(d))) if len(d) else np.zeros((0, 0))
        self.k = 0.5 * (self.k + self.k.T)
        self._diag = self._sub = None  # the selected inverse, formed when first read
        self._low_rank(low_rank)

    def _low_rank(self, h: sp.spmatrix | None) -> None:
        """Q = Q0 - V M V^T with V = Q0 H^T, M = (I + H V)^-1 (Woodbury)."""
        self.v, self.m = np.zeros((self.nc, 0)), np.zeros((0, 0))
        self._vm = self.v
        self._low_rank_windows = None
        self.h = sp.csr_matrix((0, self.nc))
        if h is None or not h.shape[0]:
            return
        self.h = sp.csr_matrix(h)
        self.v = self._base_matmul(self.h.T.toarray())
        self._set_inner(np.asarray(self.h @ self.v))

    def _set_inner(self, hv: np.ndarray) -> None:
        """M = (I + H V)^-1 and V M from H V."""
        self.hv = hv
        inner = np.eye(len(hv)) + hv
        self.m = np.linalg.inv(0.5 * (inner + inner.T))
        self.m = 0.5 * (self.m + self.m.T)
        self._vm = None  # V M, formed when first read
        self._low_rank_windows = None

    @property
    def vm(self) -> np.ndarray:
        """V M (nc, k)."""
        if self._vm is None:
            self._vm = self.v @ self.m
        return self._vm

    def with_low_rank_scaled(self, scale: np.ndarray) -> "SelectedInverse":
        """The inverse of the same S with the low-rank rows scaled, diag(scale) H: shares
        the factorisation (and the selected inverse of S), V' = V diag(scale), no new solve."""
        out = copy.copy(self)
        if not self.v.shape[1]:
            return out
        scale = np.asarray(scale, float)
        out.h = sp.csr_matrix(sp.diags(scale) @ self.h)
        out.v = self.v * scale
        out._set_inner(scale[:, None] * self.hv * scale)
        return out

    def low_rank_trace(self) -> float:
        """trace(H Q H^T) of the low-rank rows (Q H^T = V M)."""
        return float(np.trace(self.hv @ self.m)) if self.v.shape[1] else 0.0

    def _low_rank_part(self, rows: np.ndarray, cols: np.ndarray | None = None) -> np.ndarray:
        """V M V^T on rows x cols (dense block; `cols` None: the same as rows)."""
        return self.vm[rows] @ self.v[rows if cols is None else cols].T

    # -- factorisation ------------------------------------------------------------------------

    def _factor(self, a: sp.csr_matrix, bounds: np.ndarray) -> None:
        self.chol, self.below = [], []
        previous = None
        for k in range(self.num_levels):
            lo, hi = bounds[k], bounds[k + 1]
            block = a[lo:hi, lo:hi].toarray()
            if previous is not None:
                block -= previous @ previous.T
            factor = np.linalg.cholesky(0.5 * (block + block.T))  # LinAlgError if singular
            self.chol.append(factor)
            if k + 1 < self.num_levels:
                sub = a[hi:bounds[k + 2], lo:hi].toarray()
                # M_k = A_{k+1,k} L_k^-T
                previous = scipy.linalg.solve_triangular(factor, sub.T, lower=True).T
                self.below.append(previous)

    def _solve_a(self, rhs: np.ndarray) -> np.ndarray:
        """A^-1 rhs (rows in the permuted order of the non-border columns). The forward sweep
        takes a column from the first level where it is non-zero (zero before)."""
        b = self.levels.bounds
        z = np.array(rhs, float, copy=True)
        flat = z.ndim == 1
        if flat:
            z = z[:, None]
        order, active = self._by_first_level(z)
        if order is not None:
            z = z[:, order]
        for k in range(self.num_levels):  # L z = rhs
            lo, hi = b[k], b[k + 1]
            n = active[k]
            if not n:
                continue
            if k:
                z[lo:hi, :n] -= self.below[k - 1] @ z[b[k - 1]:lo, :n]
            z[lo:hi, :n] = scipy.linalg.solve_triangular(self.chol[k], z[lo:hi, :n], lower=True)
        for k in range(self.num_levels - 1, -1, -1):  # L^T x = z
            lo, hi = b[k], b[k + 1]
            if k + 1 < self.num_levels:
                z[lo:hi] -= self.below[k].T @ z[hi:b[k + 2]]
            z[lo:hi] = scipy.linalg.solve_triangular(self.chol[k], z[lo:hi], lower=True,
                                                     trans="T")
        if order is not None:
            z[:, order] = z.copy()
        return z.ravel() if flat else z

    def _by_first_level(self, z: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
        """(column order by the first level where a column is non-zero, or None for one
        column; per level the number of columns non-zero there or before, in that order)."""
        if z.shape[1] < 2 or not len(z):
            return None, np.full(self.num_levels, z.shape[1], np.int64)
        nonzero = z != 0
        first_row = np.where(nonzero.any(axis=0), nonzero.argmax(axis=0), len(z))
        first = np.searchsorted(self.levels.bounds, first_row, side="right") - 1
        order = np.argsort(first, kind="stable")
        active = np.searchsorted(first[order], np.arange(self.num_levels), side="right")
        return order, active

    @property
    def diag(self) -> list[np.ndarray]:
        """Z_kk: A^-1 on each level (Takahashi's recursion on first use; products Q x alone
        do not need it)."""
        if self._diag is None:
            self._takahashi()
        return self._diag

    @property
    def sub(self) -> list[np.ndarray]:
        """Z_{k+1,k}: A^-1 between consecutive levels."""
        if self._sub is None:
            self._takahashi()
        return self._sub

    def _takahashi(self) -> None:
        """Z_kk and Z_{k+1,k} of A^-1, from the last level back."""
        num = self.num_levels
        diag, sub = [None] * num, [None] * max(num - 1, 0)
        for k in range(num - 1, -1, -1):
            factor = self.chol[k]
            inverse = scipy.linalg.cho_solve((factor, True), np.eye(len(factor)))
            if k + 1 < num:
                # X = M_k L_k^-1, Z_{k+1,k} = -Z_{k+1,k+1} X, Z_kk = A_k'^-1 - Z_{k+1,k}^T X
                x = scipy.linalg.solve_triangular(factor, self.below[k].T, lower=True,
                                                  trans="T").T
                sub[k] = -diag[k + 1] @ x
                inverse -= sub[k].T @ x
            diag[k] = 0.5 * (inverse + inverse.T)
        self._diag, self._sub = diag, sub

    # -- access ---------------------------------------------------------------------------------

    def __matmul__(self, rhs: np.ndarray) -> np.ndarray:
        """Q rhs for a dense (nc,) or (nc, r) right-hand side in the original column order."""
        rhs = np.asarray(rhs, float)
        out = self._base_matmul(rhs)
        if self.v.shape[1]:  # V M V^T rhs = V M H (Q0 rhs): H is sparse
            flat = out.reshape(self.nc, -1)
            out = (flat - self.v @ (self.m @ np.asarray(self.h @ flat))).reshape(out.shape)
        return out

    def _base_matmul(self, rhs: np.ndarray) -> np.ndarray:
        """Q0 rhs: without the low-rank rows."""
        flat = rhs.ndim == 1
        r = rhs.reshape(self.nc, -1)[self.levels.perm]
        n_a = int(self.levels.bounds[-1])
        x_b = self.k @ (r[n_a:] - self.y.T @ r[:n_a])
        x_a = self._solve_a(r[:n_a]) - self.y @ x_b
        out = np.empty_like(r)
        out[self.levels.perm] = np.vstack([x_a, x_b])
        return out.ravel() if flat else out

    def __rmatmul__(self, lhs: np.ndarray) -> np.ndarray:
        """lhs Q = (Q lhs^T)^T (Q is symmetric)."""
        return (self @ np.asarray(lhs, float).T).T

    def local(self, columns: np.ndarray) -> np.ndarray:
        """Dense Q[columns][:, columns] for original columns whose levels lie within two
        consecutive ones (any set of mutually coupled unknowns) or the border."""
        columns = np.asarray(columns, np.int64)
        lv = self.levels.level_of[columns]
        inner = lv >= 0
        out = np.zeros((len(columns), len(columns)))
        if inner.any():
            lo, hi = int(lv[inner].min()), int(lv[inner].max())
            if hi > lo + 1:
                raise ValueError("columns span more than two consecutive levels")
            if hi == lo:
                idx = self.levels.local_of[columns[inner]]
                out[np.ix_(inner, inner)] = self.diag[lo][np.ix_(idx, idx)]
            else:
                idx = self.window_offsets(lo)[lv[inner] - lo] + self.levels.local_of[columns[inner]]
                out[np.ix_(inner, inner)] = self.window(lo)[np.ix_(idx, idx)]
        out = out + self._border_terms(columns)
        if self.v.shape[1]:
            out -= self._low_rank_part(columns)
        return out

    def window_offsets(self, level: int) -> np.ndarray:
        b = self.levels.bounds
        return np.array([0, b[level + 1] - b[level]], np.int64)

    def window(self, level: int, with_border: bool = False) -> np.ndarray:
        """Dense A^-1 part of Q on levels `level` and `level + 1` (Z blocks, plus the border's
        Y K Y^T with `with_border`)."""
        b = self.levels.bounds
        if level + 1 >= self.num_levels:
            out = self.diag[level].copy()
            rows = slice(b[level], b[level + 1])
        else:
            m0, m1 = len(self.diag[level]), len(self.diag[level + 1])
            out = np.empty((m0 + m1, m0 + m1))
            out[:m0, :m0] = self.diag[level]
            out[m0:, m0:] = self.diag[level + 1]
            out[m0:, :m0] = self.sub[level]
            out[:m0, m0:] = self.sub[level].T
            rows = slice(b[level], b[level + 2])
        if with_border and self.y.shape[1]:
            y = self.y[rows]
            out += y @ self.k @ y.T
        return out

    def full_window(self, level: int) -> tuple[np.ndarray, np.ndarray]:
        """(original columns, dense Q on them) for levels `level`, `level + 1` and the
        border: every entry a tie point whose unknowns start at `level` needs."""
        columns = window_columns(self.levels, level)
        inner = self.window(level)
        out = np.zeros((len(columns), len(columns)))
        out[:len(inner), :len(inner)] = inner
        if self.y.shape[1]:
            r = self.border_rows(columns)
            out += r @ self.k @ r.T
        if self.v.shape[1]:
            if self._low_rank_windows is None:
                self._low_rank_windows = WindowProducts(self.levels, self.vm, self.v)
            out -= self._low_rank_windows.window(level)
        return columns, out

    def _border_terms(self, columns: np.ndarray) -> np.ndarray | float:
        """The border's part of Q[columns][:, columns]: R K R^T (`border_rows`)."""
        if not self.y.shape[1]:
            return 0.0
        r = self.border_rows(columns)
        return r @ self.k @ r.T

    def border_rows(self, columns: np.ndarray) -> np.ndarray:
        """R with Q's border part R K R^T for `columns`: R = [Y | -I] (Y K Y^T among the
        inner columns, -Y K across, K within the border)."""
        n_a = int(self.levels.bounds[-1])
        position = np.empty(self.nc, np.int64)
        position[self.levels.perm] = np.arange(self.nc)
        pos = position[np.asarray(columns, np.int64)]
        r = np.zeros((len(pos), self.y.shape[1]))
        inner = pos < n_a
        r[inner] = self.y[pos[inner]]
        r[~inner, pos[~inner] - n_a] = -1.0
        return r

    def __getitem__(self, key) -> np.ndarray:
        """Q[rows, columns] for a diagonal block given as (slice, slice) or an index array
        pair of the same columns (as `numpy.ndarray` indexing of a dense Q)."""
        rows, cols = key
        rows = np.arange(self.nc)[rows] if isinstance(rows, slice) else np.asarray(rows)
        cols = np.arange(self.nc)[cols] if isinstance(cols, slice) else np.asarray(cols)
        if rows.ndim == 2:  # np.ix_ form
            rows, cols = rows.ravel(), cols.ravel()
        if not np.array_equal(rows, cols):
            raise IndexError("only diagonal blocks of Q are held")
        return self.local(rows)

    def trace_with(self, u: sp.spmatrix) -> float:
        """sum_ij u_ij Q_ij for a matrix `u` on the coupling pattern; the low-rank term as
        sum((U V) * (V M)), not pair by pair."""
        coo = sp.coo_matrix(u)
        total = float(np.sum(coo.data * self.pattern_values(coo.row, coo.col, low_rank=False)))
        if self.v.shape[1]:  # over u's non-zero rows only
            u = sp.csr_matrix(u)
            rows = np.flatnonzero(np.diff(u.indptr))
            total -= float(np.sum(np.asarray(u[rows] @ self.v) * self.vm[rows]))
        return total

    def pattern_values(self, rows: np.ndarray, cols: np.ndarray, low_rank: bool = True
                       ) -> np.ndarray:
        """Q[rows[i], cols[i]] for pairs of coupled columns (vectorised); `low_rank` False:
        without the low-rank term."""
        rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
        lr, lc = self.levels.level_of[rows], self.levels.level_of[cols]
        out = np.zeros(len(rows))
        inner = (lr >= 0) & (lc >= 0)
        ir, ic = self.levels.local_of[rows], self.levels.local_of[cols]
        if np.any(inner & (np.abs(lr - lc) > 1)):
            raise ValueError("pairs more than one level apart are not held")
        # pairs grouped by (row level, column level) with one sort, each group from its block
        key = np.where(inner, lr * 3 + (lc - lr + 1), -1)
        order = np.argsort(key, kind="stable")
        keys, starts = np.unique(key[order], return_index=True)
        ends = np.append(starts[1:], len(order))
        for group, lo, hi in zip(keys, starts, ends):
            if group < 0:
                continue
            idx = order[lo:hi]
            k, shift = divmod(int(group), 3)  # shift 1: same level, 0: column level below
            if shift == 1:
                out[idx] = self.diag[k][ir[idx], ic[idx]]
            elif shift == 0:
                out[idx] = self.sub[k - 1][ir[idx], ic[idx]]
            else:
                out[idx] = self.sub[k][ic[idx], ir[idx]]
        for lo in range(0, len(rows) if self.y.shape[1] else 0, 100_000):
            hi = lo + 100_000
            rr, rc = self.border_rows(rows[lo:hi]), self.border_rows(cols[lo:hi])
            out[lo:hi] += np.sum((rr @ self.k) * rc, axis=1)
        for lo in range(0, len(rows) if self.v.shape[1] and low_rank else 0, 100_000):
            hi = lo + 100_000
            out[lo:hi] -= np.sum(self.vm[rows[lo:hi]] * self.v[cols[lo:hi]], axis=1)
        return out

    @property
    def sizes(self) -> list[int]:
        return np.diff(self.levels.bounds).tolist()
