"""What the simulated cameras see: tie points sampled on the true scene with visibility by ray
casting and pixel noise, check points, and GNSS positions with noise and bias."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from .flight import Flight
from .scenario import STAGE_CHECK, STAGE_GNSS, STAGE_GNSS_GROSS, STAGE_OBS, STAGE_POINTS, \
    CheckPointOptions, GNSSOptions, ObservationOptions
from .scene import LABEL_GROUND, LABEL_ROOF, LABEL_WALL, TrueScene

logger = logging.getLogger(__name__)


def sample_surface_points(scene: TrueScene, density: float, rng: np.random.Generator,
                          near: np.ndarray | None = None, radius: float = np.inf,
                          labels: tuple[int, ...] | None = None):
    """Area-weighted random points on the true triangles (optionally only triangles within
    `radius` of a point in `near`, and/or with given labels). Returns points, triangle index."""
    from scipy.spatial import cKDTree

    tri = scene.triangles
    keep = np.ones(len(tri), dtype=bool)
    if labels is not None:
        keep &= np.isin(scene.labels, labels)
    if near is not None:
        # distance of the closest vertex or the centroid (triangles are small or near)
        tree = cKDTree(near)
        d = np.minimum.reduce([tree.query(tri[:, i])[0] for i in range(3)] +
                              [tree.query(tri.mean(1))[0]])
        keep &= d < radius
    idx = np.flatnonzero(keep)
    areas = scene.areas[idx]
    total = areas.sum()
    n = int(rng.poisson(density * total)) if density > 0 else 0
    if n == 0 or total <= 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=np.int64)
    which = idx[rng.choice(len(idx), size=n, p=areas / total)]
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)
    a, b, c = tri[which, 0], tri[which, 1], tri[which, 2]
    pts = (1 - s)[:, None] * a + (s * (1 - r2))[:, None] * b + (s * r2)[:, None] * c
    return pts, which


def visibility(flight: Flight, points: np.ndarray, normals: np.ndarray, raycaster,
               opt: ObservationOptions, progress: bool = True,
               max_incidence_deg: np.ndarray | None = None):
    """All (point, frame) pairs where the point projects into the image, lies within the
    distance limits, is seen at an incidence below the limit (per point when
    `max_incidence_deg` is given) and is not occluded (the first ray hit from the camera is the
    point itself, +-2 cm). Returns point index, frame index, pixel coordinates (no noise) and
    unit viewing rays."""
    import open3d as o3d
    from scipy.spatial import cKDTree
    from tqdm import tqdm

    tree = cKDTree(points)
    cos_max = (np.cos(np.radians(np.asarray(max_incidence_deg, float)))
               if max_incidence_deg is not None
               else np.full(len(points), math.cos(math.radians(opt.max_incidence_deg))))
    P, F, UV, RAY = [], [], [], []
    m = opt.image_margin
    frames = range(len(flight.names))
    for k in tqdm(frames, desc="visibility", disable=None if progress else True, leave=False):
        C = flight.centres[k]
        idx = np.asarray(tree.query_ball_point(C, opt.max_distance), dtype=np.int64)
        if len(idx) == 0:
            continue
        idx.sort()
        uv, z = flight.project(k, points[idx])
        ok = (z > opt.min_distance) & (uv[:, 0] >= m) & (uv[:, 0] < flight.width - m) & (
            uv[:, 1] >= m) & (uv[:, 1] < flight.height - m)
        idx, uv = idx[ok], uv[ok]
        ray = points[idx] - C
        dist = np.linalg.norm(ray, axis=1)
        ray /= dist[:, None]
        inc = np.abs(np.einsum("ij,ij->i", ray, normals[idx])) >= cos_max[idx]
        idx, uv, ray, dist = idx[inc], uv[inc], ray[inc], dist[inc]
        if len(idx) == 0:
            continue
        rays = np.concatenate([np.repeat(C[None], len(idx), 0), ray], axis=1).astype(np.float32)
        hit = raycaster.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
        vis = hit >= dist - 0.02
        P.append(idx[vis])
        F.append(np.full(vis.sum(), k, dtype=np.int64))
        UV.append(uv[vis])
        RAY.append(ray[vis])
    if not P:
        return (np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros((0, 3)))
    return np.concatenate(P), np.concatenate(F), np.concatenate(UV), np.concatenate(RAY)


@dataclass
class Observations:
    """Tie point tracks and the keypoints of every image."""

    track_xyz: np.ndarray  # (T,3) true local coordinates of each track's point
    obs_track: np.ndarray  # (M,) track index of each observation
    obs_frame: np.ndarray  # (M,) frame index
    obs_kp: np.ndarray  # (M,) keypoint index in its image
    obs_uv_true: np.ndarray  # (M,2)
    keypoints: list[np.ndarray]  # per image (K_i,2) float64, with noise, shuffled
    pairs: dict[tuple[int, int], np.ndarray]  # (frame_i, frame_j) -> (m,2) keypoint indices
    num_outlier_matches: int = 0
    num_candidates: int = 0
    num_visible: int = 0


def simulate_observations(flight: Flight, scene: TrueScene, raycaster,
                          opt: ObservationOptions, seed: int,
                          progress: bool = True) -> Observations:
    rng_pts = np.random.default_rng([seed, STAGE_POINTS])
    rng = np.random.default_rng([seed, STAGE_OBS])
    pts, tri = sample_surface_points(scene, opt.points_per_m2, rng_pts, near=flight.centres,
                                     radius=opt.max_distance)
    limits = np.full(len(pts), float(opt.max_incidence_deg))
    if opt.ground_points_per_m2 is not None or opt.ground_max_incidence_deg is not None:
        pts, tri, limits = _ground_features(scene, opt, flight, pts, tri, limits, rng_pts)
    normals = scene.normals[tri]
    logger.info("%d candidate feature points on the true surfaces", len(pts))
    p_idx, f_idx, uv, ray = visibility(flight, pts, normals, raycaster, opt, progress, limits)
    num_visible = len(p_idx)
    # detection losses
    det = rng.random(len(p_idx)) < opt.detection_probability
    p_idx, f_idx, uv, ray = p_idx[det], f_idx[det], uv[det], ray[det]
    order = np.lexsort((f_idx, p_idx))
    p_idx, f_idx, uv, ray = p_idx[order], f_idx[order], uv[order], ray[order]
    # tracks: break at frame gaps longer than the matching window and when the viewing
    # direction has turned by more than max_track_view_angle from the track's first view
    new_point = np.r_[True, p_idx[1:] != p_idx[:-1]]
    gap = np.r_[False, np.diff(f_idx) > opt.match_window] & ~new_point
    seg_gap = np.cumsum(new_point | gap)
    first = np.flatnonzero(np.r_[True, seg_gap[1:] != seg_gap[:-1]])
    first_of = first[np.searchsorted(first, np.arange(len(seg_gap)), side="right") - 1]
    cosang = np.clip(np.einsum("ij,ij->i", ray, ray[first_of]), -1, 1)
    seg_ang = np.floor(np.degrees(np.arccos(cosang)) / opt.max_track_view_angle_deg).astype(
        np.int64)
    brk = np.r_[True, (seg_gap[1:] != seg_gap[:-1]) | (seg_ang[1:] != seg_ang[:-1])]
    track_raw = np.cumsum(brk) - 1
    counts = np.bincount(track_raw)
    good = counts[track_raw] >= opt.min_track_length
    track_raw, p_idx, f_idx, uv = track_raw[good], p_idx[good], f_idx[good], uv[good]
    uniq, track = np.unique(track_raw, return_inverse=True)
    track_xyz = pts[p_idx[np.r_[True, track[1:] != track[:-1]]]]
    # noisy keypoints + unmatched ones, shuffled per image
    n_frames = len(flight.names)
    uv_noisy = uv + rng.normal(0.0, opt.pixel_noise, uv.shape)
    uv_noisy[:, 0] = np.clip(uv_noisy[:, 0], 0.0, flight.width - 1e-3)
    uv_noisy[:, 1] = np.clip(uv_noisy[:, 1], 0.0, flight.height - 1e-3)
    kp_index = np.zeros(len(track), dtype=np.int64)
    keypoints = []
    by_frame = np.argsort(f_idx, kind="stable")
    starts = np.searchsorted(f_idx[by_frame], np.arange(n_frames + 1))
    for k in range(n_frames):
        mine = by_frame[starts[k]:starts[k + 1]]
        n_un = int(round(opt.unmatched_ratio * len(mine)))
        extra = np.c_[rng.uniform(0, flight.width, n_un), rng.uniform(0, flight.height, n_un)]
        allkp = np.concatenate([uv_noisy[mine], extra])
        perm = rng.permutation(len(allkp))
        inv = np.empty_like(perm)
        inv[perm] = np.arange(len(perm))
        kp_index[mine] = inv[: len(mine)]
        keypoints.append(allkp[perm])
    # matches: every pair of observations of one track within the matching window
    order = np.lexsort((f_idx, track))
    t_s, f_s, k_s = track[order], f_idx[order], kp_index[order]
    I, J, KI, KJ = [], [], [], []
    for off in range(1, opt.match_window + 1):
        a = np.arange(len(t_s) - off)
        b = a + off
        ok = (t_s[a] == t_s[b]) & (f_s[b] - f_s[a] <= opt.match_window)
        if not ok.any():
            break
        I.append(f_s[a[ok]]), J.append(f_s[b[ok]]), KI.append(k_s[a[ok]]), KJ.append(
            k_s[b[ok]])
    I, J = np.concatenate(I), np.concatenate(J)
    KI, KJ = np.concatenate(KI), np.concatenate(KJ)
    order = np.lexsort((J, I))
    I, J, KI, KJ = I[order], J[order], KI[order], KJ[order]
    cut = np.flatnonzero(np.r_[True, (I[1:] != I[:-1]) | (J[1:] != J[:-1]), True])
    pairs: dict[tuple[int, int], np.ndarray] = {}
    n_out_total = 0
    for s, e in zip(cut[:-1], cut[1:]):
        i, j = int(I[s]), int(J[s])
        m = np.stack([KI[s:e], KJ[s:e]], axis=1)
        n_out = rng.binomial(len(m), opt.outlier_ratio) if opt.outlier_ratio > 0 else 0
        if n_out and len(m) + n_out >= opt.min_matches:
            free_i = np.setdiff1d(np.arange(len(keypoints[i])), m[:, 0])
            free_j = np.setdiff1d(np.arange(len(keypoints[j])), m[:, 1])
            n_out = min(n_out, len(free_i), len(free_j))
            out = np.stack([rng.choice(free_i, n_out, replace=False),
                            rng.choice(free_j, n_out, replace=False)], axis=1)
            m = np.concatenate([m, out])
            m = m[rng.permutation(len(m))]
        if len(m) >= opt.min_matches:
            pairs[(i, j)] = m.astype(np.uint32)
            n_out_total += len(m) - (e - s)
    return Observations(track_xyz, track, f_idx, kp_index, uv, keypoints, pairs, n_out_total,
                        len(pts), num_visible)


def _ground_features(scene: TrueScene, opt: ObservationOptions, flight: Flight, pts, tri,
                     limits, rng):
    """The ground's candidate features at `ground_points_per_m2` (instead of points_per_m2)
    and seen up to `ground_max_incidence_deg`: road markings, kerbs and paving are matched
    at grazing angles a facade's texture is not."""
    ground = scene.labels[tri] == LABEL_GROUND
    if opt.ground_points_per_m2 is not None:
        more, more_tri = sample_surface_points(scene, opt.ground_points_per_m2, rng,
                                               near=flight.centres, radius=opt.max_distance,
                                               labels=(LABEL_GROUND,))
        pts, tri = np.vstack([pts[~ground], more]), np.concatenate([tri[~ground], more_tri])
        ground = scene.labels[tri] == LABEL_GROUND
        limits = np.full(len(pts), float(opt.max_incidence_deg))
    if opt.ground_max_incidence_deg is not None:
        limits[ground] = opt.ground_max_incidence_deg
    return pts, tri, limits


