"""Model correction: the images correct the building model where they see it well.

Unger 3.2 and 6.7.3: the hybrid adjustment estimates the model's vertices and planes as
unknowns; the vertex observations f_VT (sigma_VT 0.01 m) normally "almost fix" the model so
that the block moves to the model. Released to 0.5 m they let the planes follow the tie points
(Unger 5.2.2 corrected the generalised model that way: shifts of decimetres per plane, normals
turned by less than 1 deg; topology unchanged). Here the release is selective:

- corrected faces: assigned faces whose tie points determine the face's plane to
  `correction_max_sigma` at each of its vertices (the a posteriori sigma of a plane fitted to
  them, `plane_fit_sigma`: it grows with few points, with points bunched on part of the face
  and with points that scatter about one plane); their vertices are observed with
  `sigma_vt_corrected`;
- every other vertex keeps sigma_VT, and a corrected vertex keeps f_dVT (0.01 m) to the given
  plane of each face of it that is not corrected (a constant plane in the problem), so faces
  the images do not correct keep their planes; a vertex they share with a corrected face slides
  within them;
- f_dVT ties each vertex to every plane of the problem it belongs to: shared vertices stay
  shared, faces stay planar, no face or vertex is added or removed;
- where block and model are unknowns together, the corrected model keeps the given model's
  datum (`datum_condition`): the similarity that the corrected planes' moves imply is observed
  as zero (`sigma_correction_datum`), so that block and planes cannot move together where few
  planes fix the block.

adjust.correction_loop runs the correction after refine's adjustment, by default with the
block held as the adjustment left it (its tie points are the control the planes are fitted to).

`summarise_correction` turns the solve's vertex covariances (precision stage) into the record
of what moved: per corrected vertex its shift, its sigma along the shift (s0-scaled marginal
covariance of the vertex block) and the test |shift| / sigma > `correction_significance`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..assign.assignment import Assignment
from ..citymodel.ground_faces import terrain_mask
from ..citymodel.store import PlaneStore
from ..options import AdjustmentOptions

logger = logging.getLogger(__name__)


@dataclass
class CorrectionSelection:
    """Which faces a solve corrects and which vertices it releases (store indices)."""

    faces: np.ndarray  # (C,) corrected faces, sorted
    num_points: np.ndarray  # (C,) their assigned tie points
    plane_sigma: np.ndarray  # (C,) a posteriori sigma (m) of their fitted planes at the vertices
    released: np.ndarray  # (V,) sorted vertex ids of the corrected faces
    held: np.ndarray  # (H,) faces not corrected that share a released vertex (planes kept)
    not_corrected: dict[str, int] = field(default_factory=dict)  # reason -> assigned faces
    # every assigned face (A,): its tie points and its plane's sigma (inf: none could be fitted)
    assigned: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    assigned_points: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    assigned_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def todict(self) -> dict:
        return {"num_faces": int(len(self.faces)), "num_vertices": int(len(self.released)),
                "num_held_faces": int(len(self.held)),
                "assigned_faces_not_corrected": dict(self.not_corrected)}


def plane_fit_sigma(store: PlaneStore, face: int, points: np.ndarray) -> tuple[float, float]:
    """(s0, sigma) of the plane fitted to `points` (P, 3) by least squares: s0 the RMS of
    their residuals (n - 3 degrees of freedom), sigma the largest a posteriori standard
    deviation of the fitted plane's distance at the face's vertices, s0 sqrt(j^T N^-1 j) with
    N = J^T J of the rows j = (1, u, v) (offset and two tilts; u, v along the face's plane
    from its centroid). Few points, points bunched in a corner (the plane extrapolated to the
    far vertices) and points that scatter about the plane (another surface's points among
    them) all make it large. inf below 4 points or for collinear points."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) < 4:
        return float("inf"), float("inf")
    rotation = store.rotations[face]
    centroid = store.centroids[face]
    local = (points - centroid) @ rotation
    design = np.column_stack([np.ones(len(points)), local[:, :2]])
    normal_matrix = design.T @ design
    if np.linalg.cond(normal_matrix) > 1e12:
        return float("inf"), float("inf")
    solution = np.linalg.solve(normal_matrix, design.T @ local[:, 2])
    residuals = local[:, 2] - design @ solution
    s0 = float(np.sqrt(residuals @ residuals / (len(points) - 3)))
    corners = (store.vertices[store.face_vertex_ids(face)] - centroid) @ rotation[:, :2]
    rows = np.column_stack([np.ones(len(corners)), corners])
    q = np.einsum("ij,jk,ik->i", rows, np.linalg.inv(normal_matrix), rows)
    return s0, float(s0 * np.sqrt(max(float(q.max()), 0.0)))


