"""Faces as units: a face's model error is one error shared by all its tie points.

With `AdjustmentOptions.face_weighting` "face" each face counts as one observation of its
offset (adjust.problem.face_sigmas). A face whose points sit further from it on average than
the model's generalisation error explains (an arcade behind a facade, a set-back storey, a
plane the model got wrong) is weighed less, by Huber's rule applied to the face's mean offset:
with z = |mean offset| / sqrt(sigma_face^2 + sigma_dtp^2 / n), the face's weight is
min(1, FACE_HUBER_K / z), i.e. its sigma grows by sqrt(z / FACE_HUBER_K).

A face's model is also tilted (`tilt_axes`): with `AdjustmentOptions.face_tilt_weights` each
tie point's sigma includes what that tilt moves the face at the point (`tilt_variances`,
adjust.problem.tie_point_sigmas).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..options import AdjustmentOptions

#: The faces' offset sigma (m) until their offsets give their own: Unger's typical size of a LOD2
#: model's generalisation effects (5.3).
DEFAULT_SIGMA_FACE = 0.20

def sigma_face_in_use(options: AdjustmentOptions, estimated: float | None = None) -> float:
    """The faces' offset sigma (m) a solve uses: `estimated` (the faces' own, an assignment's
    `face_sigma`), else `options.sigma_face`, else DEFAULT_SIGMA_FACE."""
    for sigma in (estimated, options.sigma_face):
        if sigma is not None:
            return float(sigma)
    return DEFAULT_SIGMA_FACE


#: Huber's constant for a face's mean offset, in sigmas of what the model's generalisation
#: error and the points' own noise allow: within it a face keeps its full weight (2: a face
#: further off happens by chance about once in twenty).
FACE_HUBER_K = 2.0


@dataclass
class FaceOffsets:
    """Per face of a solved problem: its number of tie points, their mean signed distance from
    the adjusted plane (m) and that mean in sigmas of its expected spread."""

    faces: np.ndarray
    counts: np.ndarray
    offsets: np.ndarray
    z: np.ndarray


def face_offsets(problem, options: AdjustmentOptions, sigma_face: float | None = None
                 ) -> FaceOffsets:
    """The faces' mean offsets at `problem`'s solution (adjust.problem.HybridProblem); their
    z with the faces' offset sigma `sigma_face` (default `options.sigma_face`)."""
    sigma_face = options.sigma_face if sigma_face is None else sigma_face
    faces = np.asarray(problem.blocks.faces, np.int64)
    if not len(faces) or not len(problem.point_faces):
        return FaceOffsets(faces, np.zeros(len(faces), np.int64), np.zeros(len(faces)),
                           np.zeros(len(faces)))
    slots = np.searchsorted(faces, problem.point_faces)
    metres = problem.residuals["dTP"] * options.sigma_dtp
    counts = np.bincount(slots, minlength=len(faces))
    offsets = np.bincount(slots, weights=metres, minlength=len(faces)) / np.maximum(counts, 1)
    # With the offsets estimated, a face's points sit at its offset: the distance from the
    # plane is the mean residual less it.
    estimated = problem.blocks.generalisation_slots
    if estimated and options.face_weighting == "offsets":
        slots_with = np.fromiter(estimated.keys(), np.int64, len(estimated))
        values = problem.blocks.generalisation_array[list(estimated.values())]
        offsets[slots_with] -= values
    spread = np.sqrt(sigma_face ** 2 + options.sigma_dtp ** 2 / np.maximum(counts, 1))
    return FaceOffsets(faces, counts, offsets, np.abs(offsets) / spread)


#: Fewest faces from whose mean offsets their sigma is estimated: the seven parameters of the
#: block's datum absorb part of their spread, and fewer faces leave too little of it.
MIN_FACES_FOR_SIGMA = 12

#: The estimated sigma of the faces' offsets is kept at least this (m): a model does not fit
#: its city better than a tie point's own position (a few centimetres).
SIGMA_FACE_FLOOR = 0.02