@dataclass
class CheckPoints:
    ids: np.ndarray  # (C,) int
    xyz: np.ndarray  # (C,3) local
    obs_frame: np.ndarray
    obs_id: np.ndarray
    obs_uv: np.ndarray  # with noise


def simulate_checkpoints(flight: Flight, scene: TrueScene, raycaster, obs_opt: ObservationOptions,
                         opt: CheckPointOptions, seed: int) -> CheckPoints:
    """Targets on the main wall and roof planes of the true scene, spread out by farthest-point
    sampling among candidates seen in >= min_views key frames."""
    rng = np.random.default_rng([seed, STAGE_CHECK])
    empty = CheckPoints(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64),
                        np.zeros(0, np.int64), np.zeros((0, 2)))
    if opt.count <= 0:
        return empty
    chosen_all = []
    # candidates: a fixed number on walls and on roofs near the flight
    for labels, n_want in ((LABEL_WALL,), opt.count - round(opt.count * opt.roof_fraction)), \
            ((LABEL_ROOF,), round(opt.count * opt.roof_fraction)):
        if n_want <= 0:
            continue
        area = scene.areas[np.isin(scene.labels, labels)].sum()
        density = opt.candidates / 2 / max(area, 1e-9)
        pts, tri = sample_surface_points(scene, density, rng, near=flight.centres,
                                         radius=obs_opt.max_distance, labels=labels)
        if len(pts) == 0:
            continue
        normals = scene.normals[tri]
        p, f, uv, _ = visibility(flight, pts, normals, raycaster, obs_opt, progress=False)
        views = np.bincount(p, minlength=len(pts))
        cand = np.flatnonzero(views >= opt.min_views)
        if len(cand) == 0:
            continue
        # farthest point sampling
        sel = [cand[rng.integers(len(cand))]]
        d = np.linalg.norm(pts[cand] - pts[sel[0]], axis=1)
        while len(sel) < min(n_want, len(cand)):
            nxt = int(np.argmax(d))
            sel.append(cand[nxt])
            d = np.minimum(d, np.linalg.norm(pts[cand] - pts[cand[nxt]], axis=1))
        for s in sel:
            mask = p == s
            chosen_all.append((pts[s], f[mask], uv[mask]))
    if not chosen_all:
        return empty
    # order along the flight (mean frame index), ids from 1
    chosen_all.sort(key=lambda c: float(np.mean(c[1])))
    ids = np.arange(1, len(chosen_all) + 1)
    xyz = np.array([c[0] for c in chosen_all])
    of = np.concatenate([c[1] for c in chosen_all])
    oi = np.concatenate([np.full(len(c[1]), i) for i, c in zip(ids, chosen_all)])
    ouv = np.concatenate([c[2] for c in chosen_all])
    ouv = ouv + rng.normal(0.0, opt.pixel_noise, ouv.shape)
    order = np.lexsort((oi, of))
    return CheckPoints(ids, xyz, of[order], oi[order], ouv[order])


