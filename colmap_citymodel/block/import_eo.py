"""import-eo: GNSS/IMU exterior orientations of a multi-head camera into a COLMAP 4 database
(rigs, frames, pose priors) and a known-pose COLMAP model.

What goes where (pycolmap 4.2.1):
- **database**: one camera per head (from the rig file, or the one the head's images already
  have), one rig (reference head = COLMAP's reference sensor; every other head with its
  ``sensor_from_rig`` from the lever arms and boresight angles), one frame per exposure holding
  its heads' images (images missing from the database are added, without features), and one
  pose prior per image: the image's projection centre in the local frame (CARTESIAN), its
  covariance (EO position sigmas, diagonal) and the gravity direction in the camera frame
  (``gravity`` = R_cam_from_world (0, 0, -1)). Existing rigs, frames and pose priors are
  replaced (as ``colmap rig_configurator`` does); cameras, keypoints and matches are kept.
  A COLMAP 4.2 pose prior holds no rotation beyond gravity, so the heading lives in the model:
- **model** (``--output_path``/``sparse``): cameras, the rig, every frame with its
  rig_from_world and every image, no 3D points, with the database's ids; the input of
  ``colmap point_triangulator`` / ``pycolmap.triangulate_points`` (known-pose triangulation)
  and of ``colmap-citymodel pairs``.
- ``origin.json``: the local frame's origin in the model CRS ({"origin": [X, Y, Z], "crs"}),
  the EO positions' mean rounded down to whole 100 m in easting and northing, height 0
  (``evaluate --origin_file`` reads it).
- ``gnss.txt``: image_name X Y Z sX sY sZ, projection centres in the model CRS, for
  ``refine --gnss gnss.txt --gnss_crs <model CRS>`` (refine reads CARTESIAN database priors
  as unshifted model CRS coordinates, which these are not).
"""

from __future__ import annotations

import json
import logging
import math
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ..errors import InputError
from ..files import atomic_directory
from .eo import (DEFAULT_EO_SIGMA, BlockPoses, Exposures, RigSpec, block_poses, body_angles,
                 body_rotation, exposure_from_reference, grid_north_azimuth, read_eo, read_rig)
from .gnss import _crs_info, _pyproj_crs, reproject_with_report

logger = logging.getLogger(__name__)

#: The local origin is the mean EO position rounded down to this many metres (E, N).
ORIGIN_ROUNDING = 100.0
GRAVITY_WORLD = np.array([0.0, 0.0, -1.0])


@dataclass
class ImportEOResult:
    database: Path
    output_path: Path
    origin: np.ndarray
    crs: str
    num_exposures: int
    num_heads: int
    num_images: int
    num_images_added: int
    poses: BlockPoses

    def summary(self) -> str:
        return (f"import-eo: {self.num_exposures} exposure(s) x {self.num_heads} head(s) = "
                f"{self.num_images} image(s) ({self.num_images_added} added to the database); "
                f"rig, frames and pose priors in {self.database}; known-pose model in "
                f"{self.output_path / 'sparse'}; local origin {self.origin.tolist()} "
                f"({self.crs})")


def exposures_in_model_crs(exposures: Exposures, eo_crs: str, model_crs: str | None
                           ) -> tuple[np.ndarray, np.ndarray, str]:
    """(positions (N,3) in the model CRS, R_world_from_body (N,3,3) on its grid axes, label)."""
    source = _crs_info(eo_crs)
    target = source if model_crs is None else _crs_info(model_crs)
    same = model_crs is None or _pyproj_crs(source).equals(_pyproj_crs(target))
    if same:
        if not source.is_projected:
            raise InputError(f"--eo_crs {eo_crs} is geographic: give the projected model CRS "
                             "with --model_crs")
        positions = exposures.positions.copy()
        turn = np.zeros(len(positions))
    else:
        if not target.is_projected:
            raise InputError(f"--model_crs {model_crs} must be a projected CRS")
        positions, _ = reproject_with_report(exposures.positions, source, target,
                                             what="EO positions")
        beta_source = (grid_north_azimuth(_pyproj_crs(source), exposures.positions[:, 0],
                                          exposures.positions[:, 1])
                       if source.is_projected else np.zeros(len(positions)))
        beta_target = grid_north_azimuth(_pyproj_crs(target), positions[:, 0], positions[:, 1])
        turn = np.radians(beta_source - beta_target)
    rotations = np.empty((len(positions), 3, 3))
    for k, angles in enumerate(exposures.angles):
        c, s = math.cos(turn[k]), math.sin(turn[k])
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        rotations[k] = rz @ body_rotation(angles, exposures.attitude)
    return positions, rotations, (target.label if hasattr(target, "label") else str(model_crs))


