"""Which of the 7 datum parameters (E, N, U shifts, scale, rotations about E, N, U) the
assigned planes fix, which GNSS fixes, and the a posteriori sigma of each.

A plane's tie points share its generalisation error (Unger 6.3: systematic, about 0.2 m), so a
plane adds at most about one observation of that size in its normal direction, however many
points it holds. The error is not only an offset: a face whose vertices are each off by g is
also tilted, by about g over its extent (`face_tilts`). Its points share that tilt too, so a
long facade fixes the block's rotations as well as its azimuth is known, not to the
hundredths of a degree its thousands of points alone would claim. The information of plane p
is J^T (s^2 I + A A^T)^-1 J with A = [g 1, tilt columns] (Woodbury)."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import pycolmap

from ..assign.assignment import Assignment
from ..block.priors import GNSSPriors
from ..citymodel.ground_faces import terrain_faces, terrain_groups, terrain_units
from ..citymodel.store import PlaneStore
from ..errormodel.gnss import datum_jacobian
from ..options import RefineOptions
from .faces import offsets_sigma, vertex_tilt_covariance
from .marks import active_marks, datum_observations
from .problem import tie_sigmas

logger = logging.getLogger(__name__)

#: The datum parameters, in the order of the information matrices below.
DATUM = ("E", "N", "U", "scale", "rotation_E", "rotation_N", "rotation_U")


#: A datum direction counts as fixed by a source whose sigma alone is below this many times
#: the other's (else "both").
DOMINANCE = 3.0


#: Without either source, a sigma above these counts as "none": metres for shifts, relative
#: scale, radians.
UNDETERMINED = {"shift": 10.0, "scale": 0.1, "rotation": 0.1}


@dataclass
class FaceTilt:
    """The tilt error of one face: about its vertices' centroid, along its two in-plane axes
    (rows of `axes`), with covariance `covariance` (rad^2)."""

    centroid: np.ndarray  # (3,)
    axes: np.ndarray  # (2, 3)
    covariance: np.ndarray  # (2, 2)

    def distances(self, points: np.ndarray) -> np.ndarray:
        """(N, 2): how far each point moves along the normal per unit of each principal tilt
        (the square root of `covariance`): its in-plane lever from the centroid times that
        tilt's sigma."""
        values, vectors = np.linalg.eigh(self.covariance)
        return (points - self.centroid) @ self.axes.T @ (
            vectors * np.sqrt(np.maximum(values, 0.0)))


def face_tilts(store: PlaneStore, faces, sigma_generalisation: float) -> dict[int, FaceTilt]:
    """Per face of `faces`, the tilt its plane has when each of its vertices is off by
    `sigma_generalisation` along the normal, independently: the covariance of the tilts of a
    plane fitted to the vertices, g^2 (sum_i w_i w_i^T)^-1, w_i a vertex's in-plane offset from
    their centroid. About g / L for a face of length L: 0.1 deg along a 100 m facade row,
    1.1 deg on a 10 m cross wall."""
    return {int(face): FaceTilt(*vertex_tilt_covariance(store, face, sigma_generalisation))
            for face in np.unique(np.asarray(faces, np.int64))}


def common_shift_eliminated(info: np.ndarray, sigma: float) -> np.ndarray:
    """The planes' 7x7 datum information when all faces share a shift of the model with
    `sigma` (m) per axis: that shift moves every face as the block's own shift does, so it is
    eliminated with its prior (Woodbury), and no number of faces fixes the block's position
    better than `sigma`."""
    if not sigma > 0:
        return info
    cross = info[:, :3]
    return info - cross @ np.linalg.solve(info[:3, :3] + np.eye(3) / sigma ** 2, cross.T)


def _plane_terms(points: np.ndarray, normals: np.ndarray, groups: np.ndarray,
                 centre: np.ndarray, sigma_generalisation: float,
                 tilts: dict[int, FaceTilt] | None, shared_sigmas: dict[int, float] | None):
    """Per plane (group): the datum Jacobian of its points and the columns of the error they
    share (offset and, for the groups in `tilts`, the two tilts, as distances along the
    normal at each point), and which points are the group's."""
    jac = datum_jacobian(points, normals, centre)
    for group in np.unique(groups):
        selected = groups == group
        shared = np.full((int(selected.sum()), 1), sigma_generalisation if shared_sigmas is None
                         else shared_sigmas.get(int(group), sigma_generalisation))
        tilt = None if tilts is None else tilts.get(int(group))
        if tilt is not None:
            shared = np.hstack([shared, tilt.distances(points[selected])])
        yield jac[selected], shared, selected


