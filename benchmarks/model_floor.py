"""How close to the truth a block can get on a given model: the floor set by the model's errors.

For a simulated workspace the true tie points are known. Assigned to a model variant (direct
assignment, the final threshold refine reaches, visible surfaces only, each point to the nearer
of two parallel surfaces however close: at the truth the nearer is right) and moved onto its
planes by the
least-squares similarity (7 parameters about the cameras' centroid), they take the true cameras
with them: the camera-centre error after that fit is what a method that trusts the model's
planes inherits from the model, however good its tie points and GNSS are. With exact planes
the floor is zero.

Two weightings:
- `per point`: every assigned point with the same sigma (sigma_dTP), as refine's f_dTP;
- `per face`: each face's points share one face weight (the face's plane error is one error,
  not one per point), so a face with thousands of points counts as much as one with twenty.
Each also with every point weighted by its own precision along its face's normal (`precision`,
see its table). And each point either on the nearest plane of the model variant within the
window, or (`own surfaces`) on the face whose true surface it lies on (found against the
`corrected` model, whose planes are the true surfaces'), however far the given plane stands
off it: the nearest-plane cut drops the points of a face whose given plane stands further off
than the window, which no method away from the truth can copy. Where a workspace has check
points, each fit also moves the true images, the check points are triangulated there from
their observations (with their image noise) and their RMS 3D error is the check-point floor.

The similarity has priors at the truth: translation with the sigma a GNSS-only block has
(the stated GNSS sigma / sqrt(images); unbiased, unlike the simulated GNSS), rotation 1 deg, scale
1 %. Where the planes fix a direction these do not matter; where they leave it free (the drive's
height) the fit shows what the planes' small components in that direction (a wall tilted by the
model's 0.5 deg) do to it. Where the planes fix a direction only weakly, these priors at the
truth lower the floor: the `planes alone` fits (translation 100 m, rotation 20 deg, scale 20 %)
show the floor without them.

The floor assumes that the true block is where the model's planes want the block to be. A
further table checks that with the given model. Three sets of tie points are each assigned to the
model as above and scored as a fit to it: the true block (its true tie points, without SfM
noise, which favours the truth); the same true block moved rigidly to where refine put the
cameras (the similarity that takes the true cameras onto refine's, fitted to their centres and
to points 10 m along their three axes, so that the roll about a straight line is fixed too); and
refine's own tie points, which the adjustment has also moved each towards its plane (so they fit
better than a rigid block could; the rigid one is the fair comparison). The scores: the share of
tie points within the threshold, their RMS distance, both in one as the mean over all tie points
of Tukey's biweight (1 - (d / threshold)^2)^2 (`near score`, 0 beyond the threshold), and the
faces' mean offsets in units of the generalisation sigma (0.2 m), each capped at 2 (a face
further off counts as an outlier, not more), summed in squares (`face score`). Where the true
block at refine's pose fits the model at least as well as at its true pose by both scores, no
method that fits these planes can prefer the truth: what remains is the model's error, not the
optimiser's. Another scores the true block moved by 0.3 m along each axis the same way:
where a moved block scores better than the true one, the model itself pulls the block off the
truth in that direction. Last, refine is started at the truth: the same block with the true
projection centres as its GNSS (stated sigma as the workspace's, no bias, no noise), so that its
GNSS-only block is within millimetres of the truth; where it ends there is the model's optimum
near the truth, and how far that lies from where refine ends with the workspace's biased GNSS
says whether the start matters.

Writes benchmarks/results/model_floor.md (with refine's own figures and the per-direction
target from the `robustness` section of scenarios.json beside the floor), the `model_floor`
section of scenarios.json and benchmarks/results/model_floor.json (per case: the planes-alone
floors of the given model, every point alike and each face once, and refine's own result).
With `--seeds 1 2 3 --results model_floor_seeds` each robustness case is also measured at other
realisations of its block (other plane errors, GNSS and SfM noise), with a table of refine
against its floors per realisation: one realisation's floor can be luck.
Other generated workspaces (`--cases long/Scn3 long/Scn4`, with `--results model_floor_long`)
are compared on check points with their `refine_a` run in scenarios.json.

    .venv/bin/python benchmarks/model_floor.py [--cases drive orbit strip short]
        [--variants original corrected detailed] [--threshold 0.45] [--no_refine] [--seeds N ...]
        [--results model_floor]
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pycolmap

from colmap_citymodel.assign.direct import assign_direct
from colmap_citymodel.assign.direct import centred_surfaces as centred_on_faces
from colmap_citymodel.citymodel.ground_faces import terrain_mask
from colmap_citymodel.citymodel.read import read_city_model
from colmap_citymodel.options import AssignmentOptions
from colmap_citymodel.precision.checkpoints import (evaluate_checkpoints,
                                                    read_checkpoint_observations,
                                                    read_checkpoints)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
from scenarios import (ROBUST_CASES, build_robust_workspace, centre_errors,  # noqa: E402
                       inputs, truth_centres, update_json)
GENERATED = ROOT / "workspaces" / "generated"
ROBUST = GENERATED / "robust"
RESULTS = ROOT / "benchmarks" / "results"
# The per-direction target of the robustness cases where the planes fix a direction.
TARGET_M, TARGET_GAIN = 0.25, 10.0
SIGMA_DTP = 0.2
ROTATION_SIGMA = np.radians(1.0)
SCALE_SIGMA = 0.01
#: Priors of the `planes alone` fits: so loose that only the planes hold the similarity.
LOOSE_PRIORS = np.concatenate([np.full(3, 100.0), np.full(3, np.radians(20.0)), [0.2]])


def true_block(workspace: Path):
    truth = pycolmap.Reconstruction(str(workspace / "truth"))
    origin = np.loadtxt(workspace / "truth" / "origin.txt", comments="#")[:3]
    points = np.array([p.xyz for p in truth.points3D.values()])
    ids = np.array(list(truth.points3D.keys()), dtype=np.int64)
    centres = np.array([truth.images[i].projection_center() for i in sorted(truth.images)])
    return points + origin, ids, centres + origin


#: The image sigma (px) of the tie points' observations in `point_covariances`.
SIGMA_PX = 1.0


def point_covariances(workspace: Path, ids: np.ndarray, sigma_px: float = SIGMA_PX
                      ) -> np.ndarray:
    """(N, 3, 3) covariance (m^2) of each true tie point `ids` from its track's geometry: the
    inverse of sum_i J_i^T J_i / sigma_px^2 over the truth's images that observe it, J_i the
    2x3 derivative of the pinhole projection (the camera's focal lengths, distortion left out)
    with respect to the point. Nearly parallel rays leave it long along them."""
    truth = pycolmap.Reconstruction(str(workspace / "truth"))
    rows, images = [], []
    for row, point_id in enumerate(ids.tolist()):
        for element in truth.points3D[point_id].track.elements:
            rows.append(row)
            images.append(element.image_id)
    rows, images = np.array(rows), np.array(images)
    order = sorted(truth.images)
    slot = {image_id: k for k, image_id in enumerate(order)}
    rotation = np.array([truth.images[i].cam_from_world().rotation.matrix() for i in order])
    translation = np.array([truth.images[i].cam_from_world().translation for i in order])
    focal = np.array([np.diag(truth.cameras[truth.images[i].camera_id].calibration_matrix())[:2]
                      for i in order])
    k = np.array([slot[i] for i in images.tolist()])
    xyz = np.array([truth.points3D[i].xyz for i in ids.tolist()])[rows]
    camera = np.einsum("kij,kj->ki", rotation[k], xyz) + translation[k]
    z = camera[:, 2]
    jac = np.zeros((len(k), 2, 3))
    for axis in (0, 1):
        jac[:, axis, axis] = focal[k, axis] / z
        jac[:, axis, 2] = -focal[k, axis] * camera[:, axis] / z ** 2
    jac = np.einsum("kab,kbc->kac", jac, rotation[k]) / sigma_px
    information = np.zeros((len(ids), 3, 3))
    np.add.at(information, rows, np.einsum("kai,kaj->kij", jac, jac))
    return np.linalg.inv(information)


def precision_weights(covariances: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Each point's weight 1 / (sigma_dTP^2 + s_n^2), s_n its position sigma along its face's
    normal (`covariances` projected on `normals`)."""
    along = np.einsum("ki,kij,kj->k", normals, covariances, normals)
    return 1.0 / (SIGMA_DTP ** 2 + along)


def fit_similarity(points: np.ndarray, normals: np.ndarray, offsets: np.ndarray,
                   weights: np.ndarray, centre: np.ndarray,
                   prior_sigmas: np.ndarray) -> np.ndarray:
    """Linearised least squares: x' = x + t + omega x (x - c) + s (x - c) onto the planes
    n.x' + d = 0. Returns [t (3), omega (3), s]."""
    r = points - centre
    a = np.hstack([normals, np.cross(r, normals), np.einsum("ij,ij->i", normals, r)[:, None]])
    b = -(np.einsum("ij,ij->i", normals, points) + offsets)
    w = weights[:, None]
    lhs = a.T @ (a * w) + np.diag(1.0 / prior_sigmas ** 2)
    return np.linalg.solve(lhs, a.T @ (b * weights))


def apply(params: np.ndarray, x: np.ndarray, centre: np.ndarray) -> np.ndarray:
    r = x - centre
    return x + params[:3] + np.cross(params[3:6], r) + params[6] * r


def camera_error(points: np.ndarray, normals: np.ndarray, offsets: np.ndarray,
                 weights: np.ndarray, centres: np.ndarray, prior_sigmas: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """`fit_similarity` about the cameras' centroid and what it does to the cameras: the
    parameters and the (3,) RMS per axis of the moved `centres` against where they were."""
    centre = centres.mean(axis=0)
    params = fit_similarity(points, normals, offsets, weights, centre, prior_sigmas)
    error = apply(params, centres, centre) - centres
    return params, np.sqrt(np.mean(error ** 2, axis=0))


#: The assignment at the truth: every point to its nearest visible face, also where a parallel
#: surface is near (at the true pose the nearer one is right): the floor keeps all information.
AT_TRUTH = AssignmentOptions(ambiguity_margin=0.0)
#: A tie point whose sigma along its face's normal exceeds this (m) counts as imprecise in the
#: tables: it holds the block less than a tenth as much as an exact one.
IMPRECISE_SIGMA = 3 * SIGMA_DTP


def own_surfaces(workspace: Path, store, points_crs: np.ndarray, ids: np.ndarray,
                 threshold: float):
    """The assignment of the true tie points to the surfaces they lie on: made against the
    `corrected` model (the true surfaces' planes, without the given model's plane errors) and
    carried to `store`'s faces, which are the same faces (same ids, same order) moved by the
    given model's errors; None where the two models do not hold the same faces."""
    surfaces = read_city_model(workspace / "models" / "corrected.gml")
    same = (surfaces.num_faces == store.num_faces
            and all(surfaces.faces.gml_id[f] == store.faces.gml_id[f]
                    for f in range(store.num_faces)))
    if not same:
        return None
    return assign_direct(surfaces.to_local(points_crs), ids, surfaces, threshold, AT_TRUTH)


def floor(workspace: Path, variant: str, block, threshold: float, gnss_sigma: np.ndarray,
          covariances: np.ndarray | None = None, by_surface: bool = False) -> dict | None:
    """The floor of one model variant; `block` is `true_block(workspace)`. With `covariances`
    (`point_covariances` of the block's points) also the `precision` weightings: each point
    weighted by `precision_weights`, every point alike or each face's points sharing it.
    `by_surface`: each point on the face whose true surface it lies on (`own_surfaces`)
    instead of the face nearest to it (None where that cannot be told)."""
    store = read_city_model(workspace / "models" / f"{variant}.gml")
    points_crs, ids, centres_crs = block
    points = store.to_local(points_crs)
    centres = store.to_local(centres_crs)
    assignment = (own_surfaces(workspace, store, points_crs, ids, threshold) if by_surface
                  else assign_direct(points, ids, store, threshold, AT_TRUTH))
    if assignment is None:
        return None
    mask = assignment.assigned
    faces = assignment.face_index[mask]
    normals = store.normals[faces]
    offsets = store.offsets[faces]
    prior_sigmas = np.concatenate([gnss_sigma / np.sqrt(len(centres)),
                                   np.full(3, ROTATION_SIGMA), [SCALE_SIGMA]])
    counts = np.bincount(faces, minlength=store.num_faces)
    out = {"points": int(mask.sum()), "faces": int(len(np.unique(faces)))}
    weightings = [("per point", np.full(mask.sum(), 1.0 / SIGMA_DTP ** 2)),
                  ("per face", 1.0 / SIGMA_DTP ** 2 / counts[faces])]
    if covariances is not None:
        precise = precision_weights(covariances[mask], normals)
        weightings += [("precision per point", precise),
                       ("precision per face", precise / counts[faces])]
        out["imprecise_points"] = int(np.sum(1.0 / precise - SIGMA_DTP ** 2
                                             > IMPRECISE_SIGMA ** 2))
    checks = checkpoints_local(workspace, store)
    for (name, weights), (suffix, priors) in itertools.product(
            weightings, (("", prior_sigmas), (", planes alone", LOOSE_PRIORS))):
        name += suffix
        params, rms = camera_error(points[mask], normals, offsets, weights, centres, priors)
        out[name] = {"rms_x": float(rms[0]), "rms_y": float(rms[1]), "rms_z": float(rms[2]),
                     "rms_3d": float(np.sqrt(np.sum(rms ** 2))),
                     "translation": params[:3].tolist(),
                     "rotation_deg": np.degrees(params[3:6]).tolist(), "scale_ppm": params[6] * 1e6}
        if checks is not None:
            out[name]["checkpoints_3d"] = checkpoint_floor(checks, params, centres.mean(axis=0),
                                                           store)
    return out


@dataclasses.dataclass
class Checks:
    """A workspace's true block and check points: what `checkpoint_floor` triangulates."""
    truth: pycolmap.Reconstruction
    origin: np.ndarray  # of the truth's local frame (CRS)
    points: dict  # id -> (3,) CRS
    observations: list


def checkpoints_local(workspace: Path, store) -> Checks | None:
    """The workspace's true block, check points and their image observations, or None."""
    if not (workspace / "checkpoint_observations.txt").exists():
        return None
    return Checks(pycolmap.Reconstruction(str(workspace / "truth")),
                  np.loadtxt(workspace / "truth" / "origin.txt", comments="#")[:3],
                  read_checkpoints(workspace / "checkpoints.txt"),
                  read_checkpoint_observations(workspace / "checkpoint_observations.txt"))


def checkpoint_floor(checks: Checks, params: np.ndarray, centre: np.ndarray, store) -> float:
    """The check points' RMS 3D error (m) of the true block moved by a floor's similarity
    (`params` about `centre`, in `store`'s local frame): each check point triangulated from
    its observations (with their image noise) in the moved true images, as refine's check
    points are in its block."""
    from scipy.spatial.transform import Rotation

    shift = checks.origin - store.origin  # truth's local frame -> store's
    rotation = Rotation.from_rotvec(params[3:6]).as_matrix()
    scale = 1.0 + params[6]
    translation = scale * rotation @ (shift - centre) + centre + params[:3] - shift
    moved = pycolmap.Reconstruction(checks.truth)
    moved.transform(pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), translation))
    found = evaluate_checkpoints(moved, checks.points, checks.observations, checks.origin,
                                 frame="local")
    return float(found.rms_3d)