def estimate_sigma_face(found: FaceOffsets, options: AdjustmentOptions,
                        model_faces: np.ndarray | None = None) -> float | None:
    """The faces' offset sigma (m) from their mean offsets by moments: the mean of the
    squared offsets less their points' noise (sigma_dtp^2 / n), over the faces' number less the
    block's seven datum parameters; None with fewer than MIN_FACES_FOR_SIGMA faces.
    `model_faces`: (F,) bool, the faces of `found` that are the city model's (terrain cells
    have their own error model, a DTM's noise and tile offsets, and do not count)."""
    keep = np.ones(len(found.faces), bool) if model_faces is None else np.asarray(model_faces)
    return offsets_sigma(found.offsets[keep],
                         options.sigma_dtp ** 2 / np.maximum(found.counts[keep], 1))


def offsets_sigma(offsets: np.ndarray, noise: np.ndarray) -> float | None:
    """The sigma (m) of faces' mean `offsets` by moments: their sum of squares less their
    points' noise (`noise`, each offset's variance from its points alone) over the faces'
    number less the block's seven datum parameters, at least SIGMA_FACE_FLOOR; None with fewer
    than MIN_FACES_FOR_SIGMA faces."""
    if len(offsets) < MIN_FACES_FOR_SIGMA:
        return None
    variance = (np.sum(offsets ** 2) - np.sum(noise)) / (len(offsets) - 7)
    return float(max(np.sqrt(max(variance, 0.0)), SIGMA_FACE_FLOOR))


def outlier_factors(problem, options: AdjustmentOptions, sigma_face: float
                    ) -> dict[int, float]:
    """{face: sigma factor > 1} for the faces beyond FACE_HUBER_K (empty unless
    `options.face_weighting` is "face"), their offsets' sigma `sigma_face`."""
    if options.face_weighting != "face":
        return {}
    found = face_offsets(problem, options, sigma_face)
    beyond = found.z > FACE_HUBER_K
    return {int(f): float(np.sqrt(z / FACE_HUBER_K))
            for f, z in zip(found.faces[beyond], found.z[beyond])}


@dataclass
class _FaceRows:
    """Each assigned point's row of the linearised similarity (translation, rotation, scale
    about the points' centroid) that moves it along its face's normal, its signed distance,
    and its face."""

    design: np.ndarray  # (P, 7)
    distance: np.ndarray  # (P,)
    slot: np.ndarray  # (P,) index into `faces`
    faces: np.ndarray  # (F,) face ids


def _face_rows(points: np.ndarray, assignment, store) -> _FaceRows:
    mask = assignment.assigned
    faces = assignment.face_index[mask]
    pts = points[mask]
    normals = store.normals[faces]
    r = pts - pts.mean(axis=0)
    design = np.hstack([normals, np.cross(r, normals), np.einsum("ij,ij->i", normals, r)[:, None]])
    distance = np.einsum("ij,ij->i", normals, pts) + store.offsets[faces]
    used, slot = np.unique(faces, return_inverse=True)
    return _FaceRows(design, distance, slot, used)