def plane_information(points: np.ndarray, normals: np.ndarray, groups: np.ndarray,
                      centre: np.ndarray, sigma: float, sigma_generalisation: float,
                      tilts: dict[int, FaceTilt] | None = None,
                      shared_sigmas: dict[int, float] | None = None) -> list[np.ndarray]:
    """7x7 information of the datum from the tie points of each plane (one group per plane):
    each plane's points share its offset error (sigma_generalisation) and, for the groups in
    `tilts`, its tilt error."""
    s2 = sigma ** 2
    out = []
    for j, shared, _ in _plane_terms(points, normals, groups, centre, sigma_generalisation,
                                     tilts, shared_sigmas):
        projected = j.T @ shared
        inner = s2 * np.eye(shared.shape[1]) + shared.T @ shared
        out.append((j.T @ j - projected @ np.linalg.solve(inner, projected.T)) / s2)
    return out


def per_point_covariance(points: np.ndarray, normals: np.ndarray, groups: np.ndarray,
                         centre: np.ndarray, sigma: float, sigma_generalisation: float,
                         tilts, shared_sigmas, gnss: np.ndarray, gnss_bias: np.ndarray,
                         model_bias_sigma: float, weights_sigmas: np.ndarray | None = None
                         ) -> np.ndarray:
    """7x7 covariance of the datum as refine weighs it: every tie point alike (`sigma`; or each
    with its sigma in `weights_sigmas`, (n,) m: a terrain unit's points weigh as one
    observation), GNSS by its stated sigmas (`gnss`: that information), whatever the errors
    they share. Sandwich H^-1 M H^-1: H the normal matrix of those weights, M the covariance of
    its right-hand side under the full model (each point's own noise `sigma`, each face's offset
    and tilt, `gnss_bias`: the GNSS bias's part, the model's common shift). Above the optimal
    weighting's sigmas where a few faces hold most of the points."""
    s2 = sigma ** 2
    weights = np.full(len(points), 1.0 / s2) if weights_sigmas is None else (
        1.0 / np.asarray(weights_sigmas, float) ** 2)
    hessian, middle = gnss.copy(), gnss + gnss_bias
    planes = np.zeros((7, 7))
    for j, shared, selected in _plane_terms(points, normals, groups, centre,
                                            sigma_generalisation, tilts, shared_sigmas):
        w = weights[selected][:, None]
        normal = j.T @ (w * j)
        projected = j.T @ (w * shared)
        planes += normal
        middle += s2 * (j.T @ (w * w * j)) + projected @ projected.T
    hessian += planes
    if model_bias_sigma > 0:
        middle += model_bias_sigma ** 2 * planes[:, :3] @ planes[:3, :]
    inverse = _inverse(hessian)
    return inverse @ middle @ inverse


def gnss_information(positions: np.ndarray, sigmas: np.ndarray, centre: np.ndarray,
                     free_axes=None, bias_sigmas=None) -> np.ndarray:
    """7x7 information of the datum from GNSS. Along `free_axes` (bool (3,)) a constant offset
    of all positions is an unknown too (GNSSPriors.offset_axes): it is eliminated, so GNSS
    keeps only the differences between its positions there (tilts, scale), not their level.
    `bias_sigmas` ((3,) m): a bias common to all positions with this sigma per axis, which does
    not average out over them (the positions' covariance sigma_i^2 I + b^2 1 1^T)."""
    info = np.zeros((7, 7))
    free = np.zeros(3, bool) if free_axes is None else np.asarray(free_axes, bool)
    bias = np.zeros(3) if bias_sigmas is None else np.asarray(bias_sigmas, float)
    for axis in range(3):
        directions = np.zeros_like(positions)
        directions[:, axis] = 1.0
        jac = datum_jacobian(positions, directions, centre) / sigmas[:, axis:axis + 1]
        info += jac.T @ jac
        a = 1.0 / sigmas[:, axis]  # the common offset's column (whitened, sign irrelevant)
        g = jac.T @ a
        if free[axis]:
            info -= np.outer(g, g) / float(a @ a)
            info[axis, :] = info[:, axis] = 0.0  # exactly: no information on that level
        elif bias[axis] > 0:  # the bias eliminated with its prior (Woodbury)
            info -= np.outer(g, g) / float(a @ a + 1.0 / bias[axis] ** 2)
    return info


def gnss_bias_part(positions: np.ndarray, sigmas: np.ndarray, centre: np.ndarray,
                   free_axes=None, bias_sigmas=None) -> np.ndarray:
    """7x7: what a bias common to all positions (`bias_sigmas` per axis) adds to the covariance
    of GNSS's right-hand side J^T W e when GNSS is weighed by its stated sigmas alone; nothing
    along `free_axes`, where an offset is estimated."""
    out = np.zeros((7, 7))
    if bias_sigmas is None:
        return out
    free = np.zeros(3, bool) if free_axes is None else np.asarray(free_axes, bool)
    for axis in range(3):
        if free[axis] or not bias_sigmas[axis] > 0:
            continue
        directions = np.zeros_like(positions)
        directions[:, axis] = 1.0
        jac = datum_jacobian(positions, directions, centre) / sigmas[:, axis:axis + 1]
        g = jac.T @ (1.0 / sigmas[:, axis])
        out += bias_sigmas[axis] ** 2 * np.outer(g, g)
    return out


