"""COLMAP's part of the simulator: the database with the simulated matches and pose priors,
incremental mapping, and the true reconstruction to compare with."""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..files import quiet_colmap  # noqa: F401 (simulate callers import it from here too)
from .flight import Flight
from .observations import Observations
from .scenario import MappingOptions


logger = logging.getLogger(__name__)


def make_camera(flight: Flight, true: bool = False):
    """The camera as calibrated (database, COLMAP) or, with true=True, as it really is."""
    import pycolmap

    k1 = flight.k1 if true else flight.k1_calibrated
    cam = pycolmap.Camera(model="SIMPLE_RADIAL", width=flight.width, height=flight.height,
                          params=[flight.focal, flight.width / 2, flight.height / 2, k1])
    cam.camera_id = 1
    cam.has_prior_focal_length = True
    return cam


def write_database(path: Path, flight: Flight, obs: Observations, gnss_crs: np.ndarray | None,
                   gnss_sigma, available: np.ndarray | None = None) -> None:
    """Camera, one rig, one frame per image, images, keypoints, raw matches and pose priors
    (positions in the model CRS, covariance diag(sigma^2), CARTESIAN)."""
    import pycolmap

    db = pycolmap.Database.open(str(path))
    try:
        cam = make_camera(flight)
        cam_id = db.write_camera(cam, use_camera_id=True)
        cam = db.read_camera(cam_id)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(cam.sensor_id)
        rig_id = db.write_rig(rig)
        for k, name in enumerate(flight.names):
            image = pycolmap.Image(name=name, camera_id=cam_id, image_id=k + 1)
            image_id = db.write_image(image, use_image_id=True)
            image = db.read_image(image_id)
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(image.data_id)
            db.write_frame(frame)
            db.write_keypoints(image_id, obs.keypoints[k].astype(np.float32))
        for (i, j), m in obs.pairs.items():
            db.write_matches(i + 1, j + 1, m)
        if gnss_crs is not None:
            write_pose_priors(db, gnss_crs, gnss_sigma, available)
    finally:
        db.close()


def write_pose_priors(db, gnss_crs: np.ndarray, sigma, available: np.ndarray | None) -> None:
    import pycolmap

    cov = np.diag(np.asarray(sigma, dtype=np.float64) ** 2)
    db.clear_pose_priors()
    for k, pos in enumerate(gnss_crs):
        if available is not None and not available[k]:
            continue
        image = db.read_image(k + 1)
        prior = pycolmap.PosePrior(
            position=np.asarray(pos, dtype=np.float64), position_covariance=cov,
            coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN)
        prior.corr_data_id = image.data_id
        db.write_pose_prior(prior)


def truth_two_view_geometries(db_path: Path, flight: Flight, obs: Observations,
                              max_error: float = 4.0) -> None:
    """Two-view geometries from the true relative poses: E, F, inliers with Sampson error below
    `max_error` px (what COLMAP's verification finds without its RANSAC)."""
    import pycolmap

    K = np.array([[flight.focal, 0, flight.width / 2], [0, flight.focal, flight.height / 2],
                  [0, 0, 1]])
    Kinv = np.linalg.inv(K)
    db = pycolmap.Database.open(str(db_path))
    try:
        for (i, j), m in obs.pairs.items():
            R = flight.rotations[j] @ flight.rotations[i].T
            t = flight.translations[j] - R @ flight.translations[i]
            tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
            E = tx @ R
            F = Kinv.T @ E @ Kinv
            x1 = np.c_[obs.keypoints[i][m[:, 0]], np.ones(len(m))]
            x2 = np.c_[obs.keypoints[j][m[:, 1]], np.ones(len(m))]
            Fx1 = x1 @ F.T
            Ftx2 = x2 @ F
            num = np.einsum("ij,ij->i", x2, Fx1) ** 2
            den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
            inl = num / den < max_error ** 2
            tvg = pycolmap.TwoViewGeometry()
            tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
            tvg.E = E / np.linalg.norm(E)
            tvg.F = F / np.linalg.norm(F)
            tvg.inlier_matches = m[inl]
            db.write_two_view_geometry(i + 1, j + 1, tvg)
    finally:
        db.close()