def snooped_faces(points: np.ndarray, assignment, store, sigma_dtp: float, sigma_face: float,
                  alpha: float = AdjustmentOptions.face_test_alpha,
                  candidates: np.ndarray | None = None) -> dict[int, float]:
    """{face: z} of the faces the other faces contradict, dropped one at a time, worst first.

    The block's 7 parameters are fitted (linearised, each face weighing as one observation
    of its offset: its points at sigma^2 = sigma_dtp^2 + n sigma_face^2) to all faces but one;
    z = that face's points' mean distance after the fit over the sigma of its offset
    (sqrt(sigma_face^2 + sigma_dtp^2 / n)) and of the prediction; `alpha`: two-sided level
    per face and round (`AdjustmentOptions.face_test_alpha`). A face that held the block
    where it wanted shows its offset only when left out; a face the others cannot check
    (the only one fixing a direction) has a large prediction sigma and is kept. `points`:
    the tie points in the order of `assignment.point_ids`; `candidates`: (store faces,) bool,
    the faces the test may drop (None: all); the others only help place the block.
    """
    from scipy.stats import norm

    if not np.any(assignment.assigned):
        return {}
    rows = _face_rows(points, assignment, store)
    counts = np.bincount(rows.slot, minlength=len(rows.faces))
    weights = 1.0 / (sigma_dtp ** 2 + counts[rows.slot] * sigma_face ** 2)
    weighted = rows.design * weights[:, None]
    per_face_n = np.zeros((len(rows.faces), 7, 7))
    per_face_b = np.zeros((len(rows.faces), 7))
    np.add.at(per_face_n, rows.slot, weighted[:, :, None] * rows.design[:, None, :])
    np.add.at(per_face_b, rows.slot, -weighted * rows.distance[:, None])
    mean_row = np.zeros((len(rows.faces), 7))
    np.add.at(mean_row, rows.slot, rows.design)
    mean_row /= counts[:, None]
    mean_distance = np.bincount(rows.slot, weights=rows.distance) / counts
    own = sigma_face ** 2 + sigma_dtp ** 2 / counts
    critical = norm.isf(alpha / 2)
    dropped: dict[int, float] = {}
    active = np.ones(len(rows.faces), bool)
    testable = (np.ones(len(rows.faces), bool) if candidates is None
                else np.asarray(candidates, bool)[rows.faces])
    while np.count_nonzero(active) > 1:
        z = np.zeros(len(rows.faces))
        total_n, total_b = per_face_n[active].sum(0), per_face_b[active].sum(0)
        for k in np.flatnonzero(active & testable):
            normal = total_n - per_face_n[k]
            # The block's datum without face k. A direction the other faces leave free gets
            # only this tiny ridge: its variance, and so the prediction's sigma, is huge.
            normal = normal + np.eye(7) * 1e-6 * max(np.trace(normal), 1.0)
            inverse = np.linalg.inv(normal)
            shift = inverse @ (total_b - per_face_b[k])
            predicted = mean_distance[k] + mean_row[k] @ shift
            z[k] = abs(predicted) / np.sqrt(own[k] + mean_row[k] @ inverse @ mean_row[k])
        worst = int(np.argmax(z))
        if z[worst] <= critical:
            break
        dropped[int(rows.faces[worst])] = float(z[worst])
        active[worst] = False
    return dropped


def vertex_tilt_covariance(store, face: int, sigma: float
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`face`'s vertices' centroid, its two in-plane axes (2, 3) and the covariance (2, 2,
    rad^2) of its plane's tilt about them when each vertex is off by `sigma` (m) along the
    normal, independently: sigma^2 (sum_j w_j w_j^T)^-1, w_j a vertex's in-plane offset from the
    centroid."""
    axes = store.rotations[int(face)][:, :2].T
    vertices = store.vertices[store.face_vertex_ids(int(face))]
    centroid = vertices.mean(0)
    w = (vertices - centroid) @ axes.T
    return centroid, axes, sigma ** 2 * np.linalg.pinv(w.T @ w)


def tilt_axes(store, face: int, sigma: float) -> np.ndarray:
    """(2, 3) the principal tilt axes of `face` (in-plane) scaled by the sigma (rad) of its tilt
    about them. Each vertex off by `sigma` (m) along the normal, independently, tilts the plane
    fitted to them about their centroid with covariance sigma^2 (sum_j w_j w_j^T)^-1 (w_j: a
    vertex's in-plane offset from the centroid); a narrow face's vertices are its neighbours'
    too, so no axis tilts by more than sigma / R (R: the farthest vertex from the centroid). A
    point at lever r moves by z_k a_k . r along the normal for z_k sigmas of tilt k."""
    centroid, axes, covariance = vertex_tilt_covariance(store, face, sigma)
    values, vectors = np.linalg.eigh(covariance)
    lever = store.vertices[store.face_vertex_ids(int(face))] - centroid
    radius = max(float(np.max(np.linalg.norm(lever @ axes.T, axis=1))), 1e-9)
    sigmas = np.minimum(np.sqrt(np.maximum(values, 0.0)), sigma / radius)
    return (vectors * sigmas).T @ axes


def tilt_variances(store, point_faces: np.ndarray, points: np.ndarray, sigma: float
                   ) -> np.ndarray:
    """(N,) per point, the variance (m^2) along its face's normal of the face's tilt error
    (`tilt_axes`, each vertex off by `sigma`). `point_faces`: the face of each point;
    `points`: (N, 3) in the store's frame."""
    out = np.zeros(len(points))
    if not len(points):
        return out
    order = np.argsort(point_faces, kind="stable")
    faces, starts = np.unique(point_faces[order], return_index=True)
    for face, rows in zip(faces, np.split(order, starts[1:])):
        centroid = store.vertices[store.face_vertex_ids(int(face))].mean(0)
        out[rows] = np.sum(((points[rows] - centroid) @ tilt_axes(store, face, sigma).T) ** 2,
                           axis=1)
    return out