#: Rounds of assignment and fit in `reassigned_from_truth`, and the band (m) in which a face's
#: own offset (the median signed distance of the points near it) is measured for the windows
#: centred on it.
ICP_ROUNDS, CENTRE_BAND = 12, 1.0


def centred_surfaces(store, points: np.ndarray, ids: np.ndarray, threshold: float):
    """`store` with each face moved to the median signed distance of the points within
    CENTRE_BAND of it (assign.direct.centred_surfaces): an assignment window centred there
    takes a face's points evenly from both sides of where they lie, wherever the block
    stands."""
    return centred_on_faces(points, ids, store, threshold,
                            dataclasses.replace(AT_TRUTH, window_reach=CENTRE_BAND - threshold))


def fit_face_units(points: np.ndarray, faces: np.ndarray, store, centre: np.ndarray,
                   prior_sigmas: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`fit_similarity` with each face's error as a random effect shared by its points: an
    offset and a tilt (its edges off by the same sigma), all with the prior SIGMA_FACE_UNIT.
    Returns the 7 parameters and the (F,) offsets (0 for faces without points)."""
    used, slot = np.unique(faces, return_inverse=True)
    k, rows = len(used), np.arange(len(points))
    normals, r = store.normals[faces], points - centre
    effects = np.zeros((len(points), 3 * k))
    effects[rows, slot] = 1.0
    rotations, radius = store.rotations[faces], np.sqrt(store.areas[faces]) / 2
    local = points - store.centroids[faces]
    for axis in (0, 1):
        effects[rows, k * (axis + 1) + slot] = np.einsum(
            "ki,ki->k", local, rotations[:, :, axis]) / radius
    design = np.hstack([normals, np.cross(r, normals),
                        np.einsum("ij,ij->i", normals, r)[:, None], effects])
    observed = -(np.einsum("ij,ij->i", normals, points) + store.offsets[faces])
    priors = np.concatenate([1.0 / prior_sigmas ** 2, np.full(3 * k, SIGMA_FACE_UNIT ** -2)])
    solution = np.linalg.solve(design.T @ design / SIGMA_DTP ** 2 + np.diag(priors),
                               design.T @ observed / SIGMA_DTP ** 2)
    offsets = np.zeros(store.num_faces)
    offsets[used] = solution[7:7 + k]
    return solution[:7], offsets


#: The prior sigma (m) of a face's offset and of its edges' tilt in the face-unit fits: a LOD2
#: model's generalisation (Unger 5.3). The scale priors of those fits: GNSS-like and tight.
SIGMA_FACE_UNIT, UNIT_SCALE_SIGMAS = 0.2, (0.01, 0.001)

REASSIGNED_SCHEMES = ("per point, at the plane", "per point, centred", "per face, at the plane",
                      "per face, centred", "face units, scale 1 %", "face units, scale 0.1 %")


def _reassign_rounds(scheme: str, store, true_points: np.ndarray, ids: np.ndarray,
                     truth: np.ndarray, threshold: float, prior_sigmas: np.ndarray) -> dict:
    """ICP_ROUNDS of assignment at the last pose and fit of the true block for one scheme."""
    points, centres, centre = true_points, truth, truth.mean(axis=0)
    units = scheme.startswith("face units")
    if units:
        prior_sigmas = prior_sigmas.copy()
        prior_sigmas[6] = UNIT_SCALE_SIGMAS[0 if scheme.endswith(" 1 %") else 1]
    shifts = np.zeros(store.num_faces)
    for _ in range(ICP_ROUNDS):
        if units:  # the window around where the last fit put each face's surface
            surfaces = store.with_plane_shifts(shifts)
        else:
            surfaces = (centred_surfaces(store, points, ids, threshold) if "centred" in scheme
                        else store)
        assignment = assign_direct(points, ids, surfaces, threshold, AT_TRUTH)
        mask = assignment.assigned
        faces = assignment.face_index[mask]
        # Each fit moves the true block (the priors hold it near the truth, not near the
        # last pose); only the assignment follows where the last fit put it.
        if units:
            params, shifts = fit_face_units(true_points[mask], faces, store, centre,
                                            prior_sigmas)
        else:
            weights = np.full(mask.sum(), 1.0 / SIGMA_DTP ** 2)
            if scheme.startswith("per face"):
                weights = weights / np.bincount(faces, minlength=store.num_faces)[faces]
            params = fit_similarity(true_points[mask], store.normals[faces],
                                    store.offsets[faces], weights, centre, prior_sigmas)
        points, centres = apply(params, true_points, centre), apply(params, truth, centre)
    rms = np.sqrt(np.mean((centres - truth) ** 2, axis=0))
    return {"rms_3d": float(np.sqrt(np.sum(rms ** 2))), "rms": rms.tolist(),
            "scale_ppm": float(params[6] * 1e6), "points": int(mask.sum()),
            "faces": int(len(np.unique(faces)))}


def reassigned_from_truth(workspace: Path, block, threshold: float, gnss_sigma: np.ndarray
                          ) -> dict:
    """The true block of the given model, assigned and fitted (7 parameters, the floor's priors
    at the truth) again and again from its true pose, as refine's loop does: where it settles
    is the floor of a method that reassigns (each fit moves the true block; only the
    assignment follows the last pose), for each scheme of REASSIGNED_SCHEMES: weighting (every
    point alike, each face once, each face's offset and tilt as random effects) and window
    (at the plane as refine's, centred on each face's own offset)."""
    store = read_city_model(workspace / "models" / "original.gml")
    points_crs, ids, centres_crs = block
    truth = store.to_local(centres_crs)
    prior_sigmas = np.concatenate([gnss_sigma / np.sqrt(len(truth)),
                                   np.full(3, ROTATION_SIGMA), [SCALE_SIGMA]])
    true_points = store.to_local(points_crs)
    return {scheme: _reassign_rounds(scheme, store, true_points, ids, truth, threshold,
                                     prior_sigmas) for scheme in REASSIGNED_SCHEMES}


#: Thresholds (m) of the assignment at the truth in `threshold_table`: from refine's final
#: one to one that takes a face's points wholly however far its model plane stands off.
SWEEP_THRESHOLDS = (0.45, 0.6, 0.8, 1.0)


#: The window (m) at the truth that takes a face's whole visible part: refine's final 0.45 m
#: plus the given model's 0.5 deg tilt per face acting at the farthest visible point of a face
#: from its centroid in these blocks (~40 m: 0.35 m).
WIDE_WINDOW_M = 0.8


def compact(fit: dict) -> dict:
    """A `floor` entry as camera-centre RMS per axis and 3D (m) and the fit's scale (ppm)."""
    return {"E": fit["rms_x"], "N": fit["rms_y"], "U": fit["rms_z"], "3d": fit["rms_3d"],
            "scale_ppm": fit["scale_ppm"]}


def threshold_sweep(workspace: Path, block, gnss_sigma: np.ndarray,
                    covariances: np.ndarray) -> dict:
    """The planes-alone floors of the given model with the truth assigned at each of
    SWEEP_THRESHOLDS: {threshold: {"per point": rms_3d, "per face": rms_3d, "points": n,
    "imprecise_points": n, "precision per point" / "precision per face": `compact`}}."""
    out = {}
    for threshold in SWEEP_THRESHOLDS:
        f = floor(workspace, "original", block, threshold, gnss_sigma, covariances)
        out[f"{threshold:g}"] = {
            "per point": f["per point, planes alone"]["rms_3d"],
            "per face": f["per face, planes alone"]["rms_3d"], "points": f["points"],
            "imprecise_points": f["imprecise_points"],
            **{k: compact(f[f"{k}, planes alone"])
               for k in ("precision per point", "precision per face")}}
    return out


def precision_table(rows: dict) -> list[str]:
    """The planes-alone floors with each point weighted by its own precision, per case and
    window at the truth (`threshold_sweep`'s rows)."""
    keys = [f"{t:g}" for t in SWEEP_THRESHOLDS]
    lines = ["| case | window (m) | points | imprecise | every point alike: 3D "
             "| precision per point: E | N | U | 3D | scale | precision per face: E | N | U "
             "| 3D | scale |", "|---" * 15 + "|"]
    for case, found in rows.items():
        for key in keys:
            row = found[key]
            cells = [f"{case}", key + (" (wide)" if float(key) == WIDE_WINDOW_M else ""),
                     str(row["points"]), str(row["imprecise_points"]), f"{row['per point']:.3f}"]
            for weighting in ("precision per point", "precision per face"):
                fit = row[weighting]
                cells += [f"{fit[a]:.3f}" for a in ("E", "N", "U", "3d")]
                cells.append(f"{fit['scale_ppm'] / 1e4:+.2f} %")
            lines.append("| " + " | ".join(cells) + " |")
    return lines


def threshold_table(rows: dict) -> list[str]:
    keys = [f"{t:g}" for t in SWEEP_THRESHOLDS]
    lines = ["| case | " + " | ".join(f"{k} m: per point / per face (points)" for k in keys)
             + " |", "|---" * (len(keys) + 1) + "|"]
    for case, found in rows.items():
        lines.append(f"| {case} | " + " | ".join(
            f"{found[k]['per point']:.3f} / {found[k]['per face']:.3f} ({found[k]['points']})"
            for k in keys) + " |")
    return lines


def reassigned_table(rows: dict) -> list[str]:
    keys = REASSIGNED_SCHEMES
    lines = ["| case | " + " | ".join(keys) + " |", "|---" * (len(keys) + 1) + "|"]
    for case, found in rows.items():
        lines.append(f"| {case} | " + " | ".join(
            f"{found[k]['rms_3d']:.3f} ({found[k]['scale_ppm']:+.0f} ppm)" for k in keys) + " |")
    return lines


#: The generalisation sigma (m) a face's mean offset is measured in, and the cap (in those
#: units) beyond which a face counts as an outlier in `model_fit`.
GENERALISATION_SIGMA, FACE_CAP = 0.2, 2.0


def model_fit(points_crs: np.ndarray, store, threshold: float) -> dict:
    """How well tie points (model CRS) fit `store`: directly assigned at `threshold`, the share
    within it, their RMS distance and the capped per-face score (see the module text)."""
    points = store.to_local(points_crs)
    ids = np.arange(len(points), dtype=np.int64)
    assignment = assign_direct(points, ids, store, threshold, AssignmentOptions())
    mask = assignment.assigned
    faces = assignment.face_index[mask]
    distances = np.einsum("ij,ij->i", points[mask], store.normals[faces]) + store.offsets[faces]
    score = 0.0
    for face in np.unique(faces):
        mean = distances[faces == face].mean() / GENERALISATION_SIGMA
        score += min(abs(mean), FACE_CAP) ** 2
    # Both in one: each tie point scores (1 - (d / threshold)^2)^2 within the threshold, 0
    # beyond (Tukey's biweight), averaged over all of them.
    near = np.sum((1.0 - (distances / threshold) ** 2) ** 2) / max(len(points), 1)
    return {"points": int(mask.sum()), "share": float(mask.mean()) if len(mask) else 0.0,
            "near_score": float(near),
            "rms": float(np.sqrt(np.mean(distances ** 2))) if len(distances) else float("nan"),
            "faces": int(len(np.unique(faces))), "face_score": float(score)}


#: How far along each camera axis the points that fix the pose similarity lie (m).
AXIS_LEVER_M = 10.0


def pose_points(rec: pycolmap.Reconstruction, names: list[str], origin: np.ndarray,
                lever: float = AXIS_LEVER_M) -> np.ndarray:
    """Per image (by name): its projection centre and the points `lever` along its camera
    axes, model CRS (`origin` added to the reconstruction's frame)."""
    by_name = {image.name: image for image in rec.images.values()}
    out = []
    for name in names:
        image = by_name[name]
        centre = image.projection_center() + origin
        axes = np.asarray(image.cam_from_world().rotation.matrix())
        out += [centre, *(centre + lever * axes)]
    return np.array(out)


def true_centres_as_gnss(centres: dict[str, np.ndarray], store, sigma: np.ndarray):
    """GNSS observations that are the true projection centres (`truth_centres`, model CRS)
    with `sigma`."""
    import tempfile

    from colmap_citymodel.block.gnss import read_gnss_text

    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "true_centres.txt"
        path.write_text("".join(f"{name} {c[0]:.4f} {c[1]:.4f} {c[2]:.4f} "
                                f"{sigma[0]} {sigma[1]} {sigma[2]}\n"
                                for name, c in centres.items()))
        return read_gnss_text(path, store.crs.label, store.crs)


def refine_against_truth(workspace: Path, workspace_inputs, block, threshold: float,
                         gnss_sigma: np.ndarray) -> dict:
    """refine() on the workspace (`workspace_inputs`: its reconstruction, given model and GNSS,
    scenarios.inputs), then `model_fit` against that model of the true tie points, of them
    moved rigidly to refine's pose of the block, and of refine's own tie points; with refine's
    camera-centre RMS against the truth. Also refine started at the truth
    (`true_centres_as_gnss`) and how far its cameras end from the first refine's."""
    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.precision.checkpoints import helmert_transform
    from colmap_citymodel.workflow import refine

    rec, store, gnss = workspace_inputs
    centres = truth_centres(workspace)
    options = RefineOptions.preset("generalised")
    options.precision.covariances = "off"
    dtm = sorted((workspace / "dtm").glob("*.tif"))  # as scenarios.refine_with_quality
    if dtm:
        options.terrain.files = tuple(str(p) for p in dtm)
    result = refine(rec, store, gnss, options, progress=False)

    def block_of(r):
        """Refine's own block, also where its verdict "failed" handed back the GNSS-only one."""
        return r.refined if r.refined is not None else r.reconstruction

    own = block_of(result)
    refined = np.array([p.xyz for p in own.points3D.values()]) + store.origin
    cameras = centre_errors(own, store.origin, centres)
    at_truth = refine(rec, store, true_centres_as_gnss(centres, store, gnss_sigma), options,
                      progress=False)
    started = {"cameras": centre_errors(block_of(at_truth), store.origin, centres),
               "gnss_only": centre_errors(at_truth.gnss_only, store.origin, centres),
               "verdict": at_truth.quality.verdict, "reasons": at_truth.quality.reasons}
    first = {image.name: image.projection_center()
             for image in own.images.values() if image.has_pose}
    apart = np.array([image.projection_center() - first[image.name]
                      for image in block_of(at_truth).images.values()
                      if image.has_pose and image.name in first])
    started["apart_rms"] = np.sqrt(np.mean(apart ** 2, axis=0)).tolist()
    truth = pycolmap.Reconstruction(str(workspace / "truth"))
    origin = np.loadtxt(workspace / "truth" / "origin.txt", comments="#")[:3]
    names = sorted(image.name for image in own.images.values() if image.has_pose)
    pose = helmert_transform(pose_points(own, names, store.origin),
                             pose_points(truth, names, origin))
    return {"refine": model_fit(refined, store, threshold),
            "truth": model_fit(block[0], store, threshold),
            "truth_at_refine_pose": model_fit(pose.apply(block[0]), store, threshold),
            "pose_fit_rms": pose.rms_3d,
            "cameras_rms_3d": cameras.get("rms_3d"), "cameras": cameras,
            "gnss_only_rms_3d": (centre_errors(result.gnss_only, store.origin,
                                               centres).get("rms_3d")
                                 if result.gnss_only is not None else None),
            "verdict": result.quality.verdict, "started_at_truth": started,
            "assignment_at_truth": assignment_at_truth(workspace, result, threshold, truth,
                                                       origin)}


#: Faces whose assigned tie points lie further than this from their plane on average at the
#: truth are listed, with at least this many points.
OFF_FACE_M, OFF_FACE_POINTS = 0.3, 50


def assignment_at_truth(workspace: Path, result, threshold: float,
                        truth: pycolmap.Reconstruction, origin: np.ndarray) -> dict:
    """Refine's last assignment judged at the truth: the SfM block (the workspace's
    reconstruction, whose shape is within millimetres of the truth's) moved onto the true
    block by the similarity of their cameras (`pose_points`), and the similarity fit with
    every point weighted alike and the planes alone (`floor`'s) made twice, with refine's
    assignment and with the points assigned afresh at `threshold` at the truth; the faces
    whose points lie further than OFF_FACE_M from their plane, or from their true surface,
    on average at the truth (`off_faces`).
    `truth`, `origin`: the workspace's true block and its origin."""
    from colmap_citymodel.precision.checkpoints import helmert_transform

    store = result.store  # the faces refine's assignment indexes (cropped to the block)
    sfm = pycolmap.Reconstruction(str(workspace / "sparse" / "0"))
    names = sorted(image.name for image in sfm.images.values() if image.has_pose)
    true_centres = np.array([truth.find_image_with_name(n).projection_center()
                             for n in names]) + origin
    # SfM's frame has its own unit: the axis points at the same distance in metres.
    unit = helmert_transform(true_centres, [sfm.find_image_with_name(n).projection_center()
                                            for n in names]).scale
    onto_truth = helmert_transform(pose_points(truth, names, origin),
                                   pose_points(sfm, names, np.zeros(3), AXIS_LEVER_M / unit))
    ids = np.array(list(sfm.points3D.keys()), dtype=np.int64)
    points = store.to_local(onto_truth.apply(np.array([sfm.points3D[i].xyz for i in ids])))
    centres = store.to_local(true_centres)
    row = {point_id: k for k, point_id in enumerate(ids.tolist())}  # point id -> row
    assignment = result.assignment
    mask = assignment.assigned & np.isin(assignment.point_ids, ids)
    refine_rows = np.array([row[int(i)] for i in assignment.point_ids[mask]], dtype=np.int64)
    refine_faces = assignment.face_index[mask]
    fresh = assign_direct(points, ids, store, threshold, AT_TRUTH)

    def fit(rows: np.ndarray, faces: np.ndarray) -> dict:
        params, rms = camera_error(points[rows], store.normals[faces], store.offsets[faces],
                                   np.full(len(rows), 1.0 / SIGMA_DTP ** 2), centres,
                                   LOOSE_PRIORS)
        return {"points": int(len(rows)), "faces": int(len(np.unique(faces))),
                "rms": rms.tolist(), "rms_3d": float(np.sqrt(np.sum(rms ** 2))),
                "scale_ppm": float(params[6] * 1e6)}

    return {"refine": fit(refine_rows, refine_faces),
            "fresh": fit(np.flatnonzero(fresh.assigned), fresh.face_index[fresh.assigned]),
            "camera_fit_rms": onto_truth.rms_3d,
            **off_faces(workspace, store, onto_truth.apply(
                np.array([sfm.points3D[i].xyz for i in ids]))[refine_rows], refine_faces,
                threshold)}


def true_surface_distances(workspace: Path, store, points_crs: np.ndarray, faces: np.ndarray
                           ) -> np.ndarray:
    """Each point's signed distance (m) from the true surface of its face in `store`: that
    face's plane in the `corrected` model (same id, parallel), NaN for faces it lacks
    (terrain cells)."""
    surfaces = read_city_model(workspace / "models" / "corrected.gml")
    by_id = {}
    for f in range(surfaces.num_faces):
        by_id.setdefault(surfaces.faces.gml_id[f], []).append(f)
    local = surfaces.to_local(points_crs)
    out = np.full(len(faces), np.nan)
    for face in np.unique(faces):
        rows = np.flatnonzero(faces == face)
        for twin in by_id.get(store.faces.gml_id[face], []):
            if abs(surfaces.normals[twin] @ store.normals[face]) > 0.99:
                out[rows] = local[rows] @ surfaces.normals[twin] + surfaces.offsets[twin]
                break
    return out


def off_faces(workspace: Path, store, points_crs: np.ndarray, faces: np.ndarray,
              threshold: float) -> dict:
    """The faces of an assignment (at least OFF_FACE_POINTS points, true positions
    `points_crs`) whose points lie further than OFF_FACE_M from the face on average, judged
    twice: `off_faces` against the given model's plane (its plane error or points of another
    surface), `off_own_surface` against the face's true surface (points of another surface);
    terrain cells, which carry an offset unknown of their own, counted apart."""
    terrain = terrain_mask(store)
    given = np.einsum("ij,ij->i", store.to_local(points_crs), store.normals[faces]) \
        + store.offsets[faces]
    true = true_surface_distances(workspace, store, points_crs, faces)
    out = {"off_faces": [], "off_own_surface": [], "terrain_cells_off": 0}
    for face in np.unique(faces):
        rows = faces == face
        d = given[rows]
        if len(d) < OFF_FACE_POINTS or abs(d.mean()) <= OFF_FACE_M:
            continue
        if terrain[face]:
            out["terrain_cells_off"] += 1
            continue
        entry = {"face": int(face), "points": int(len(d)), "mean_m": float(d.mean()),
                 "own_surface_m": float(np.mean(true[rows])),
                 "normal": np.round(store.normals[face], 2).tolist(),
                 "beyond_threshold": int(np.sum(np.abs(d) > threshold))}
        out["off_faces"].append(entry)
    for face in np.unique(faces[~terrain[faces]]):
        d = true[faces == face]
        if len(d) >= OFF_FACE_POINTS and np.isfinite(d).all() and abs(d.mean()) > OFF_FACE_M:
            out["off_own_surface"].append({"face": int(face), "points": int(len(d)),
                                           "mean_m": float(d.mean())})
    return out


def assignment_table(rows: dict, threshold: float) -> list[str]:
    lines = ["| case | assignment | points | faces | cameras after the fit: X | Y | Z | 3D "
             "| scale (ppm) | faces off their given plane at the truth (points, mean distance; "
             "from their true surface) | faces off their own surface | terrain cells off |",
             "|---" * 12 + "|"]
    for case, row in rows.items():
        judged = row.get("assignment_at_truth")
        if not judged:
            continue
        for key, label in (("refine", "refine's last"), ("fresh", f"at the truth, {threshold} m")):
            f = judged[key]
            off = own = cells = ""
            if key == "refine":
                off = "; ".join(f"{o['points']} on a face with normal {o['normal']}, "
                                f"{o['mean_m']:+.2f} m ({o['own_surface_m']:+.2f} m)"
                                for o in judged["off_faces"]) or "none"
                own = "; ".join(f"{o['points']} at {o['mean_m']:+.2f} m"
                                for o in judged["off_own_surface"]) or "none"
                cells = str(judged["terrain_cells_off"])
            lines.append(f"| {case} | {label} | {f['points']} | {f['faces']} | "
                         f"{f['rms'][0]:.3f} | {f['rms'][1]:.3f} | {f['rms'][2]:.3f} | "
                         f"{f['rms_3d']:.3f} | {f['scale_ppm']:.0f} | {off} | {own} | {cells} |")
    return lines


def preference_table(rows: dict) -> list[str]:
    lines = ["| case | refine's cameras (m) | tie points | within the threshold | share "
             "| RMS (m) | near score | faces | face score | the model prefers |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for case, r in rows.items():
        moved, true = r["truth_at_refine_pose"], r["truth"]
        better = [moved["near_score"] >= true["near_score"],
                  moved["face_score"] <= true["face_score"]]
        verdict = ("refine's pose" if all(better) else "the true pose" if not any(better)
                   else "refine's pose by the " + ("near" if better[0] else "face") + " score")
        for label, fit in (("true", true),
                           (f"true, at refine's pose (fit RMS {r['pose_fit_rms']:.3f} m)", moved),
                           ("refine's own", r["refine"])):
            lines.append(f"| {case} | {r['cameras_rms_3d']:.3f} | {label} | {fit['points']} | "
                         f"{fit['share']:.1%} | {fit['rms']:.3f} | {fit['near_score']:.3f} | "
                         f"{fit['faces']} | {fit['face_score']:.2f} | "
                         f"{verdict if fit is moved else ''} |")
    return lines


def started_at_truth_table(rows: dict) -> list[str]:
    lines = ["| case | GNSS | GNSS only: 3D | refine: E | N | U | 3D | verdict |",
             "|---|---|---|---|---|---|---|---|"]
    for case, r in rows.items():
        start = r["started_at_truth"]
        for label, cameras, gnss_only, verdict in (
                ("the workspace's (biased)", r["cameras"], r.get("gnss_only_rms_3d"), r["verdict"]),
                ("the true centres", start["cameras"], start["gnss_only"]["rms_3d"],
                 start["verdict"])):
            if verdict == "failed":
                verdict += " (the GNSS-only block handed back)"
            only = f"{gnss_only:.3f}" if gnss_only is not None else "-"
            lines.append(f"| {case} | {label} | {only} | {cameras['rms_x']:.3f} | "
                         f"{cameras['rms_y']:.3f} | {cameras['rms_z']:.3f} | "
                         f"{cameras['rms_3d']:.3f} | {verdict} |")
        apart = start["apart_rms"]
        lines.append(f"| {case} | the two results apart | | {apart[0]:.3f} | {apart[1]:.3f} | "
                     f"{apart[2]:.3f} | {float(np.sqrt(np.sum(np.square(apart)))):.3f} | |")
    return lines


#: How far `moved_truth_table` moves the true block along each axis (m).
MOVE_M = 0.3


def moved_truth_table(preferences: dict, blocks: dict, stores: dict, threshold: float
                      ) -> list[str]:
    """Near score / face score of the true block and of it moved by +-MOVE_M along E, N, U,
    against each case's given model (`stores`)."""
    moves = [(axis, sign) for axis in range(3) for sign in (1.0, -1.0)]
    lines = ["| case | true block | " + " | ".join(
        f"{'ENU'[axis]} {sign * MOVE_M:+.1f} m" for axis, sign in moves) + " |",
        "|---|---|" + "---|" * len(moves)]
    for case in preferences:
        store = stores[case]
        true = preferences[case]["truth"]
        cells = []
        for axis, sign in moves:
            shift = np.zeros(3)
            shift[axis] = sign * MOVE_M
            fit = model_fit(blocks[case][0] + shift, store, threshold)
            better = (fit["near_score"] > true["near_score"]) + (
                fit["face_score"] < true["face_score"])
            cells.append(f"{fit['near_score']:.3f} / {fit['face_score']:.2f}"
                         + (" (better)" if better == 2 else " (better by one)" if better else ""))
        lines.append(f"| {case} | {true['near_score']:.3f} / {true['face_score']:.2f} | "
                     + " | ".join(cells) + " |")
    return lines


def comparison(rows: dict, robustness: dict, sweeps: dict) -> list[str]:
    """Per case and direction with the given model: refine, GNSS only, the target and the
    floor; a target below the floor cannot be met by a fit that takes these planes as given.
    Last the planes-alone floors with each point weighted by its own precision, at the
    floor's window and at WIDE_WINDOW_M (`sweeps`: `threshold_sweep` per case)."""
    lines = ["| case | axis | fixed by | refine | GNSS only | target | floor per point "
             "| floor per face | target below both floors | per point, planes alone "
             "| per face, planes alone | precision per point, planes alone | precision per "
             f"face, planes alone | precision per point, {WIDE_WINDOW_M:g} m | precision per "
             f"face, {WIDE_WINDOW_M:g} m |", "|---" * 15 + "|"]
    for case, variants in rows.items():
        run = robustness.get(case, {})
        refined = (run.get("refine") or {}).get("cameras")
        gnss_only = (run.get("gnss_only") or {}).get("cameras")
        floor_ = variants.get("original")
        if not (refined and gnss_only and floor_):
            continue
        for axis, key in (("E", "rms_x"), ("N", "rms_y"), ("U", "rms_z")):
            fixed = (run.get("observability") or {}).get(axis, {})
            source = fixed.get("source", "?") + (" (one plane)" if fixed.get("one_plane") else "")
            point, face = floor_["per point"][key], floor_["per face"][key]
            if fixed.get("source") in ("planes", "both") and not fixed.get("one_plane"):
                target = min(TARGET_M, gnss_only[key] / TARGET_GAIN)
                below = "yes" if target < min(point, face) else "no"
                target = f"<= {target:.3f}"
            else:  # left to GNSS: no worse than GNSS only
                target, below = f"<= {gnss_only[key]:.3f}", "-"
            loose = [floor_.get(f"{w}, planes alone", {}).get(key, float("nan"))
                     for w in ("per point", "per face", "precision per point",
                               "precision per face")]
            wide = sweeps.get(case, {}).get(f"{WIDE_WINDOW_M:g}", {})
            loose += [wide.get(w, {}).get(axis, float("nan"))
                      for w in ("precision per point", "precision per face")]
            lines.append(f"| {case} | {axis} | {source} | {refined[key]:.3f} | "
                         f"{gnss_only[key]:.3f} | {target} | {point:.3f} | {face:.3f} | {below} "
                         "| " + " | ".join(f"{v:.3f}" for v in loose) + " |")
    return lines


@dataclasses.dataclass
class Runs:
    """What `main` measures, per case: the true block, the floors per model variant, the
    threshold sweep, the reassigning floors and (unless --no_refine) refine against the truth
    with the case's given model."""
    blocks: dict = dataclasses.field(default_factory=dict)
    rows: dict = dataclasses.field(default_factory=dict)
    sweeps: dict = dataclasses.field(default_factory=dict)
    reassigned: dict = dataclasses.field(default_factory=dict)
    preferences: dict = dataclasses.field(default_factory=dict)
    stores: dict = dataclasses.field(default_factory=dict)


FLOOR_TABLE = ["| case | model | points | faces | per point: X | Y | Z | 3D | per face: X | Y | Z "
               "| 3D | planes alone, per point: 3D | per face: 3D | precision, planes alone, "
               "per point: 3D | per face: 3D |", "|---" * 16 + "|"]


def floor_row(case: str, variant: str, f: dict) -> str:
    """One row of FLOOR_TABLE from a `floor` result."""
    p, q = f["per point"], f["per face"]
    loose = [f[f"{w}, planes alone"]["rms_3d"] for w in
             ("per point", "per face", "precision per point", "precision per face")]
    return (f"| {case} | {variant} | {f['points']} | {f['faces']} | "
            f"{p['rms_x']:.3f} | {p['rms_y']:.3f} | {p['rms_z']:.3f} | {p['rms_3d']:.3f} | "
            f"{q['rms_x']:.3f} | {q['rms_y']:.3f} | {q['rms_z']:.3f} | {q['rms_3d']:.3f} | "
            + " | ".join(f"{v:.3f}" for v in loose) + " |")


#: The row of the given model's floor with each tie point on the face whose true surface it
#: lies on (`own_surfaces`), however far the model's plane stands off it.
OWN_SURFACES = "original, own surfaces"

#: The floors of `own_surface_table`, planes alone: every point alike, each face once, each
#: point by its own precision (alike / each face once).
OWN_WEIGHTINGS = ("per point", "per face", "precision per point", "precision per face")


def own_surface_table(rows: dict, robustness: dict) -> list[str]:
    """Per case: refine's camera-centre RMS with the given model beside the planes-alone
    floors with each tie point on its own surface (`OWN_SURFACES`), per axis and 3D, and
    refine over the lower of the floors every point alike and each face once."""
    lines = ["| case | axis | refine | " + " | ".join(OWN_WEIGHTINGS)
             + " | refine / lower of per point and per face |", "|---" * 7 + "|"]
    for case, variants in rows.items():
        refined = ((robustness.get(case, {}).get("refine") or {}).get("cameras"))
        own = variants.get(OWN_SURFACES)
        if not (refined and own):
            continue
        for axis, key in (("E", "rms_x"), ("N", "rms_y"), ("U", "rms_z"), ("3D", "rms_3d")):
            floors = [own[f"{w}, planes alone"][key] for w in OWN_WEIGHTINGS]
            lines.append(f"| {case} | {axis} | {refined[key]:.3f} | "
                         + " | ".join(f"{v:.3f}" for v in floors)
                         + f" | {refined[key] / min(floors[:2]):.2f} |")
    return lines


def case_workspace(case: str) -> Path:
    """A robustness case by name ("orbit"), any other generated workspace by its path under
    workspaces/generated ("long/Scn3")."""
    return GENERATED / case if "/" in case else ROBUST / case


def run_case(case: str, args: argparse.Namespace, runs: Runs, table: list[str]) -> None:
    """Everything `main` measures for one case, into `runs` (rows into `table`), printed as it
    comes."""
    workspace, gnss_sigma = case_workspace(case), np.array(args.gnss_sigma)
    block = runs.blocks[case] = true_block(workspace)
    covariances = point_covariances(workspace, block[1])
    for variant in args.variants:
        f = floor(workspace, variant, block, args.threshold, gnss_sigma, covariances)
        runs.rows.setdefault(case, {})[variant] = f
        table.append(floor_row(case, variant, f))
        print(table[-1], flush=True)
    own = floor(workspace, "original", block, args.threshold, gnss_sigma, covariances,
                by_surface=True)
    if own is not None:
        runs.rows[case][OWN_SURFACES] = own
        table.append(floor_row(case, OWN_SURFACES, own))
        print(table[-1], flush=True)
    runs.sweeps[case] = threshold_sweep(workspace, block, gnss_sigma, covariances)
    print("\n".join(threshold_table({case: runs.sweeps[case]})[2:]), flush=True)
    print("\n".join(precision_table({case: runs.sweeps[case]})[2:]), flush=True)
    runs.reassigned[case] = reassigned_from_truth(workspace, block, args.threshold, gnss_sigma)
    print("\n".join(reassigned_table({case: runs.reassigned[case]})[2:]), flush=True)
    if not args.no_refine:
        workspace_inputs = inputs(workspace)
        runs.stores[case] = workspace_inputs[1]
        runs.preferences[case] = refine_against_truth(workspace, workspace_inputs, block,
                                                      args.threshold, gnss_sigma)
        print("\n".join(preference_table({case: runs.preferences[case]})[2:]), flush=True)


def floor_lines(args: argparse.Namespace, runs: Runs, table: list[str], robustness: dict,
                commit: str) -> list[str]:
    """model_floor.md up to the reassigning floors: the module text, the floors per model
    variant, beside refine and the target, by threshold and each point by its precision."""
    return [
        "# The floor a model's errors set: the true block fitted onto the model's planes", "",
        "Produced by", "", "    " + " ".join([".venv/bin/python benchmarks/model_floor.py",
                                                 *sys.argv[1:]]), "",
        __doc__.split("\n\n", 1)[1].split("\nWrites")[0].strip(), "",
        f"Robustness workspaces (workspaces/generated/robust), code {commit}; true tie "
        f"points assigned directly at {args.threshold} m. Camera-centre RMS (m) after the "
        "fit, per axis and 3D:", "", *table, "",
        OWN_SURFACES_TEXT, "", *own_surface_table(runs.rows, robustness), "",
        "With the given (`original`) model, beside refine's own camera-centre RMS and the "
        "GNSS-only adjustment of the same block (the `robustness` section of "
        "scenarios.json), the per-direction target of a direction the planes fix (<= 0.25 m "
        "and >= 10x better than GNSS only); last the planes-alone floors with each point "
        f"weighted by its own precision (below) at {args.threshold} m and at "
        f"{WIDE_WINDOW_M:g} m:", "", *comparison(runs.rows, robustness, runs.sweeps), "",
        "The planes-alone floors of the given model with the truth assigned at other "
        "thresholds (m): where a face's model plane stands further off its surface than "
        "the threshold, the assignment at the truth keeps only the points that happen to "
        "lie near the plane, or none, and so leaves out the faces that would pull the "
        "block most; at 1 m every face keeps all its points. A method away from the "
        "truth cannot copy that cut:", "", *threshold_table(runs.sweeps), "",
        PRECISION_TEXT.format(sigma_px=SIGMA_PX, sigma_dtp=SIGMA_DTP,
                              imprecise=IMPRECISE_SIGMA, wide=WIDE_WINDOW_M), "",
        *precision_table(runs.sweeps), ""]


#: What the `own surfaces` floors mean (model_floor.md).
OWN_SURFACES_TEXT = (
    f"`{OWN_SURFACES}`: each true tie point on the face whose true surface it lies on, found "
    "against the `corrected` model (the true surfaces' planes) with the same window and carried "
    "to the same face of the given model, whose planes stay as they are however far they stand "
    "off their points. The other rows assign each point to the nearest plane of their own "
    "model: where a given plane stands further than the window off its surface (its 0.2 m "
    "shift and 0.5 deg tilt over a long wall), that cut keeps only the points that happen to "
    "lie near the wrong plane and so drops the faces that would pull the block most, which no "
    "method away from the truth can copy. This floor is what a method that puts every point "
    "on its own surface and trusts the given planes inherits from the model. With the given "
    "model, refine's camera-centre RMS (the `robustness` section of scenarios.json) beside "
    "these floors (planes alone), per axis and 3D:")


#: What the `precision` floors mean (model_floor.md).
PRECISION_TEXT = (
    "Each tie point weighted by its own precision. The floors above take every true tie point "
    "as exactly known. In the adjustment a tie point is known only as well as its rays fix it: "
    "one seen from far away along nearly parallel rays is moved along them onto its plane and "
    "holds the block hardly at all. The `precision` floors weight each point's distance to its "
    "plane by 1 / (sigma_dTP^2 + s_n^2), sigma_dTP = {sigma_dtp:g} m, s_n the point's own "
    "position sigma along its face's normal from its track at the truth: the 3x3 covariance "
    "(sum_i J_i^T J_i / sigma_px^2)^-1 of the point from the rays of the images that observe "
    "it (sigma_px = {sigma_px:g} px, J_i the projection's derivative), projected on the "
    "normal. `per face` divides these weights by the face's number of points, as above. "
    "`imprecise`: points with s_n above {imprecise:g} m (less than a tenth of an exact point's "
    "weight). The window at the truth matters as much: refine's final one cuts a face whose "
    "model plane is tilted (0.5 deg in these models) where its visible part reaches far from "
    "the face's centroid, where refine, away from the truth, takes it whole; {wide:g} m (wide) "
    "adds the tilt over ~40 m, the farthest a visible point lies from its face's centroid in "
    "these blocks. Camera-centre RMS (m) after the fit with the planes-alone priors, per axis "
    "and 3D, and the fit's scale change; every point alike: the same fit unweighted, as in the "
    "table above:")


def refine_lines(args: argparse.Namespace, runs: Runs) -> list[str]:
    """model_floor.md's tables of refine against the truth (empty with --no_refine)."""
    if not runs.preferences:
        return []
    return [
        "Which pose of the block the given model prefers: the true block at its true "
        "pose and at the pose refine gave it (fit RMS: what is left of the similarity "
        "between the true cameras and refine's, its bending), and refine's own tie "
        f"points; tie points assigned directly at {args.threshold} m (refine's "
        "cameras: its camera-centre RMS 3D against the truth in this run):", "",
        *preference_table(runs.preferences), "",
        f"The true block moved by {MOVE_M} m along each axis, scored the same way "
        "(near score / face score; better: higher near score and lower face score "
        "than the true block's):", "",
        *moved_truth_table(runs.preferences, runs.blocks, runs.stores, args.threshold), "",
        "Refine started at the truth: the true projection centres as GNSS (sigma "
        f"{'/'.join(f'{v:g}' for v in args.gnss_sigma)} m, no bias), against refine "
        "with the workspace's GNSS (3-5 m bias); camera-centre RMS against the truth "
        "(m) of refine's own block (also where its verdict handed back the GNSS-only "
        "one), and the two results' cameras apart:", "",
        *started_at_truth_table(runs.preferences), "",
        "Refine's last assignment judged at the truth: the SfM block moved onto the "
        "true cameras by a similarity, its tie points then fitted onto the planes "
        "they were assigned to (every point alike, the planes alone, as `per point, "
        "planes alone` above), against the same fit with the points assigned afresh "
        "at the truth; and the faces of refine's assignment whose points lie more "
        f"than {OFF_FACE_M} m on average (at least {OFF_FACE_POINTS} points) from their "
        "given plane at the truth (in brackets: from the face's true surface, its plane in "
        "the `corrected` model), and from their own true surface. A face far from its "
        "given plane but on its true surface is the model's plane error (0.2 m shift and "
        "0.5 deg tilt per face), not a wrong assignment; a face far from its own surface "
        "holds points of another surface. Terrain cells (their offsets are unknowns of "
        "the adjustment) are only counted:", "",
        *assignment_table(runs.preferences, args.threshold), ""]


def reassigned_lines(runs: Runs) -> list[str]:
    """model_floor.md's table of the reassigning floors."""
    return [
        "The floor of a method that assigns again wherever the block stands: the true "
        "block of the given model, assigned and fitted (with the priors at the truth of "
        f"the first table) {ICP_ROUNDS} times from its true pose, as refine's loop does; "
        "camera-centre RMS 3D (m) where it settles. `at the plane`: refine's window "
        "(|distance| below the threshold); `centred`: the window centred on the median "
        f"offset of the points within {CENTRE_BAND} m of each face, so that a face's points "
        "are taken from both sides of where they lie and the assignment does not follow "
        "the block. `face units`: each face's offset and tilt as random effects (prior "
        f"{SIGMA_FACE_UNIT} m at its edges) estimated with the similarity, the window "
        "centred on where the last fit put each face's surface, the scale held to 1 % "
        "(as the other columns) or 0.1 %. In brackets the fit's scale change (ppm): "
        "with the faces free to move and tilt, shrinking the block shortens every "
        "point's lever about its face and lowers the residuals of detail the model "
        "does not hold, so the scale must come from elsewhere. Where these lie above "
        "the floors of the first table, the truncation of a face's points at the truth "
        "(which a method away from the truth cannot copy) made the floor:", "",
        *reassigned_table(runs.reassigned), ""]


#: What the check-point table of other workspaces shows (model_floor_long.md).
CHECKPOINT_TEXT = (
    "Check points (m, RMS 3D) of these workspaces: refine's (`refine_a` in scenarios.json), "
    "what of it remains after the best similarity onto the truth (the block's shape), and the "
    "planes-alone floors on the same check points. The floors move the true block rigidly: "
    "they hold no error of the block's shape, which in a long SfM block (its drift along the "
    "sequence) refine must remove as well.")


def checkpoint_table(rows: dict, everything: dict) -> list[str]:
    """Per generated workspace other than the robustness ones ("long/Scn3"): refine's
    check-point RMS 3D (its `refine_a` run in scenarios.json's section of that sequence)
    beside the planes-alone floors on the same check points, nearest plane and own surface,
    and refine over the lower own-surface floor of every point alike and each face once."""
    lines = ["| case | refine (check points) | refine after the best similarity "
             "| nearest plane: per point | per face | own surface: per point | per face "
             "| refine / lower own-surface floor |", "|---" * 8 + "|"]
    for case, variants in rows.items():
        if "/" not in case or OWN_SURFACES not in variants:
            continue
        section, name = case.split("/", 1)
        refined = (everything.get(section, {}).get(name, {}).get("refine_a") or {})
        floors = [variants[key][f"{w}, planes alone"].get("checkpoints_3d", float("nan"))
                  for key in ("original", OWN_SURFACES) for w in ("per point", "per face")]
        ratio = refined.get("rms_3d", float("nan")) / min(floors[2:])
        lines.append(f"| {case} | {refined.get('rms_3d', float('nan')):.3f} | "
                     f"{refined.get('rms_3d_after_helmert', float('nan')):.3f} | "
                     + " | ".join(f"{v:.3f}" for v in floors) + f" | {ratio:.2f} |")
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="+", default=["drive", "orbit", "strip", "short"],
                        help="robustness cases, or workspaces under workspaces/generated "
                             "(long/Scn3)")
    parser.add_argument("--seeds", nargs="+", type=int, default=[],
                        help="each robustness case of --cases also built and measured at these "
                             "seeds (other model errors, GNSS and SfM noise: other "
                             "realisations of the same block), with a table of refine against "
                             "its floors per realisation")
    parser.add_argument("--variants", nargs="+", default=["original", "corrected", "detailed"])
    parser.add_argument("--threshold", type=float, default=0.45)
    parser.add_argument("--gnss_sigma", nargs=3, type=float, default=[3.0, 3.0, 5.0])
    parser.add_argument("--no_refine", action="store_true",
                        help="leave out the fit of refine's block against the true one")
    parser.add_argument("--summary_only", action="store_true",
                        help="only rewrite the summary over the realisations at the end of "
                             "the results' markdown from their json (after a run with --seeds)")
    parser.add_argument("--results", default="model_floor",
                        help="name of the results (benchmarks/results/NAME.md and .json, and "
                             "the section of scenarios.json)")
    args = parser.parse_args()
    if args.summary_only:
        write_summary(args.results)
        return
    runs, table = Runs(), list(FLOOR_TABLE)
    print("\n".join(table))
    for case in with_seeds(args.cases, args.seeds):
        run_case(case, args, runs, table)
    everything = update_json(RESULTS / "scenarios.json", [args.results], runs.rows)
    if runs.preferences:
        update_json(RESULTS / "scenarios.json", [
            "model_preference" if args.results == "model_floor"
            else f"{args.results}_preference"], runs.preferences)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT,
                            capture_output=True, text=True).stdout.strip()
    robustness = everything.get("robustness", {})
    checks = checkpoint_table(runs.rows, everything)
    lines = (floor_lines(args, runs, table, robustness, commit)
             + ([CHECKPOINT_TEXT, "", *checks, ""] if len(checks) > 2 else [])
             + reassigned_lines(runs) + refine_lines(args, runs)
             + (realisation_lines(args, runs) if args.seeds else []))
    (RESULTS / f"{args.results}.md").write_text("\n".join(lines))
    floors = floor_summary(runs.rows, robustness if args.results == "model_floor" else {},
                           runs.sweeps, runs.preferences)
    for case, found in runs.sweeps.items():
        if case in floors:
            floors[case]["floors_by_threshold"] = found
    for case, found in runs.reassigned.items():
        if case in floors:
            floors[case]["reassigned_from_truth_3d"] = {k: v["rms_3d"] for k, v in found.items()}
    (RESULTS / f"{args.results}.json").write_text(json.dumps(floors, indent=1) + "\n")
    if args.seeds:
        write_summary(args.results)


def with_seeds(cases: list[str], seeds: list[int]) -> list[str]:
    """`cases`, each robustness case followed by its workspaces at `seeds` (built where
    missing), named as generated workspaces ("robust/strip-seed1")."""
    out = []
    for case in cases:
        out.append(case)
        if case in ROBUST_CASES:
            for seed in seeds:
                build_robust_workspace(case, seed=seed)
                out.append(f"robust/{case}-seed{seed}")
    return out


#: The tolerance against a realisation's floor: a refine within this factor of the lower of
#: its two planes-alone floors counts as at the floor its model allows (30 % above it).
AT_FLOOR_FACTOR = 1.3


def realisation_lines(args: argparse.Namespace, runs: Runs) -> list[str]:
    """model_floor.md's table of refine against its floors per realisation of each case (its
    own seed and `--seeds`): camera-centre RMS 3D and in plan (E, N) of refine's run in
    `refine_against_truth`, the planes-alone floors at the window and on the points' own
    surfaces, and refine over the lower of each pair."""
    lines = [
        "## Refine against its floors per realisation", "",
        "Each robustness case at its own seed and "
        f"at seeds {', '.join(map(str, args.seeds))} (other plane errors of the given model, "
        "GNSS and SfM noise, the same city and flight). Camera-centre RMS (m), 3D and in plan "
        f"(E, N); floors planes alone at the {args.threshold:g} m window and on the points' "
        "own surfaces, per point / per face; last, refine over the lower floor of each pair "
        f"(at most {AT_FLOOR_FACTOR} counts as at the floor). Where one realisation lies far "
        "above its window floor and the others do not, that floor's cut at the truth (which "
        "keeps only the points that happen to lie near a plane standing off its surface) "
        "favoured it, not the method:", "",
        "| case | refine 3D | refine plan | window: per point / per face (3D) | plan | "
        "own surfaces: per point / per face (3D) | plan | refine / window floor: 3D | plan | "
        "refine / own-surfaces floor: 3D | plan |",
        "|---|---|---|---|---|---|---|---|---|---|---|"]

    def plan(fit: dict) -> float:
        return float(np.hypot(fit["E"], fit["N"]))

    for case, preference in runs.preferences.items():
        variants = runs.rows.get(case, {})
        if "original" not in variants or OWN_SURFACES not in variants:
            continue
        cameras = preference["cameras"]
        refined = {"3d": cameras["rms_3d"], "plan": float(np.hypot(cameras["rms_x"],
                                                                    cameras["rms_y"]))}
        cells, ratios = [], []
        for key in ("original", OWN_SURFACES):
            fits = [compact(variants[key][f"{w}, planes alone"])
                    for w in ("per point", "per face")]
            floors = {"3d": [f["3d"] for f in fits], "plan": [plan(f) for f in fits]}
            cells += [" / ".join(f"{v:.3f}" for v in floors[k]) for k in ("3d", "plan")]
            ratios += [f"{refined[k] / min(floors[k]):.2f}" for k in ("3d", "plan")]
        lines.append(f"| {case} | {refined['3d']:.3f} | {refined['plan']:.3f} | "
                     + " | ".join(cells + ratios) + " |")
    return lines + [""]


SUMMARY_HEADER = "## Refine against its floors over the realisations"


def realisation_summary(floors: dict, preferences: dict) -> list[str]:
    """model_floor.md's summary over the realisations of each case (`floors`: the results'
    json, `preferences`: scenarios.json's `<results>_preference`, which holds each run's
    verdict): the medians of refine and of the planes-alone floors (3D and plan), and how many
    realisations lie within AT_FLOOR_FACTOR of the lower floor of each pair. One realisation's
    floor is one draw of the model's errors, and so is refine's result: the medians compare
    the method with the floor over the draws, where a single realisation's ratio scatters
    with both. A realisation refine refused ("failed", the GNSS-only block handed back) is
    counted apart, not in the medians."""
    cases: dict[str, list[str]] = {}
    for name in floors:
        cases.setdefault(name.split("/")[-1].split("-seed")[0], []).append(name)
    lines = [
        SUMMARY_HEADER, "",
        "Medians over each case's realisations (its own seed and the others above) of "
        "refine's camera-centre RMS and of its planes-alone floors (the lower of per point "
        "and per face, at the window, on the points' own surfaces, and there with each point "
        "weighted by its own precision as the adjustment weighs it: `precision`), 3D and in "
        "plan (E, N), m; `within`: realisations whose refine lies within "
        f"{AT_FLOOR_FACTOR}x that floor; `refused`: realisations whose verdict was \"failed\" "
        "(the GNSS-only block handed back; left out of the medians):", "",
        "| case | realisations | refused | refine: 3D | plan | window floor: 3D | plan "
        "| own-surfaces floor: 3D | plan | precision: 3D | plan "
        "| refine / window floor: 3D | plan | refine / own-surfaces floor: 3D | plan "
        "| refine / precision: 3D | plan "
        "| within: window (3D / plan) | own surfaces | precision |",
        "|---" * 20 + "|"]
    for case, names in cases.items():
        kept = [n for n in names
                if (preferences.get(n) or {}).get("verdict") != "failed"]
        if len(names) < 2 or not kept:
            continue
        floor_keys = ("w3", "wp", "o3", "op", "p3", "pp")
        values = {key: [] for key in ("r3", "rp", *floor_keys)}
        within = {key: 0 for key in floor_keys}
        for name in kept:
            row = floors[name]
            axes = row["per_axis"]
            columns = axes["columns"]

            def axis(column: str, ax: str) -> float:
                return axes[ax][columns.index(column)]

            refine = [axis("refine", ax) for ax in "ENU"]
            window = [[axis(c, ax) for ax in "ENU"]
                      for c in ("floor_planes_per_point", "floor_planes_per_face")]
            own, precise = ([[row[f"floor_own_surfaces_{w}_axes"][ax] for ax in "ENU"]
                             for w in pair] for pair in (("per_point", "per_face"),
                                                         ("precision_per_point",
                                                          "precision_per_face")))
            got = {"r3": np.linalg.norm(refine), "rp": np.hypot(*refine[:2]),
                   "w3": min(np.linalg.norm(f) for f in window),
                   "wp": min(np.hypot(*f[:2]) for f in window),
                   "o3": min(np.linalg.norm(f) for f in own),
                   "op": min(np.hypot(*f[:2]) for f in own),
                   "p3": min(np.linalg.norm(f) for f in precise),
                   "pp": min(np.hypot(*f[:2]) for f in precise)}
            for key, value in got.items():
                values[key].append(float(value))
            for key in within:
                within[key] += got["r" + key[1]] <= AT_FLOOR_FACTOR * got[key]
        m = {key: float(np.median(v)) for key, v in values.items()}
        n = len(kept)
        lines.append(
            f"| {case} | {len(names)} | {len(names) - n} | {m['r3']:.3f} | {m['rp']:.3f} | "
            + " | ".join(f"{m[k]:.3f}" for k in floor_keys) + " | "
            + " | ".join(f"{m['r' + k[1]] / m[k]:.2f}" for k in floor_keys) + " | "
            + " | ".join(f"{within[a]} / {within[b]} of {n}"
                         for a, b in (("w3", "wp"), ("o3", "op"), ("p3", "pp"))) + " |")
    return lines + [""]


def write_summary(results: str) -> None:
    """Rewrite the summary over the realisations at the end of benchmarks/results/RESULTS.md
    from RESULTS.json and scenarios.json, without measuring anything again."""
    floors = json.loads((RESULTS / f"{results}.json").read_text())
    everything = json.loads((RESULTS / "scenarios.json").read_text())
    preferences = everything.get(f"{results}_preference", {})
    path = RESULTS / f"{results}.md"
    text = path.read_text().split(SUMMARY_HEADER)[0].rstrip("\n")
    path.write_text(text + "\n\n" + "\n".join(realisation_summary(floors, preferences)))


def own_surface_summary(own: dict | None) -> dict:
    """model_floor.json's keys of the `OWN_SURFACES` floors (planes alone): 3D and per axis."""
    if own is None:
        return {}
    out = {}
    for w in OWN_WEIGHTINGS:
        fit = compact(own[f"{w}, planes alone"])
        key = "floor_own_surfaces_" + w.replace(" ", "_")
        out[key + "_3d"] = fit["3d"]
        out[key + "_axes"] = {a: fit[a] for a in "ENU"}
    return out


def floor_summary(rows: dict, robustness: dict, sweeps: dict, preferences: dict | None = None,
                  variant: str = "original") -> dict:
    """model_floor.json: per case, the planes-alone floors of the given model (every point
    alike, each face once, each point weighted by its own precision at the floor's window and
    at WIDE_WINDOW_M; camera-centre RMS 3D and per axis) and refine's own result with its
    defaults on that model (the `robustness` section of scenarios.json; failing that this
    run's own refine, `preferences`; None if neither ran)."""
    out = {}
    for case, variants in rows.items():
        if variant not in variants:
            continue
        f = variants[variant]
        fits = [compact(f[f"{w}, planes alone"]) for w in
                ("per point", "per face", "precision per point", "precision per face")]
        wide = sweeps[case][f"{WIDE_WINDOW_M:g}"]
        fits += [wide["precision per point"], wide["precision per face"]]
        cameras = ((robustness.get(case, {}).get("refine") or {}).get("cameras")
                   or (preferences or {}).get(case, {}).get("cameras") or {})
        refined = {"E": cameras.get("rms_x"), "N": cameras.get("rms_y"),
                   "U": cameras.get("rms_z")}
        out[case] = {
            "floor_planes_per_point_3d": fits[0]["3d"],
            "floor_planes_per_face_3d": fits[1]["3d"],
            "floor_precision_per_point_3d": fits[2]["3d"],
            "floor_precision_per_face_3d": fits[3]["3d"],
            "floor_precision_wide_per_point_3d": fits[4]["3d"],
            "floor_precision_wide_per_face_3d": fits[5]["3d"],
            "refine_3d": cameras.get("rms_3d"),
            # Existing positions first: floor per point, per face, refine; then the rest.
            "per_axis": {**{a: [fits[0][a], fits[1][a], refined[a], *(x[a] for x in fits[2:])]
                            for a in "ENU"},
                         "columns": ["floor_planes_per_point", "floor_planes_per_face",
                                     "refine", "floor_precision_per_point",
                                     "floor_precision_per_face",
                                     "floor_precision_wide_per_point",
                                     "floor_precision_wide_per_face"]},
            "precision_scale_ppm": {"per_point": fits[2]["scale_ppm"],
                                    "per_face": fits[3]["scale_ppm"],
                                    "wide_per_point": fits[4]["scale_ppm"],
                                    "wide_per_face": fits[5]["scale_ppm"]},
            **own_surface_summary(variants.get(OWN_SURFACES)),
            "imprecise_points": f["imprecise_points"], "wide_window_m": WIDE_WINDOW_M,
            "sigma_px": SIGMA_PX, "refine_code": robustness.get(case, {}).get("code"),
        }
    return out

if __name__ == "__main__":
    main()