def select_corrected_faces(store: PlaneStore, assignment: Assignment, points: np.ndarray,
                           options: AdjustmentOptions) -> CorrectionSelection:
    """The faces whose vertices the images correct: assigned faces whose tie points determine
    the plane to `correction_max_sigma` at every vertex (`plane_fit_sigma`). `points` (P, 3):
    current coordinates of `assignment.point_ids`."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    faces, counts = np.unique(assignment.face_index[assignment.assigned], return_counts=True)
    chosen, num_points, sigmas, all_sigmas = [], [], [], []
    reasons: dict[str, int] = {}
    terrain = terrain_mask(store)  # the terrain's cells are no faces of the model
    for face, count in zip(faces.tolist(), counts.tolist()):
        if terrain[face]:
            all_sigmas.append(np.inf)
            reasons["terrain"] = reasons.get("terrain", 0) + 1
            continue
        _, sigma = plane_fit_sigma(store, face, points[assignment.face_index == face])
        all_sigmas.append(sigma)
        if not sigma <= options.correction_max_sigma:
            reasons["plane_sigma_too_large"] = reasons.get("plane_sigma_too_large", 0) + 1
            continue
        chosen.append(face)
        num_points.append(count)
        sigmas.append(sigma)
    chosen_arr = np.array(chosen, dtype=np.int64)
    if len(chosen_arr):
        released = np.unique(np.concatenate([store.face_vertex_ids(f) for f in chosen_arr]))
        indptr, owners = store.vertex_faces
        touching = np.unique(np.concatenate([owners[indptr[v]:indptr[v + 1]] for v in released]))
        held = np.setdiff1d(touching, chosen_arr)
    else:
        released = np.zeros(0, np.int64)
        held = np.zeros(0, np.int64)
    return CorrectionSelection(chosen_arr, np.array(num_points, np.int64),
                               np.array(sigmas, np.float64), released,
                               held.astype(np.int64), reasons, faces.astype(np.int64),
                               counts.astype(np.int64), np.array(all_sigmas, np.float64))


def datum_condition(store: PlaneStore, selection: CorrectionSelection, sigma: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The corrected model keeps the given model's datum: (vertex ids (K,), A (m, 3K),
    X_0 (3K,)) of the condition A (X - X_0) = 0 (core.LinearPointsConditionCost).

    The moves d_i of the released vertices are explained, along the normals n_f of their
    corrected faces, by a small similarity (shift t, rotation w, scale s about the vertices'
    centroid): min sum_(f, i in f) (n_f.(d_i - t - w x c_i - s c_i))^2. Its least-squares
    parameters p = N^+ G d are observed as zero with `sigma` (m; rotation and scale as the
    displacement they cause at the vertices' RMS radius). Only the moves along the normals
    count: a vertex sliding within a plane moves no plane. Directions no corrected plane
    fixes (all normals parallel, say) get no condition; the faces that keep their planes
    hold them. Without it, with the block moving too, block and corrected planes can drift
    together where few planes fix the block (AdjustmentOptions.sigma_correction_datum)."""
    ids = np.asarray(selection.released, np.int64)
    column = {int(v): k for k, v in enumerate(ids)}
    x0 = store.vertices[ids]
    centred = x0 - x0.mean(axis=0)
    rho = max(float(np.sqrt(np.mean(np.sum(centred ** 2, axis=1)))), 1e-9)
    normal_matrix = np.zeros((7, 7))
    g = np.zeros((7, 3 * len(ids)))
    for f in np.asarray(selection.faces, np.int64):
        n = store.normals[f]
        for v in store.face_vertex_ids(f):
            k = column[int(v)]
            c = centred[k]
            j = np.concatenate([n, np.cross(c, n) / rho, [c @ n / rho]])
            normal_matrix += np.outer(j, j)
            g[:, 3 * k:3 * k + 3] += np.outer(j, n)
    values, vectors = np.linalg.eigh(normal_matrix)
    keep = values > 1e-6 * max(float(values.max()), 1e-12)
    matrix = (vectors[:, keep] / values[keep]).T @ g / sigma
    return ids, matrix, x0.reshape(-1)