#: Prior sigmas (shifts in metres, log scale, rotations in radians) that keep a singular
#: information matrix invertible, far above every UNDETERMINED limit.
REGULARISATION = np.array([1e6, 1e6, 1e6, 1e3, 1e3, 1e3, 1e3])


def _inverse(info: np.ndarray) -> np.ndarray:
    """The inverse of a datum information with REGULARISATION as priors, in units scaled by
    its diagonal (see `_sigmas`)."""
    prior = 1.0 / REGULARISATION ** 2
    regularised = info + np.diag(prior)
    scale = np.sqrt(np.diag(regularised))
    normalised = regularised / np.outer(scale, scale)
    values, vectors = np.linalg.eigh(0.5 * (normalised + normalised.T))
    return (vectors / np.maximum(values, 1e-300)) @ vectors.T / np.outer(scale, scale)


def image_sigmas(covariance: np.ndarray, determined: np.ndarray, positions: np.ndarray | None,
                 centre: np.ndarray) -> np.ndarray:
    """(3,) sigma (m) per axis E N U of the image centres at `positions` as the datum's
    `covariance` (7x7, about `centre`) moves them, shift, scale and rotations together: the
    root of the mean variance over the images. Only the `determined` parameters count (one
    left free says so through its own sigma); a free shift gives inf on its axis. Without
    positions: the shift's sigma at `centre`."""
    cov = np.where(np.outer(determined, determined), covariance, 0.0)
    offsets = (np.zeros((1, 3)) if positions is None or not len(positions)
               else np.asarray(positions, float) - centre)
    variance = np.zeros(3)
    for axis in range(3):
        directions = np.zeros_like(offsets)
        directions[:, axis] = 1.0
        jac = datum_jacobian(offsets, directions, np.zeros(3))
        variance[axis] = np.mean(np.einsum("ij,jk,ik->i", jac, cov, jac))
    out = np.sqrt(np.maximum(variance, 0.0))
    out[~determined[:3]] = np.inf
    return out


def _sigmas(info: np.ndarray) -> np.ndarray:
    """Marginal sigma per datum parameter; inf where the information leaves it free. The
    inverse is taken with REGULARISATION as priors: a direction with hardly any information
    (vertical walls and the height) keeps its large sigma without dragging the others it barely
    touches into the null space (in units scaled by the diagonal, the height's null vector
    looked half made of E and N)."""
    sigma = np.sqrt(np.maximum(np.diag(_inverse(info)), 0.0))
    # Within a factor of two of the regularisation: the information said (almost) nothing.
    sigma[sigma > 0.5 * REGULARISATION] = np.inf
    return sigma


def _no_sharper(covariance: np.ndarray, s_both: np.ndarray, images_both: np.ndarray,
                positions: np.ndarray | None, centre: np.ndarray):
    """The datum's sigmas and its images' (`image_sigmas`) from refine's weighting
    (`covariance`), never below the optimal weighting's (`s_both`, `images_both`)."""
    determined = np.isfinite(s_both)
    stated = np.maximum(s_both, np.sqrt(np.maximum(np.diag(covariance), 0.0)))
    stated[~determined] = np.inf
    images = np.maximum(images_both, image_sigmas(covariance, determined, positions, centre))
    return stated, images


def _leave_one_out(total: np.ndarray, per_plane: list[np.ndarray]) -> np.ndarray:
    """(7,) the datum's sigmas from the planes with the most important one left out. A
    direction that only one plane fixes rests on that plane's assignment being right (one roof
    among facades): it counts for the planes only if it survives leaving any one out (judged
    with the other parameters held, so that two parallel facades, which together also fix the
    scale, still count for their normal direction)."""
    if len(per_plane) < 2:
        return np.full(7, np.inf)
    diagonals = np.array([np.diag(total - info) for info in per_plane]).reshape(-1, 7)
    return 1.0 / np.sqrt(np.maximum(diagonals.min(axis=0), 1e-30))


def _source(s_planes: float, s_gnss: float, s_robust: float, limit: float) -> tuple[str, bool]:
    """What fixes one datum parameter from the sigmas of planes, GNSS and the planes' leave-one-
    out (`limit`: beyond it, nothing): planes, gnss, both or none; and whether the planes do,
    robustly."""
    g_ok = s_gnss < limit
    p_ok = s_planes < limit and s_robust < (s_gnss if g_ok else limit)
    if p_ok and (not g_ok or s_planes * DOMINANCE < s_gnss):
        return "planes", p_ok
    if g_ok and (not p_ok or s_gnss * DOMINANCE < s_planes):
        return "gnss", p_ok
    return ("both" if p_ok and g_ok else "none"), p_ok