def simulate_gnss(flight: Flight, opt: GNSSOptions, seed: int) -> np.ndarray:
    """Local GNSS positions: truth + white noise + a smooth bias (Gaussian-filtered noise along
    the path with std `bias_sigma` and correlation length `bias_length`) + a constant bias of
    length `bias_magnitude` in a direction uniform on the sphere (drawn from the seed only, so
    the same direction for every magnitude and independent of the other noise) + the gross
    errors of `gnss_gross_errors` (outliers and a step)."""
    rng = np.random.default_rng([seed, STAGE_GNSS])
    n = len(flight.centres)
    white_sigma = opt.sigma if opt.white_sigma is None else opt.white_sigma
    white = rng.standard_normal((n, 3)) * np.asarray(white_sigma)
    s = flight.arc
    grid = np.arange(s.min() - 3 * opt.bias_length, s.max() + 3 * opt.bias_length + 1.0, 1.0)
    raw = rng.standard_normal((len(grid), 3))
    sig = max(opt.bias_length / 2.0, 1e-6)
    kx = np.arange(-int(3 * sig), int(3 * sig) + 1)
    kernel = np.exp(-0.5 * (kx / sig) ** 2)
    kernel /= np.sqrt(np.sum(kernel ** 2))  # unit variance after filtering
    smooth = np.stack([np.convolve(raw[:, i], kernel, mode="same") for i in range(3)], axis=1)
    bias = np.stack([np.interp(s, grid, smooth[:, i]) for i in range(3)], axis=1)
    bias *= np.asarray(opt.bias_sigma)
    if opt.bias_magnitude:
        bias = bias + opt.bias_magnitude * constant_bias_direction(seed)
    return flight.centres + white + bias + gnss_gross_errors(flight, opt, seed)[0]


