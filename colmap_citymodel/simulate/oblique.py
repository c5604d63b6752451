"""A simulated oblique aerial block: a five-head camera (one nadir, four oblique heads tilted
45 deg forward, backward, left and right; Mulder 3.2) flown in parallel strips over a real
CityGML tile, with GNSS/IMU exterior orientations and their noise.

What it writes into the workspace (a new directory):

- ``database.db``: one camera per head (as ``colmap feature_extractor --ImageReader.
  single_camera_per_folder 1`` does), every image with its keypoints (true projections with
  `pixel_noise`, unmatched keypoints added) and a trivial rig and frame per image; no matches.
- ``eo.txt``: per exposure the GNSS antenna position (model CRS, white noise `eo_sigma`) and the
  body attitude omega, phi, kappa (white noise `attitude_sigma_deg`), with the position sigmas;
  ``rig.json``: the heads with Mulder's lever arms (Table 3.3), boresight angles and the GNSS
  antenna 1.2 m above the body.
- ``truth/``: true poses and tie points (COLMAP text model, local frame), ``origin.txt``,
  ``observations.npz`` (which image sees which point with which keypoint and viewing ray: the
  matcher below reads it), ``simulation.json``.

`simulate_matching` is the simulated stand-in for ``colmap matches_importer --match_type
pairs``: for each listed pair it writes the keypoint correspondences of the points both images
see with viewing rays less than `max_match_angle_deg` apart (descriptors do not match across
larger viewpoint changes: the forward and the backward head never match, nadir and oblique do),
then runs COLMAP's own geometric verification (``pycolmap.verify_matches``) on them.

One pinhole camera for all heads (the same focal length): Mulder's oblique heads have longer
lenses than the nadir one; the oblique images' ground resolution here is coarser than theirs.
"""

from __future__ import annotations

import json
import logging
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..block.eo import Head, RigSpec, angles_opk, block_poses, rotation_opk
from ..errors import InputError
from .flight import Flight
from .observations import sample_surface_points, visibility
from .scenario import ObservationOptions
from .scene import DetailOptions, GroundModel, build_true_scene

logger = logging.getLogger(__name__)