def incremental_options(opt: MappingOptions, seed: int):
    import pycolmap

    o = pycolmap.IncrementalPipelineOptions()
    o.extract_colors = False  # there are no image files
    o.num_threads = opt.num_threads
    o.random_seed = seed if opt.random_seed is None else opt.random_seed
    if not opt.refine_intrinsics:
        o.ba_refine_focal_length = False
        o.ba_refine_principal_point = False
        o.ba_refine_extra_params = False
        o.mapper.abs_pose_refine_focal_length = False
        o.mapper.abs_pose_refine_extra_params = False
    if opt.incremental:
        try:
            o.mergedict(dict(opt.incremental))
        except Exception as error:  # pycolmap rejects unknown keys
            raise InputError(f"mapping.incremental: {error}") from None
    return o


def run_mapping(workspace: Path, flight: Flight, obs: Observations, opt: MappingOptions,
                seed: int) -> dict:
    """Geometric verification and COLMAP's incremental mapper; the largest model -> sparse/0.
    Returns statistics (times, models, registered images)."""
    import pycolmap

    db_path = workspace / "database.db"
    log = workspace / "colmap.log"
    stats: dict[str, Any] = {}
    t0 = time.perf_counter()
    if opt.two_view_geometry == "verify":
        pairs_txt = workspace / "pairs.txt"
        pairs_txt.write_text("".join(f"{flight.names[i]} {flight.names[j]}\n"
                                     for i, j in obs.pairs))
        with quiet_colmap(log):
            pycolmap.verify_matches(str(db_path), str(pairs_txt),
                                    pycolmap.TwoViewGeometryOptions())
        pairs_txt.unlink()
    else:
        truth_two_view_geometries(db_path, flight, obs)
    stats["verification_seconds"] = time.perf_counter() - t0
    db = pycolmap.Database.open(str(db_path))
    stats["num_verified_pairs"] = int(db.num_verified_image_pairs())
    stats["num_inlier_matches"] = int(db.num_inlier_matches())
    db.close()
    if not opt.run:
        return stats
    images = workspace / "images"
    images.mkdir(exist_ok=True)  # must exist; COLMAP maps from the database alone
    raw = workspace / "sparse_raw"
    raw.mkdir()
    t0 = time.perf_counter()
    with quiet_colmap(log):
        models = pycolmap.incremental_mapping(str(db_path), str(images), str(raw),
                                              incremental_options(opt, seed))
    stats["mapping_seconds"] = time.perf_counter() - t0
    ordered = sorted(models.values(), key=lambda r: (r.num_reg_images(), r.num_points3D()),
                     reverse=True)
    sparse = workspace / "sparse"
    sparse.mkdir()
    for i, rec in enumerate(ordered):
        (sparse / str(i)).mkdir()
        rec.write(str(sparse / str(i)))
    shutil.rmtree(raw)
    shutil.rmtree(images)
    stats["num_models"] = len(ordered)
    stats["model_sizes"] = [int(r.num_reg_images()) for r in ordered]
    if ordered:
        best = ordered[0]
        stats["num_registered_images"] = int(best.num_reg_images())
        stats["registered_fraction"] = best.num_reg_images() / len(flight.names)
        stats["num_points3D"] = int(best.num_points3D())
        stats["num_observations"] = int(best.compute_num_observations())
        stats["mean_reprojection_error"] = float(best.compute_mean_reprojection_error())
        stats["mean_track_length"] = float(best.compute_mean_track_length())
    else:
        stats["num_registered_images"] = 0
        stats["registered_fraction"] = 0.0
    if len(ordered) != 1:
        logger.warning("COLMAP produced %d models (sizes %s); sparse/0 is the largest",
                       len(ordered), stats["model_sizes"])
    return stats


def truth_reconstruction(flight: Flight, obs: Observations):
    """The true poses and tie points as a pycolmap Reconstruction (local frame)."""
    import pycolmap

    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(make_camera(flight, true=True))
    for k, name in enumerate(flight.names):
        image = pycolmap.Image(name=name, keypoints=obs.keypoints[k], camera_id=1,
                               image_id=k + 1)
        pose = pycolmap.Rigid3d(np.c_[flight.rotations[k], flight.translations[k]])
        rec.add_image_with_trivial_frame(image, pose)
    order = np.lexsort((obs.obs_frame, obs.obs_track))
    t, f, kp = obs.obs_track[order], obs.obs_frame[order], obs.obs_kp[order]
    cut = np.flatnonzero(np.r_[True, t[1:] != t[:-1], True])
    for s, e in zip(cut[:-1], cut[1:]):
        track = pycolmap.Track()
        for ff, kk in zip(f[s:e], kp[s:e]):
            track.add_element(int(ff) + 1, int(kk))
        rec.add_point3D(obs.track_xyz[t[s]], track)
    return rec