def local_origin(positions: np.ndarray) -> np.ndarray:
    mean = np.mean(positions, axis=0)
    return np.array([math.floor(mean[0] / ORIGIN_ROUNDING) * ORIGIN_ROUNDING,
                     math.floor(mean[1] / ORIGIN_ROUNDING) * ORIGIN_ROUNDING, 0.0])


def _camera(spec: dict, path) -> pycolmap.Camera:
    try:
        camera = pycolmap.Camera(model=str(spec["model"]), width=int(spec["width"]),
                                 height=int(spec["height"]),
                                 params=[float(v) for v in spec["params"]])
    except Exception as error:  # pycolmap raises ValueError/RuntimeError on a bad model
        raise InputError(f"rig camera {spec!r}: {error}", path) from None
    if not camera.verify_params():
        raise InputError(f"rig camera {spec!r}: wrong number of parameters for "
                         f"{spec['model']}", path)
    camera.has_prior_focal_length = True
    return camera


def _rigid(rotation: np.ndarray, translation: np.ndarray) -> pycolmap.Rigid3d:
    return pycolmap.Rigid3d(pycolmap.Rotation3d(np.asarray(rotation, float)),
                            np.asarray(translation, float))


def _head_cameras(db, rig: RigSpec, names: list[list[str]], existing: dict, rig_path
                  ) -> list[int]:
    """Camera id of each head: the rig file's camera (written) or the head's images' own."""
    ids = []
    for h, head in enumerate(rig.heads):
        if head.camera is not None:
            ids.append(db.write_camera(_camera(head.camera, rig_path)))
            continue
        cams = {existing[n].camera_id for n in names[h] if n in existing}
        if not cams:
            raise InputError(f"rig head {head.name!r} has no 'camera' and none of its images "
                             "is in the database", rig_path)
        first = db.read_camera(min(cams))
        for cam_id in cams:
            other = db.read_camera(cam_id)
            if (other.model != first.model or other.width != first.width
                    or other.height != first.height
                    or not np.allclose(other.params, first.params)):
                raise InputError(f"rig head {head.name!r}: its images in the database have "
                                 "different cameras; give the head's 'camera' in the rig file",
                                 rig_path)
        ids.append(int(first.camera_id))
    return ids


def write_database(database, rig: RigSpec, poses: BlockPoses, sigmas: np.ndarray,
                   rig_path=None) -> tuple[dict[str, int], int, list[int], int]:
    """Cameras, rig, frames, images and pose priors (see the module docstring). Returns (image
    id by name, rig id, camera id per head, number of images added)."""
    names = [[head.image(e) for e in poses.exposure_ids] for head in rig.heads]
    flat = [n for per_head in names for n in per_head]
    if len(set(flat)) != len(flat):
        raise InputError("the rig's image_name templates give the same name twice", rig_path)
    try:
        db = pycolmap.Database.open(str(database))
    except Exception as error:
        raise InputError(f"cannot open COLMAP database: {error}", database) from None
    try:
        existing = {image.name: image for image in db.read_all_images()}
        camera_ids = _head_cameras(db, rig, names, existing, rig_path)
        # the old rigs and frames go first: COLMAP checks an image's camera against its frame
        db.clear_pose_priors()
        db.clear_frames()
        db.clear_rigs()
        added = 0
        image_ids: dict[str, int] = {}
        for h, per_head in enumerate(names):
            for name in per_head:
                if name in existing:
                    image = existing[name]
                    if image.camera_id != camera_ids[h]:
                        db.update_image(pycolmap.Image(name=name, camera_id=camera_ids[h],
                                                       image_id=image.image_id))
                    image_ids[name] = int(image.image_id)
                else:
                    image_ids[name] = int(db.write_image(
                        pycolmap.Image(name=name, camera_id=camera_ids[h])))
                    added += 1
        colmap_rig = pycolmap.Rig()
        colmap_rig.add_ref_sensor(db.read_camera(camera_ids[rig.reference]).sensor_id)
        for h in range(len(rig.heads)):
            if h != rig.reference:
                colmap_rig.add_sensor(db.read_camera(camera_ids[h]).sensor_id,
                                      _rigid(*rig.sensor_from_rig(h)))
        rig_id = int(db.write_rig(colmap_rig))
        covariances = np.zeros((len(sigmas), 3, 3))
        covariances[:, [0, 1, 2], [0, 1, 2]] = np.asarray(sigmas, float) ** 2
        for e in range(len(poses.exposure_ids)):
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            for h in range(len(rig.heads)):
                image = db.read_image(image_ids[names[h][e]])
                frame.add_data_id(image.data_id)
                prior = pycolmap.PosePrior(
                    position=poses.centres[e, h], position_covariance=covariances[e],
                    coordinate_system=pycolmap.PosePriorCoordinateSystem.CARTESIAN)
                prior.gravity = poses.cam_rotations[e, h] @ GRAVITY_WORLD
                prior.corr_data_id = image.data_id
                db.write_pose_prior(prior)
            db.write_frame(frame)
    finally:
        db.close()
    return image_ids, rig_id, camera_ids, added