#: Heads: name, boresight (omega, phi, kappa, degrees, in the body frame whose y axis points
#: along the flight), lever arm (m; Mulder Table 3.3, mm -> m).
HEADS = (
    ("N", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    ("F", (45.0, 0.0, 0.0), (-0.106878, -0.099972, -0.129667)),
    ("B", (-45.0, 0.0, 0.0), (-0.106712, -0.021692, -0.007892)),
    ("L", (0.0, 45.0, 0.0), (-0.035468, -0.086232, 0.005913)),
    ("R", (0.0, -45.0, 0.0), (-0.115159, -0.085854, -0.144906)),
)
GNSS_LEVER_ARM = (0.0, 0.0, 1.2)


@dataclass
class ObliqueOptions:
    citymodel: str = ""
    """CityGML/CityJSON file of the buildings (model CRS = the file's)."""
    centre: tuple[float, float] | None = None
    """Block centre in the model CRS (default: the model's bounding box centre)."""
    strips: int = 3
    strip_spacing: float = 100.0
    strip_length: float = 600.0
    exposure_spacing: float = 50.0
    flying_height: float = 250.0
    """Metres above the model's lowest vertex."""
    width: int = 4000
    height: int = 3000
    focal: float = 5000.0
    points_per_m2: float = 0.03
    detection_probability: float = 0.9
    pixel_noise: float = 0.5
    unmatched_ratio: float = 0.2
    max_distance: float = 700.0
    max_incidence_deg: float = 80.0
    max_match_angle_deg: float = 50.0
    eo_sigma: tuple[float, float, float] = (0.05, 0.05, 0.10)
    attitude_sigma_deg: float = 0.005
    aircraft_attitude_deg: float = 1.0
    """Sigma of the true roll and pitch of the aircraft (deg) and of its crab angle."""
    seed: int = 1


def _exposures(options: ObliqueOptions, centre_local: np.ndarray, z: float, rng
               ) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Exposure ids, true body origins (local) and true R_world_from_body (opk body frame,
    y along the flight)."""
    ids, origins, rotations = [], [], []
    xs = np.arange(-options.strip_length / 2, options.strip_length / 2 + 1e-6,
                   options.exposure_spacing)
    for s in range(options.strips):
        y = (s - (options.strips - 1) / 2) * options.strip_spacing
        east = s % 2 == 0
        for k, x in enumerate(xs if east else xs[::-1]):
            ids.append(f"s{s}e{k:02d}")
            origins.append(centre_local + [x, y, 0.0])
            kappa = -90.0 if east else 90.0
            noise = rng.normal(0.0, options.aircraft_attitude_deg, 3)
            rotations.append(rotation_opk(noise[0], noise[1], kappa + noise[2]))
    origins = np.asarray(origins)
    origins[:, 2] = z
    return ids, origins, np.asarray(rotations)


def rig_spec(camera: dict | None = None) -> RigSpec:
    heads = [Head(name, f"{name}/{{exposure}}.jpg", np.asarray(lever, float),
                  np.asarray(bore, float), camera) for name, bore, lever in HEADS]
    return RigSpec(heads, 0, np.asarray(GNSS_LEVER_ARM, float))


def rig_dict(camera: dict | None = None) -> dict:
    heads = []
    for name, bore, lever in HEADS:
        head = {"name": name, "image_name": f"{name}/{{exposure}}.jpg",
                "lever_arm": list(lever), "boresight": list(bore)}
        if camera is not None:
            head["camera"] = camera
        heads.append(head)
    heads[0]["reference"] = True
    return {"heads": heads, "gnss_lever_arm": list(GNSS_LEVER_ARM)}


def true_scene(options: ObliqueOptions, store, centre: np.ndarray):
    """The true scene under the block (local frame of `store`): the buildings with
    generalisation effects and terrain wherever the heads look; deterministic for a seed."""
    ground = GroundModel(store)
    step = 40.0
    half = np.r_[options.strip_length / 2, (options.strips - 1) / 2 * options.strip_spacing]
    reach = options.flying_height * 1.6
    gx, gy = np.meshgrid(np.arange(-half[0] - reach, half[0] + reach + step, step),
                         np.arange(-half[1] - reach, half[1] + reach + step, step))
    roi = np.c_[gx.ravel() + centre[0], gy.ravel() + centre[1]]
    roi = np.c_[roi, ground(roi)]
    return build_true_scene(store, DetailOptions(tree_spacing=0.0, car_spacing=0.0),
                            options.seed, roi_centres=roi, roi_radius=step, ground=ground)


def block_centre(options: ObliqueOptions, store) -> np.ndarray:
    """The block centre in the store's local frame (z = 0)."""
    if options.centre is not None:
        return np.r_[np.asarray(options.centre, float) - store.origin[:2], 0.0]
    lo, hi = store.vertices.min(0), store.vertices.max(0)
    return np.r_[(lo[:2] + hi[:2]) / 2, 0.0]


def simulate_oblique_block(options: ObliqueOptions, output_path, *, progress: bool = False
                           ) -> dict:
    """Build the workspace described in the module docstring; returns its statistics."""
    import pycolmap

    from ..citymodel.read import read_city_model
    from ..files import atomic_directory

    if not options.citymodel:
        raise InputError("the oblique simulation needs a city model file")
    t0 = time.perf_counter()
    rng = np.random.default_rng([options.seed, 1])
    store = read_city_model(options.citymodel)
    origin = store.origin
    centre = block_centre(options, store)
    z = store.vertices[:, 2].min() + options.flying_height
    ids, body_origin, body_rot = _exposures(options, centre, z, rng)
    rig = rig_spec()
    # true antenna positions: body origin + R a
    antenna = body_origin + np.einsum("eij,j->ei", body_rot, rig.gnss_lever_arm)
    poses = block_poses(rig, ids, antenna, body_rot)
    num_e, num_h = len(ids), len(rig.heads)
    names = [rig.heads[h].image(e) for e in ids for h in range(num_h)]
    centres = poses.centres.reshape(-1, 3)
    rotations = poses.cam_rotations.reshape(-1, 3, 3)
    flight = Flight(names, centres, rotations, np.arange(len(names), dtype=float),
                    options.width, options.height, options.focal)

    scene = true_scene(options, store, centre)
    raycaster = scene.raycasting_scene()
    obs_opt = ObservationOptions(points_per_m2=options.points_per_m2,
                                 max_distance=options.max_distance,
                                 max_incidence_deg=options.max_incidence_deg,
                                 pixel_noise=options.pixel_noise)
    pts, tri = sample_surface_points(scene, options.points_per_m2,
                                     np.random.default_rng([options.seed, 2]))
    p_idx, f_idx, uv, ray = visibility(flight, pts, scene.normals[tri], raycaster, obs_opt,
                                       progress)
    detected = rng.random(len(p_idx)) < options.detection_probability
    p_idx, f_idx, uv, ray = p_idx[detected], f_idx[detected], uv[detected], ray[detected]
    views = np.bincount(p_idx, minlength=len(pts))
    seen = views[p_idx] >= 2
    p_idx, f_idx, uv, ray = p_idx[seen], f_idx[seen], uv[seen], ray[seen]
    noisy = uv + rng.normal(0.0, options.pixel_noise, uv.shape)
    noisy[:, 0] = np.clip(noisy[:, 0], 0.0, options.width - 1e-3)
    noisy[:, 1] = np.clip(noisy[:, 1], 0.0, options.height - 1e-3)
    keypoints, kp_index = [], np.zeros(len(p_idx), np.int64)
    for k in range(len(names)):
        mine = np.flatnonzero(f_idx == k)
        extra_n = int(round(options.unmatched_ratio * len(mine)))
        extra = np.c_[rng.uniform(0, options.width, extra_n),
                      rng.uniform(0, options.height, extra_n)]
        allkp = np.concatenate([noisy[mine], extra])
        perm = rng.permutation(len(allkp))
        inverse = np.empty_like(perm)
        inverse[perm] = np.arange(len(perm))
        kp_index[mine] = inverse[:len(mine)]
        keypoints.append(allkp[perm])

    # the observed exterior orientation
    eo_antenna = antenna + rng.normal(0.0, 1.0, antenna.shape) * np.asarray(options.eo_sigma)
    eo_angles = np.array([angles_opk(r) + rng.normal(0.0, options.attitude_sigma_deg, 3)
                          for r in body_rot])

    with atomic_directory(output_path) as tmp:
        out = Path(tmp)
        camera = {"model": "PINHOLE", "width": options.width, "height": options.height,
                  "params": [options.focal, options.focal, options.width / 2,
                             options.height / 2]}
        (out / "rig.json").write_text(json.dumps(rig_dict(), indent=2))
        lines = [f"# exposure X Y Z omega phi kappa sX sY sZ ({store.crs.label}; GNSS antenna, "
                 "body attitude in degrees)"]
        for e, exposure in enumerate(ids):
            x, y, zz = eo_antenna[e] + origin
            o, p, k = eo_angles[e]
            sx, sy, sz = options.eo_sigma
            lines.append(f"{exposure} {x:.4f} {y:.4f} {zz:.4f} {o:.6f} {p:.6f} {k:.6f} "
                         f"{sx} {sy} {sz}")
        (out / "eo.txt").write_text("\n".join(lines) + "\n")
        # database: a camera per head (folder), images, keypoints, trivial rigs and frames
        db = pycolmap.Database.open(str(out / "database.db"))
        try:
            cam_ids, rig_ids = [], []
            for _ in range(num_h):
                cam = pycolmap.Camera(model="PINHOLE", width=options.width,
                                      height=options.height, params=camera["params"])
                cam.has_prior_focal_length = True
                cam_ids.append(db.write_camera(cam))
                trivial = pycolmap.Rig()
                trivial.add_ref_sensor(db.read_camera(cam_ids[-1]).sensor_id)
                rig_ids.append(db.write_rig(trivial))
            for k, name in enumerate(names):
                h = k % num_h
                image_id = db.write_image(pycolmap.Image(name=name, camera_id=cam_ids[h],
                                                         image_id=k + 1), use_image_id=True)
                frame = pycolmap.Frame()
                frame.rig_id = rig_ids[h]
                frame.add_data_id(db.read_image(image_id).data_id)
                db.write_frame(frame)
                db.write_keypoints(image_id, keypoints[k].astype(np.float32))
        finally:
            db.close()
        truth = out / "truth"
        truth.mkdir()
        rec = pycolmap.Reconstruction()
        for h in range(num_h):
            rec.add_camera_with_trivial_rig(pycolmap.Camera(
                model="PINHOLE", width=options.width, height=options.height,
                params=camera["params"], camera_id=h + 1))
        for k, name in enumerate(names):
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(rotations[k]),
                                    -rotations[k] @ centres[k])
            rec.add_image_with_trivial_frame(
                pycolmap.Image(name=name, camera_id=k % num_h + 1, image_id=k + 1), pose)
        rec.write_text(str(truth))
        (truth / "origin.txt").write_text(
            "# origin X Y Z: local = model CRS - origin\n"
            f"{float(origin[0])!r} {float(origin[1])!r} {float(origin[2])!r}\n"
            f"# crs: {store.crs.label}\n")
        np.savez_compressed(truth / "observations.npz", point=p_idx, image=f_idx,
                            keypoint=kp_index, ray=ray.astype(np.float32),
                            xyz=pts.astype(np.float64))
        stats = {"crs": store.crs.label, "origin": origin.tolist(), "exposures": num_e,
                 "heads": num_h, "images": len(names),
                 "true_triangles": int(len(scene.triangles)),
                 "candidate_points": int(len(pts)), "observations": int(len(p_idx)),
                 "points_seen_twice": int(np.count_nonzero(np.bincount(p_idx) >= 2)),
                 "seconds": time.perf_counter() - t0,
                 "options": asdict(options)}
        (truth / "simulation.json").write_text(json.dumps(stats, indent=2))
    logger.info("oblique block: %d exposures x %d heads, %d observations of %d points",
                num_e, num_h, len(p_idx), stats["points_seen_twice"])
    return stats