def observability(points: np.ndarray, normals: np.ndarray, groups: np.ndarray,
                  gnss_positions: np.ndarray | None, gnss_sigmas: np.ndarray | None,
                  sigma_dtp: float, sigma_generalisation: float, gnss_free_axes=None,
                  tilts: dict[int, FaceTilt] | None = None, gnss_bias_sigmas=None,
                  terrain: dict[int, tuple[int, float]] | None = None,
                  model_bias_sigma: float = 0.0, per_point: bool = False,
                  weights_sigmas: np.ndarray | None = None,
                  image_positions: np.ndarray | None = None,
                  marks: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """Per datum parameter: the source that fixes it (planes, gnss, both, none) and its sigma
    (metres; relative for scale; degrees for rotations) from planes, GNSS and both. The stated
    shifts' `sigma` and `sigma_gnss_with_bias` are those of the images' centres (at
    `image_positions`, default the GNSS positions; `image_sigmas`): a short block's uncertain
    rotation moves its far images.
    `gnss_free_axes`: the shifts along which a GNSS offset is estimated (GNSS fixes none);
    `tilts`: the tilt errors of the planes (`face_tilts`, by group), else offsets only;
    `gnss_bias_sigmas` ((3,) m): the part of the GNSS error common to the block. `sigma` (what
    a user can rely on) includes it; `sigma_gnss` is the GNSS positions' mean without it (how
    far refined and GNSS-only blocks, which share the bias, may differ), and the sources are
    decided on it; `sigma_gnss_with_bias` is GNSS alone with it. `model_bias_sigma` (m): a
    shift all faces share (`common_shift_eliminated`), in `sigma` and `sigma_planes`.
    `per_point`: `sigma` is that of refine's weighting, every tie point alike
    (`per_point_covariance`; `weights_sigmas`: each point's sigma in that weighting), not that of
    the optimal one, where the planes fix the direction. `marks`: ground control marks
    (positions, (N, 3) sigmas; adjust.marks.datum_observations) in every sigma but the planes'
    and GNSS's own; each row then has `sigma_gcp` and `shares` (each source's share of the
    information), and "gcp" as its source where the marks fix what would be free or GNSS's
    alone (`_with_marks`)."""
    # Shifts and their sigmas refer to the cameras' centroid (where GNSS observes), else to
    # the tie points': the position users care about, and rotations then do not leak into it
    # (without either, the control marks').
    centre = (gnss_positions.mean(0) if gnss_positions is not None and len(gnss_positions)
              else points.mean(0) if len(points) or marks is None else marks[0].mean(0))
    # Terrain faces (citymodel.ground_faces): one group per terrain unit, with its sigma.
    shared_sigmas, terrain_keys = None, set()
    if terrain:
        groups, shared_sigmas, terrain_keys = terrain_groups(groups, terrain)
    per_plane = (plane_information(points, normals, groups, centre, sigma_dtp,
                                   sigma_generalisation, tilts, shared_sigmas)
                 if len(points) else [])
    by_terrain = terrain_shares(per_plane, np.unique(groups), terrain_keys)
    total = sum(per_plane, np.zeros((7, 7)))
    planes = common_shift_eliminated(total, model_bias_sigma)
    has_gnss = gnss_positions is not None and len(gnss_positions)
    gnss = (gnss_information(gnss_positions, gnss_sigmas, centre, gnss_free_axes)
            if has_gnss else np.zeros((7, 7)))
    biased = (gnss_information(gnss_positions, gnss_sigmas, centre, gnss_free_axes,
                               gnss_bias_sigmas) if has_gnss else np.zeros((7, 7)))
    # The marks' information (a position observation each, like GNSS) in every combined sigma.
    from_marks = (gnss_information(marks[0], marks[1], centre) if marks is not None
                  else np.zeros((7, 7)))
    # Our order is (shift, log scale, rotation); DATUM's is the same.
    s_planes, s_gnss = _sigmas(planes), _sigmas(gnss)
    s_biased, s_both = _sigmas(biased), _sigmas(planes + biased + from_marks)
    at = image_positions if image_positions is not None else (
        gnss_positions if has_gnss else None)
    images_both = image_sigmas(_inverse(planes + biased + from_marks), np.isfinite(s_both), at,
                               centre)
    images_biased = image_sigmas(_inverse(biased), np.isfinite(s_biased), at, centre)
    s_stated, images_stated = s_both, images_both
    if per_point and len(points):
        bias_part = (gnss_bias_part(gnss_positions, gnss_sigmas, centre, gnss_free_axes,
                                    gnss_bias_sigmas) if has_gnss else np.zeros((7, 7)))
        covariance = per_point_covariance(
            points, normals, groups, centre, sigma_dtp, sigma_generalisation, tilts,
            shared_sigmas, gnss + from_marks, bias_part, model_bias_sigma, weights_sigmas)
        s_stated, images_stated = _no_sharper(covariance, s_both, images_both, at, centre)
    out = _rows(s_planes, s_gnss, _leave_one_out(total, per_plane), by_terrain,
                stated=(np.r_[images_stated, s_stated[3:]], np.r_[images_both, s_both[3:]]),
                with_bias=np.r_[images_biased, s_biased[3:]])
    if marks is not None:
        _with_marks(out, _sigmas(from_marks), s_planes, s_gnss)
    return out


def _rows(s_planes: np.ndarray, s_gnss: np.ndarray, s_robust: np.ndarray, by_terrain: list,
          stated: tuple[np.ndarray, np.ndarray], with_bias: np.ndarray) -> dict:
    """`observability`'s row per datum parameter from the sigmas of the planes, GNSS, the
    planes' leave-one-out, what refine's weighting and the optimal one state (`stated`; the
    shifts' as they move the images) and GNSS with its bias."""
    refine_weighting, optimal = stated
    out = {}
    for k, name in enumerate(DATUM):
        kind = "shift" if k < 3 else "scale" if k == 3 else "rotation"
        limit = UNDETERMINED[kind]
        source, p_ok = _source(s_planes[k], s_gnss[k], s_robust[k], limit)
        factor = np.degrees(1.0) if kind == "rotation" else 1.0
        # Refine's weighting where the planes hold the direction; where GNSS alone does, the
        # loop holds it to GNSS (workflow.hold_gnss_height, scale priors), as weighed optimally.
        sigma = refine_weighting[k] if source in ("planes", "both") else optimal[k]
        # What a user can rely on: planes (a single one too, with its generalisation error)
        # and GNSS with its bias; whether that one plane is the right one the verdict's tests
        # judge (precision.quality), not this sigma.
        out[name] = {"source": source, **by_terrain[k],
                     "one_plane": bool(s_planes[k] < limit and not p_ok),
                     "sigma": _finite(sigma * factor),
                     "sigma_planes": _finite(s_planes[k] * factor),
                     "sigma_gnss": _finite(s_gnss[k] * factor),
                     "sigma_gnss_with_bias": _finite(with_bias[k] * factor)}
    return out


def _with_marks(out: dict, s_gcp: np.ndarray, s_planes: np.ndarray, s_gnss: np.ndarray) -> None:
    """The rows of `out` with the ground control marks: `sigma_gcp`, each source's share of
    the information (1/sigma^2 over their sum), and the source "gcp" where the marks fix a
    parameter nothing else does, or one GNSS fixes alone while the marks know it at least a
    DOMINANCE-th as well (GNSS is then not alone). Planes keep their source: the verdict's
    tests of the model read it."""
    for k, name in enumerate(DATUM):
        row = out[name]
        kind = "shift" if k < 3 else "scale" if k == 3 else "rotation"
        factor = np.degrees(1.0) if kind == "rotation" else 1.0
        sigmas = {"planes": s_planes[k], "gnss": s_gnss[k], "gcp": s_gcp[k]}
        information = {s: 1.0 / v ** 2 for s, v in sigmas.items() if np.isfinite(v)}
        total = sum(information.values())
        row["sigma_gcp"] = _finite(s_gcp[k] * factor)
        row["shares"] = {s: float(v / total) for s, v in information.items()} if total else {}
        if not s_gcp[k] < UNDETERMINED[kind]:
            continue
        if row["source"] == "none" or (row["source"] == "gnss"
                                       and s_gcp[k] < DOMINANCE * s_gnss[k]):
            row["source"] = "gcp"
            row["one_plane"] = False


def gnss_only_observability(observability_dict: dict) -> dict:
    """The rows of `observability` for the GNSS-only block (handed back when the verdict
    fails): every shift fixed by GNSS, its sigma GNSS's with the bias common to the block."""
    out = {}
    for name, row in observability_dict.items():
        sigma = row.get("sigma_gnss_with_bias")
        out[name] = {**row, "source": "gnss" if sigma is not None else "none",
                     "one_plane": False, "sigma": sigma}
    return out


def _widened(row: dict, sigma: float) -> dict:
    """A shift's `row` stating `sigma` (m, at least its own), at most GNSS's sigma with its
    bias (the block's position without the planes; source "gnss" and `widened_to_gnss` then:
    the block goes back to GNSS's position there, left_to_gnss); inf without GNSS: no sigma,
    source "none"."""
    with_bias = row.get("sigma_gnss_with_bias")
    if with_bias is not None and sigma > max(row["sigma"], with_bias):
        return {**row, "source": "gnss", "one_plane": False, "widened_to_gnss": True,
                "sigma": max(row["sigma"], with_bias)}
    if not np.isfinite(sigma):
        return {**row, "source": "none", "sigma": None}
    return {**row, "sigma": float(sigma)}


def unsettled_observability(observability_dict: dict, remaining) -> dict:
    """The rows of `observability` for a block whose assignment loop ran out of iterations
    while still moving it: `remaining` (m, E N U; adjust.record.remaining_move) is how far it
    would still have moved the block. That move is an error of the block the planes' sigma
    does not hold, so each shift's sigma becomes sqrt(sigma^2 + remaining^2), at most GNSS's
    sigma with its bias (the block's position without the planes; source "gnss" then). The
    rows keep the remaining move and the planes' sigma (`remaining_move_m`, `sigma_settled`);
    without GNSS a creep that does not slow leaves the shift without a sigma."""
    def widen(row: dict, sigma: float, rest: float) -> dict | None:
        if not rest > 0.0:
            return None
        return {**_widened(row, float(np.hypot(sigma, rest))), "remaining_move_m": rest,
                "sigma_settled": sigma}

    return _shift_rows(observability_dict, remaining, widen)


def weighting_observability(observability_dict: dict, move) -> dict:
    """The rows of `observability` for a block the faces' errors as unknowns moved by `move`
    (m, E N U; adjust.loop.LoopResult.weighting_move) from where every tie point alike had
    placed it. Both weightings estimate the same block under one error model, which expects
    them within about the stated sigma of each other; a move beyond it along an axis shows
    errors the model does not describe there (details standing out of the faces to one side),
    and how the faces are weighted then moves the block by that much: the stated sigma is at
    least the move, at most GNSS's sigma with its bias (source "gnss" then). The rows keep the
    move and the sigma before it (`weighting_move_m`, `sigma_one_weighting`)."""
    def widen(row: dict, sigma: float, step: float) -> dict | None:
        if not step > sigma:
            return None
        return {**_widened(row, step), "weighting_move_m": step, "sigma_one_weighting": sigma}

    return _shift_rows(observability_dict, None if move is None else np.abs(move), widen)


def _shift_rows(observability_dict: dict, values, widen) -> dict:
    """`observability` with each shift's row (E, N, U) that states a sigma replaced by
    `widen(row, sigma, value)` where that gives one; unchanged without `values`."""
    if values is None:
        return observability_dict
    out = dict(observability_dict)
    for k, name in enumerate(("E", "N", "U")):
        row = observability_dict.get(name)
        if row and row.get("sigma") is not None:
            widened = widen(row, row["sigma"], float(values[k]))
            out[name] = widened if widened is not None else row
    return out


def terrain_shares(per_plane: list[np.ndarray], keys: np.ndarray, terrain_keys: set
                   ) -> list[dict]:
    """Per datum parameter: {} without terrain, else `terrain` (True where the buildings'
    planes alone know it DOMINANCE times worse than with the terrain: the ground fixes it)
    and `sigma_terrain` (the terrain's units alone)."""
    if not terrain_keys or not per_plane:
        return [{} for _ in DATUM]
    is_terrain = np.isin(keys, list(terrain_keys))
    ground = sum((p for p, t in zip(per_plane, is_terrain) if t), np.zeros((7, 7)))
    buildings = sum((p for p, t in zip(per_plane, is_terrain) if not t), np.zeros((7, 7)))
    s_all, s_ground, s_buildings = _sigmas(ground + buildings), _sigmas(ground), \
        _sigmas(buildings)
    return [{"terrain": bool(np.isfinite(s_all[k]) and s_buildings[k] > DOMINANCE * s_all[k]),
             "sigma_terrain": _finite(s_ground[k] * (np.degrees(1.0) if k > 3 else 1.0))}
            for k in range(len(DATUM))]


def _finite(value: float) -> float | None:
    return float(value) if np.isfinite(value) else None


def rests_on_one_plane(observability_dict: dict) -> list[str]:
    """The datum parameters that only a single plane fixes."""
    return [k for k, v in observability_dict.items() if v.get("one_plane")]


def left_to_gnss(observability_dict: dict, names=("E", "N", "U")) -> np.ndarray:
    """(len(names),) bool, default E N U: the datum parameters (DATUM's names) that GNSS fixes
    while the planes' information there (each plane with its generalisation error) is
    DOMINANCE times weaker or none. Per tie point, as the adjustment weighs them, the same
    planes can seem to fix it: walls tilted by a fraction of a degree, thousands of points
    each. Also a shift whose stated sigma, widened by an error the faces' model does not
    describe (how far their weighting or an unsettled loop moves the block), reached GNSS's
    sigma with its bias (`widened_to_gnss`): GNSS alone states that position no worse, and
    the model's move there is not evidence, so GNSS's position is the one stated."""
    out = np.zeros(len(names), bool)
    for k, name in enumerate(names):
        row = observability_dict.get(name, {})
        planes, gnss = row.get("sigma_planes"), row.get("sigma_gnss")
        out[k] = (row.get("source") == "gnss" and gnss is not None
                  and (planes is None or planes > DOMINANCE * gnss
                       or bool(row.get("widened_to_gnss"))))
    return out


def planes_fix(observability_dict: dict) -> list[str]:
    """The datum parameters the planes fix alone or together with GNSS."""
    return [k for k, v in observability_dict.items() if v["source"] in ("planes", "both")]


def datum_line(observability_dict: dict) -> str:
    """'E planes (0.09 m), ..., U gnss (0.79 m), ...' for the log and the console."""
    parts = []
    for name, row in observability_dict.items():
        unit = " deg" if name.startswith("rotation") else "" if name == "scale" else " m"
        sigma = f" ({row['sigma']:.3g}{unit})" if row["sigma"] is not None else ""
        source = f"{row['source']} (terrain)" if row.get("terrain") else row["source"]
        parts.append(f"{name} {source}{sigma}")
    return ", ".join(parts)


def assigned_observability(points: np.ndarray, assignment: Assignment, store: PlaneStore,
                           priors: GNSSPriors | None, rec: pycolmap.Reconstruction,
                           options: RefineOptions, *, from_data: bool = False) -> dict:
    """quality.observability for the assigned tie points and the GNSS of `rec`. `from_data`:
    the faces' generalisation sigma is the one their offsets give (`face_fit`, outlier faces
    left out), else the a priori one."""
    from ..options import GENERALISATION_SIGMA

    assigned = assignment.assigned
    faces = assignment.face_index[assigned]
    sigma_gen = options.adjustment.sigma_generalisation or GENERALISATION_SIGMA
    selected = np.ones(len(faces), bool)
    if from_data:
        fit = face_fit(points[assigned], faces, store, sigma_gen)
        sigma_gen = fit.sigma_generalisation
        selected = ~np.isin(faces, fit.outlier_faces)
    faces = faces[selected]
    unique = np.unique(faces)
    # As the adjustment weighs them: a terrain unit as one observation of its offset.
    weights_sigmas = tie_sigmas(options.adjustment, store, unique, faces,
                                assignment)[np.searchsorted(unique, faces)]
    gnss_sigmas = None
    if priors is not None:
        gnss_sigmas = np.asarray(priors.sigmas, float)
        if from_data:  # GNSS no better than stated, and no better than the block lets it fit
            gnss_sigmas = gnss_sigmas * gnss_variance_factor(
                priors.observed_points(rec), priors.observed, gnss_sigmas)
    return observability(points[assigned][selected], store.normals[faces], faces,
                         priors.observed_points(rec) if priors is not None else None,
                         gnss_sigmas,
                         options.adjustment.sigma_dtp, sigma_gen,
                         priors.free_offset_axes if priors is not None else None,
                         face_tilts(store, faces, sigma_gen),
                         gnss_bias_sigmas(priors, options.adjustment.gnss_bias_share),
                         terrain=terrain_faces(store, faces),
                         model_bias_sigma=options.adjustment.sigma_model_datum if from_data
                         else 0.0,
                         per_point=from_data
                         and options.adjustment.face_weighting == "per_point",
                         weights_sigmas=weights_sigmas,
                         image_positions=None if priors is not None else np.array(
                             [image.projection_center() for image in rec.images.values()
                              if image.has_pose]).reshape(-1, 3),
                         marks=datum_observations(active_marks(), rec))


# -- the faces' fit: generalisation sigma from the data ----------------------------------------

#: A face whose mean offset exceeds this many of its expected spread is an outlier face (an
#: arcade, an inner wall, a set-back storey the model lacks): left out of the estimate and of
#: the datum's information, and reported. 3: a face of the model's own error gets there about
#: once in 370.
OUTLIER_FACE_SIGMAS = 3.0


@dataclass
class FaceFit:
    """How the assigned tie points sit on their faces: per face its number of points and their
    mean signed distance (m, the face's offset), the points' scatter about that mean
    (`sigma_point`, m, median-based) and the faces' offset sigma by moments
    (`sigma_generalisation`, m, adjust.faces.offsets_sigma; the a priori one with too few faces,
    `estimated` False). `outlier_faces`: faces beyond OUTLIER_FACE_SIGMAS. Terrain faces
    (`terrain`) carry their unit's sigma, not the model's generalisation: they are left out of
    both."""

    faces: np.ndarray
    counts: np.ndarray
    offsets: np.ndarray
    sigma_point: float
    sigma_generalisation: float
    estimated: bool
    outlier_faces: np.ndarray
    terrain: np.ndarray | None = None  # bool per face: a terrain face, with its own sigma

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    def todict(self) -> dict:
        return {"num_faces": self.num_faces, "sigma_point_m": self.sigma_point,
                "sigma_generalisation_m": self.sigma_generalisation,
                "estimated": self.estimated,
                "outlier_faces": [int(f) for f in self.outlier_faces]}


def face_fit(points: np.ndarray, faces: np.ndarray, store: PlaneStore,
             prior_sigma: float) -> FaceFit:
    """`FaceFit` of tie points `points` on `faces` (store face indices); `prior_sigma` (m):
    the generalisation sigma where too few faces give their own."""
    faces = np.asarray(faces, np.int64)
    distances = (np.einsum("ij,ij->i", points, store.normals[faces]) + store.offsets[faces]
                 if len(faces) else np.zeros(0))
    unique, slots, counts = np.unique(faces, return_inverse=True, return_counts=True)
    offsets = np.bincount(slots, weights=distances, minlength=len(unique)) / np.maximum(counts, 1)
    spread = distances - offsets[slots]
    sigma_point = float(1.4826 * np.median(np.abs(spread))) if len(spread) else 0.0
    sigma_point = max(sigma_point, 1e-3)
    noise = sigma_point ** 2 / np.maximum(counts, 1)
    terrain = terrain_units(store)[0][unique] >= 0 if len(unique) else np.zeros(0, bool)
    keep = ~terrain
    sigma, estimated = prior_sigma, False
    for _ in range(5):  # outlier faces out, the sigma again, until none leaves
        found = offsets_sigma(offsets[keep], noise[keep])
        if found is None:
            break
        sigma, estimated = found, True
        beyond = np.abs(offsets) > OUTLIER_FACE_SIGMAS * np.sqrt(sigma ** 2 + noise)
        if np.array_equal(~beyond & ~terrain, keep):
            break
        keep = ~beyond & ~terrain
    outliers = unique[~keep & ~terrain] if estimated else np.zeros(0, np.int64)
    return FaceFit(unique, counts, offsets, sigma_point, sigma, estimated, outliers, terrain)


def gnss_variance_factor(antennas: np.ndarray, observed: np.ndarray, sigmas: np.ndarray
                         ) -> float:
    """How many times their stated `sigmas` the block's GNSS residuals are, at least 1: the
    root of the mean squared normalised residual (where the block puts the `antennas` minus what
    GNSS `observed`, (N, 3) each, their common mean removed, 3N - 3 degrees of freedom). Above 1
    GNSS is worse than stated or the block's shape does not fit it (an image registered in the
    wrong place, a bent block): every sigma GNSS gives is that much larger."""
    if len(antennas) < 3:
        return 1.0
    v = (np.asarray(antennas, float) - observed) / np.asarray(sigmas, float)
    v -= v.mean(axis=0)
    factor = float(np.sqrt(np.sum(v ** 2) / (v.size - 3)))
    if factor > 1.0:
        logger.info("GNSS residuals are %.2f x their stated sigmas: GNSS's sigmas scaled by it",
                    factor)
    return max(1.0, factor)


def gnss_bias_sigmas(priors: GNSSPriors | None, share: float) -> np.ndarray | None:
    """(3,) sigma (m) of the GNSS error common to the block: `share` of the positions' median
    stated sigma per axis (AdjustmentOptions.gnss_bias_share); None without GNSS."""
    if priors is None or not len(priors.sigmas) or not share > 0:
        return None
    return share * np.median(np.asarray(priors.sigmas, float), axis=0)


def offset_refusal(observability_dict: dict, offset_axes) -> str | None:
    """Why the model planes cannot fix a GNSS offset along `offset_axes` (bool (3,), E N U),
    or None when they fix every one of them (source "planes" or "both")."""
    reasons = []
    for name, free in zip(("E", "N", "U"), np.asarray(offset_axes, bool)):
        row = observability_dict.get(name, {})
        if not free or row.get("source") in ("planes", "both", "gcp"):
            continue
        what = "the height" if name == "U" else f"the {name} position"
        if row.get("one_plane"):
            reasons.append(f"{what} rests on a single model plane, which nothing checks")
        elif name == "U":
            reasons.append(f"{what}: no roof or eave the block sees carries enough tie points")
        else:
            reasons.append(f"{what}: too few walls facing that way carry tie points")
    return "; ".join(reasons) or None



def offset_sigma(observability_dict: dict, priors: GNSSPriors) -> np.ndarray:
    """(3,) a posteriori sigma (m) of the GNSS offset per axis: the block's position there as
    the planes fix it (each plane with its generalisation error) and the mean of the GNSS
    positions; NaN where no offset is estimated or the planes leave the direction free."""
    out = np.full(3, np.nan)
    gnss_mean = priors.offset_mean_sigma()
    for k, name in enumerate(("E", "N", "U")):
        sigma = observability_dict.get(name, {}).get("sigma")
        if priors.offset_axes[k] and sigma is not None:
            out[k] = float(np.hypot(sigma, gnss_mean[k]))
    return out