def known_pose_model(database, poses: BlockPoses, rig: RigSpec) -> pycolmap.Reconstruction:
    """The database's cameras, rig, frames and images with the EO poses (no 3D points)."""
    db = pycolmap.Database.open(str(database))
    try:
        cameras = db.read_all_cameras()
        rigs = db.read_all_rigs()
        frames = db.read_all_frames()
        images = db.read_all_images()
    finally:
        db.close()
    by_data = {(int(i.data_id.sensor_id.id), int(i.data_id.id)): i for i in images}
    ref_names = {rig.heads[rig.reference].image(e): k for k, e in enumerate(poses.exposure_ids)}
    rec = pycolmap.Reconstruction()
    used_cameras = {int(s.id) for r in rigs for s in r.sensor_ids()}
    for camera in cameras:
        if int(camera.camera_id) in used_cameras:
            rec.add_camera(camera)
    for r in rigs:
        rec.add_rig(r)
    frame_images = []
    for frame in frames:
        members = [by_data[(int(d.sensor_id.id), int(d.id))] for d in frame.data_ids]
        exposure = next(ref_names[m.name] for m in members if m.name in ref_names)
        frame.rig_from_world = _rigid(poses.cam_rotations[exposure, rig.reference],
                                      -poses.cam_rotations[exposure, rig.reference]
                                      @ poses.centres[exposure, rig.reference])
        rec.add_frame(frame)
        frame_images.append((frame.frame_id, members))
    for frame_id, members in frame_images:
        for image in members:
            image.frame_id = frame_id
            rec.add_image(image)
        rec.register_frame(frame_id)
    return rec


def write_outputs(directory: Path, rec: pycolmap.Reconstruction, origin: np.ndarray,
                  crs: str, poses: BlockPoses, rig: RigSpec, sigmas: np.ndarray) -> None:
    sparse = directory / "sparse"
    sparse.mkdir()
    rec.write(str(sparse))
    (directory / "origin.json").write_text(json.dumps(
        {"origin": origin.tolist(), "crs": crs,
         "frame": "local = model CRS minus origin (x east, y north, z up)"}, indent=2))
    lines = ["# image_name X Y Z sX sY sZ (projection centres, model CRS)"]
    for e, exposure in enumerate(poses.exposure_ids):
        for h, head in enumerate(rig.heads):
            x, y, z = poses.centres[e, h] + origin
            sx, sy, sz = sigmas[e]
            lines.append(f"{head.image(exposure)} {x:.4f} {y:.4f} {z:.4f} "
                         f"{sx:.4f} {sy:.4f} {sz:.4f}")
    (directory / "gnss.txt").write_text("\n".join(lines) + "\n")