@dataclass
class MatchingResult:
    pairs: int
    matched_pairs: int
    matches: int
    verified_pairs: int
    """Pairs with inlier matches after COLMAP's verification."""
    inlier_matches: int
    seconds_verification: float


def simulate_matching(workspace, pairs_file, database=None, *,
                      max_match_angle_deg: float | None = None, min_matches: int = 15
                      ) -> MatchingResult:
    """Matches of the listed pairs from the simulation's truth, then COLMAP's verification."""
    import pycolmap

    from ..files import quiet_colmap

    workspace = Path(workspace)
    database = Path(database) if database is not None else workspace / "database.db"
    stats = json.loads((workspace / "truth" / "simulation.json").read_text())
    limit = (stats["options"]["max_match_angle_deg"] if max_match_angle_deg is None
             else max_match_angle_deg)
    data = np.load(workspace / "truth" / "observations.npz")
    point, image, keypoint, ray = data["point"], data["image"], data["keypoint"], data["ray"]
    order = np.lexsort((point, image))
    point, image, keypoint, ray = point[order], image[order], keypoint[order], ray[order]
    starts = np.searchsorted(image, np.arange(image.max() + 2))
    min_cos = math.cos(math.radians(limit))
    pairs = [line.split() for line in Path(pairs_file).read_text().splitlines() if line.strip()]
    db = pycolmap.Database.open(str(database))
    matched = total = 0
    try:
        ids = {i.name: int(i.image_id) for i in db.read_all_images()}
        for a, b in pairs:
            i, j = ids[a] - 1, ids[b] - 1
            si, sj = slice(starts[i], starts[i + 1]), slice(starts[j], starts[j + 1])
            common, ia, jb = np.intersect1d(point[si], point[sj], assume_unique=True,
                                            return_indices=True)
            ok = np.einsum("ij,ij->i", ray[si][ia], ray[sj][jb]) >= min_cos
            if np.count_nonzero(ok) < min_matches:
                continue
            m = np.c_[keypoint[si][ia[ok]], keypoint[sj][jb[ok]]].astype(np.uint32)
            db.write_matches(ids[a], ids[b], m)
            matched += 1
            total += len(m)
    finally:
        db.close()
    t0 = time.perf_counter()
    with quiet_colmap(workspace / "colmap.log"):
        pycolmap.verify_matches(str(database), str(pairs_file), pycolmap.TwoViewGeometryOptions())
    seconds = time.perf_counter() - t0
    db = pycolmap.Database.open(str(database))
    try:
        _, counts = db.read_two_view_geometry_num_inliers()
        counts = np.asarray(counts, np.int64)
        verified, inliers = int(np.count_nonzero(counts > 0)), int(counts.sum())
    finally:
        db.close()
    return MatchingResult(len(pairs), matched, total, verified, inliers, seconds)