def gnss_gross_errors(flight: Flight, opt: GNSSOptions, seed: int) -> tuple[np.ndarray, dict]:
    """GNSSOptions' outliers and step: the (N, 3) errors they add to the positions, and what
    they are (the outlying key frames with their errors, the first key frame of the step and
    its vector; {} when there are none). Drawn from their own stream (seed, STAGE_GNSS_GROSS)."""
    rng = np.random.default_rng([seed, STAGE_GNSS_GROSS])
    n = len(flight.centres)
    errors = np.zeros((n, 3))
    info: dict = {}
    if opt.outliers > 0 and n > 2:
        frames = np.sort(rng.choice(np.arange(1, n - 1), size=min(opt.outliers, n - 2),
                                    replace=False))
        lengths = rng.uniform(*opt.outlier_range, len(frames))
        errors[frames] = lengths[:, None] * _unit_vectors(rng, len(frames))
        info["outliers"] = [{"image": flight.names[k], "error_m": errors[k].tolist()}
                            for k in frames]
    if opt.step_magnitude > 0:
        at = rng.uniform(*opt.step_range) * flight.arc[-1]
        first = int(np.searchsorted(flight.arc, at))
        step = opt.step_magnitude * _unit_vectors(rng, 1)[0]
        errors[first:] += step
        if first < n:
            info["step"] = {"from_image": flight.names[first], "vector_m": step.tolist()}
    return errors, info


def _unit_vectors(rng: np.random.Generator, n: int) -> np.ndarray:
    """n directions uniform on the sphere."""
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def constant_bias_direction(seed: int) -> np.ndarray:
    """The unit direction of GNSSOptions.bias_magnitude's bias for a seed (uniform on the
    sphere)."""
    v = np.random.default_rng([seed, STAGE_GNSS, 1]).standard_normal(3)
    return v / np.linalg.norm(v)