@dataclass
class ModelCorrection:
    """What the images corrected: per released vertex (store indices, local frame) its given
    and corrected position, the shift, its covariance and the significance test."""

    faces: np.ndarray  # (C,) corrected faces
    held_faces: np.ndarray  # (H,) faces that kept their given plane next to corrected ones
    vertex_ids: np.ndarray  # (V,) released vertices
    given: np.ndarray  # (V, 3)
    corrected: np.ndarray  # (V, 3)
    covariance: np.ndarray | None  # (V, 3, 3) s0^2-scaled marginal covariance, or None
    threshold: float  # the test's critical value of |shift| / sigma
    covariance_note: str = ""
    num_points: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # per face
    not_corrected: dict[str, int] = field(default_factory=dict)  # reason -> assigned faces
    max_plane_sigma: float | None = None  # the selection's threshold (m)
    # every face with tie points in the last solve (A,): points, plane sigma (m)
    assigned: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    assigned_points: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    assigned_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def shift(self) -> np.ndarray:
        return self.corrected - self.given

    @property
    def shift_length(self) -> np.ndarray:
        return np.linalg.norm(self.shift, axis=1)

    @property
    def sigma(self) -> np.ndarray:
        """(V,) sigma of the corrected vertex along its shift (the largest axis of its error
        ellipsoid when it did not move); nan without covariances."""
        if self.covariance is None:
            return np.full(len(self.vertex_ids), np.nan)
        length = self.shift_length
        unit = np.divide(self.shift, length[:, None], out=np.zeros_like(self.shift),
                         where=length[:, None] > 0)
        along = np.einsum("vi,vij,vj->v", unit, self.covariance, unit)
        largest = np.linalg.eigvalsh(self.covariance)[:, -1]
        return np.sqrt(np.maximum(np.where(length > 0, along, largest), 0.0))

    @property
    def sigma_axes(self) -> np.ndarray:
        """(V, 3) sigma E, N, U of the corrected vertices; nan without covariances."""
        if self.covariance is None:
            return np.full((len(self.vertex_ids), 3), np.nan)
        return np.sqrt(np.maximum(np.diagonal(self.covariance, axis1=1, axis2=2), 0.0))

    @property
    def test(self) -> np.ndarray:
        """(V,) |shift| / sigma (nan without covariances)."""
        sigma = self.sigma
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(sigma > 0, self.shift_length / sigma, np.nan)

    @property
    def significant(self) -> np.ndarray:
        """(V,) the shift exceeds `threshold` sigma (False without covariances)."""
        return np.nan_to_num(self.test, nan=0.0) > self.threshold

    def corrected_store(self, store: PlaneStore) -> PlaneStore:
        """`store` (the given model) with the released vertices at their corrected positions
        and every other vertex as given: the model that is written back."""
        vertices = store.vertices.copy()
        vertices[self.vertex_ids] = self.corrected
        return store.with_vertices(vertices)

    def face_shifts(self, store: PlaneStore) -> np.ndarray:
        """(F,) per face of `store` the largest shift of its vertices (0 where none moved)."""
        moved = np.zeros(len(store.vertices))
        moved[self.vertex_ids] = self.shift_length
        ptr, ids = store._face_vertex_csr()
        out = np.zeros(store.num_faces)
        owner = np.repeat(np.arange(store.num_faces), np.diff(ptr))
        np.maximum.at(out, owner, moved[ids])
        return out

    def todict(self) -> dict:
        length = self.shift_length
        sigma = self.sigma
        finite = np.isfinite(sigma)
        return {
            "num_corrected_faces": int(len(self.faces)),
            "num_held_faces": int(len(self.held_faces)),
            "num_corrected_vertices": int(len(self.vertex_ids)),
            "num_significant_vertices": int(np.count_nonzero(self.significant)),
            "significance_threshold": self.threshold,
            "shift_rms_m": float(np.sqrt(np.mean(length ** 2))) if len(length) else None,
            "shift_max_m": float(length.max()) if len(length) else None,
            "median_sigma_m": float(np.median(sigma[finite])) if finite.any() else None,
            "covariances": self.covariance is not None,
            "covariance_note": self.covariance_note,
            "assigned_faces_not_corrected": dict(self.not_corrected),
            "max_plane_sigma_m": self.max_plane_sigma,
        }

    def face_rows(self, store: PlaneStore) -> list[dict]:
        """Per face with tie points in the last solve: its gml:id, building, tie points, the
        a posteriori sigma of the plane they determine (m; None: none) and whether it was
        corrected."""
        corrected = set(self.faces.tolist())
        return [{"face_id": store.faces[f].gml_id, "building_id": store.faces[f].building_id,
                 "num_points": int(n), "plane_sigma_m": float(s) if np.isfinite(s) else None,
                 "corrected": f in corrected}
                for f, n, s in zip(self.assigned.tolist(), self.assigned_points.tolist(),
                                   self.assigned_sigma.tolist())]


def summarise_correction(given: PlaneStore, adjusted: PlaneStore, selection: CorrectionSelection,
                         vertex_ids: np.ndarray | None, covariance: np.ndarray | None,
                         threshold: float, note: str = "",
                         max_plane_sigma: float | None = None) -> ModelCorrection:
    """The record of a correction: `given` and `adjusted` share the topology; `selection` is
    the last solve's; `vertex_ids` / `covariance` ((K,), (K, 3, 3)) the vertex blocks'
    covariances from the precision stage (None: not computed)."""
    released = np.asarray(selection.released, np.int64)
    cov = None
    if covariance is not None and vertex_ids is not None:
        row = {int(v): k for k, v in enumerate(np.asarray(vertex_ids))}
        missing = [int(v) for v in released if int(v) not in row]
        if missing:
            raise ValueError(f"no covariance for {len(missing)} corrected vertices")
        cov = np.asarray(covariance)[[row[int(v)] for v in released]].reshape(-1, 3, 3)
    return ModelCorrection(
        faces=np.asarray(selection.faces, np.int64), held_faces=np.asarray(selection.held),
        vertex_ids=released, given=given.vertices[released].copy(),
        corrected=adjusted.vertices[released].copy(), covariance=cov, threshold=threshold,
        covariance_note=note, num_points=np.asarray(selection.num_points, np.int64),
        not_corrected=dict(selection.not_corrected), max_plane_sigma=max_plane_sigma,
        assigned=np.asarray(selection.assigned, np.int64),
        assigned_points=np.asarray(selection.assigned_points, np.int64),
        assigned_sigma=np.asarray(selection.assigned_sigma, np.float64))