def main(database, eo, rig, eo_crs: str, output_path, *, model_crs: str | None = None,
         attitude: str = "opk", default_sigma=DEFAULT_EO_SIGMA) -> ImportEOResult:
    """Read the EO file and the rig, write rigs, frames and pose priors into `database` and the
    known-pose model, origin.json and gnss.txt into the new directory `output_path`."""
    database = Path(database)
    if not database.is_file():
        raise InputError("COLMAP database does not exist (run feature_extractor first, or "
                         "create it with `colmap database_creator`)", database)
    rig_spec = read_rig(rig)
    exposures = read_eo(eo, attitude, default_sigma)
    positions, rotations, label = exposures_in_model_crs(exposures, eo_crs, model_crs)
    origin = local_origin(positions)
    poses = block_poses(rig_spec, exposures.ids, positions - origin, rotations)
    with atomic_directory(output_path) as tmp:
        # the database is changed on a copy that replaces it once everything is written
        scratch = Path(tmp) / ".database.db"
        shutil.copyfile(database, scratch)
        _, _, _, added = write_database(scratch, rig_spec, poses, exposures.sigmas, rig)
        rec = known_pose_model(scratch, poses, rig_spec)
        write_outputs(Path(tmp), rec, origin, label, poses, rig_spec, exposures.sigmas)
        os.replace(scratch, database)
    result = ImportEOResult(database, Path(output_path), origin, label, len(exposures.ids),
                            len(rig_spec.heads), len(exposures.ids) * len(rig_spec.heads), added,
                            poses)
    logger.debug(result.summary())
    return result


# -- reading the block back ----------------------------------------------------------------------

@dataclass
class ReadBack:
    """What the database and the model hold, turned back into exterior orientations."""

    centres: dict[str, np.ndarray]
    """Image name -> pose prior position (local frame)."""
    gravity: dict[str, np.ndarray]
    """Image name -> pose prior gravity direction (camera frame)."""
    sensor_from_rig: dict[str, tuple[np.ndarray, np.ndarray]]
    """Image name -> (R, t) of its camera in the database rig (identity for the reference)."""
    cam_rotations: dict[str, np.ndarray]
    """Image name -> R_cam_from_world of the model."""
    model_centres: dict[str, np.ndarray]


def read_back(database, model_path) -> ReadBack:
    db = pycolmap.Database.open(str(database))
    try:
        images = db.read_all_images()
        priors = db.read_all_pose_priors()
        rigs = db.read_all_rigs()
    finally:
        db.close()
    by_data = {(int(i.data_id.sensor_id.id), int(i.data_id.id)): i for i in images}
    centres, gravity = {}, {}
    for prior in priors:
        key = (int(prior.corr_data_id.sensor_id.id), int(prior.corr_data_id.id))
        centres[by_data[key].name] = np.asarray(prior.position, float)
        gravity[by_data[key].name] = np.asarray(prior.gravity, float)
    calibration = {}
    for image in images:
        for r in rigs:
            sensor = image.data_id.sensor_id
            if r.has_sensor(sensor):
                if r.is_ref_sensor(sensor):
                    calibration[image.name] = (np.eye(3), np.zeros(3))
                else:
                    pose = r.sensor_from_rig(sensor)
                    calibration[image.name] = (np.asarray(pose.rotation.matrix()),
                                               np.asarray(pose.translation))
    rec = pycolmap.Reconstruction(str(model_path))
    rotations, model_centres = {}, {}
    for image in rec.images.values():
        pose = image.cam_from_world()
        rotations[image.name] = np.asarray(pose.rotation.matrix())
        model_centres[image.name] = np.asarray(image.projection_center())
    return ReadBack(centres, gravity, calibration, rotations, model_centres)


def exposures_from_block(rig: RigSpec, back: ReadBack, exposure_ids: list[str], attitude: str
                         ) -> tuple[np.ndarray, np.ndarray]:
    """(antenna positions (E,3) local frame, angles (E,3) degrees in `attitude`) of each exposure,
    from the reference head's pose prior position and model rotation."""
    positions, angles = [], []
    for exposure in exposure_ids:
        name = rig.heads[rig.reference].image(exposure)
        world_from_body, antenna = exposure_from_reference(rig, back.cam_rotations[name],
                                                           back.centres[name])
        positions.append(antenna)
        angles.append(body_angles(world_from_body, attitude))
    return np.asarray(positions), np.asarray(angles)
