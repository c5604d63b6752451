"""The sliding-window workflow (Unger 3.3.2, Tables 4-5; method.md 5) on an existing block.

The images are taken in capture order, which is read from the image names (natural order:
`img9` before `img10`; COLMAP models carry no capture times, and sequences are named by frame
number or time stamp). A window holds N_ws = `window_size` consecutive images; each step moves
it on by N_new = `window_new` images, keeping the N_ws - N_new most recent adjusted ones.
Per window (only its images and their observations; tie points seen by fewer than two of its
images are left out):

1. prediction: the images new to the window are still where the block was before any window
   (the GNSS-only adjustment, moved by the coarse alignment), while the kept images have been
   adjusted with the model. The similarity that carries the kept images from their earlier to
   their adjusted poses (rotation from their orientations, scale and shift from their centres)
   moves the new images and the tie points first seen by them. This stands in for Unger's
   steps 5-6 (new key frames oriented from the last adjusted ones, then a bundle adjustment
   of the window without the model): COLMAP has oriented them already, and an adjustment
   without the model would only let the GNSS bias pull the window off the planes that placed
   the kept images (on a synthetic street the prediction leaves most tie points near the
   model, such an adjustment almost none);
2. the assign + hybrid adjustment loop of the global workflow (adjust.loop; steps 3-4), the
   first window with its similarity rounds onto the planes, later ones without (their
   position comes from the window before).

Earlier images leave the window with their observations. Of the kept images, the oldest
`window_held_images` camera stations (three, as in Unger) enter every solve of the next
window with pose priors at their adjusted poses (`sigma_window_position`,
`sigma_window_rotation`), the others are estimated again. Priors rather than fixed poses because that is what the source does and
what a window needs: where the window has no GNSS (GNSS only at the start of the sequence),
the held poses are its datum until its tie points reach the model planes, and a kept image
that the window before placed poorly (few planes at its end) can still move with the new
planes' evidence; with fixed poses a poor pose at a window's end would be frozen into the
next one. Unger gives the held poses the previous window's estimated covariances; here they
get fixed sigmas of a window's typical a posteriori precision, which spares a covariance
computation per window.

Intrinsics stay constant in the windows (the global adjustments before and after estimate
them when `refine_intrinsics` is on); the GNSS offset, if estimated, stays at its start value
until the final global adjustment. What the windows leave is the initial value of the final
global hybrid adjustment of all images (Unger step 7), which workflow.refine runs as in the
global workflow. A window whose datum cannot be fixed (no GNSS, no held images, no tie point
on a plane) keeps its predicted poses, and says so in its record.
"""

from __future__ import annotations

import copy
import logging
import re
import time
from dataclasses import dataclass, field

import numpy as np
import pycolmap
from tqdm import tqdm

from ..align.objective import BlockObjective
from ..block.priors import GNSSPriors
from ..block.reconstruction import tie_points
from ..citymodel.store import PlaneStore
from ..errors import DatumError, InputError
from ..options import RefineOptions
from .loop import adjustment_loop
from .problem import PosePriors

logger = logging.getLogger(__name__)


@dataclass
class WindowRecord:
    """What one window did."""

    index: int
    first_image: str
    last_image: str
    num_images: int
    num_new: int  # images that entered with this window
    num_held: int  # images held by pose priors from the window before
    num_gnss: int  # images with GNSS in the window
    num_points: int  # tie points in the window's problem
    iterations: int
    num_assigned: int
    num_planes: int
    rms: float | None  # RMS of the normalised residuals of the last solve (None: no solve)
    seconds: float
    note: str | None = None  # why the window kept its predicted poses

    def todict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class SlidingWindowResult:
    windows: list[WindowRecord] = field(default_factory=list)
    seconds: float = 0.0
    warnings: list[str] = field(default_factory=list)

    def todict(self, options: RefineOptions) -> dict:
        o = options.workflow
        return {"order": "image name", "window_size": o.window_size,
                "window_new": o.window_new, "window_held_images": o.window_held_images,
                "sigma_window_position_m": o.sigma_window_position,
                "sigma_window_rotation_deg": o.sigma_window_rotation,
                "num_windows": len(self.windows), "seconds": self.seconds,
                "windows": [w.todict() for w in self.windows]}


def natural_key(name: str) -> list:
    """Sort key that compares the digit runs of a name as numbers (`img9` < `img10`)."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def capture_order(rec: pycolmap.Reconstruction) -> list[int]:
    """The registered frames in capture order: by the natural order of their images' names
    (a frame of several cameras by its first name)."""
    def key(frame_id: int):
        return min(natural_key(rec.image(d.id).name) for d in rec.frame(frame_id).image_ids)

    return sorted(rec.reg_frame_ids(), key=key)


def window_starts(num: int, size: int, new: int) -> list[int]:
    """First positions of the windows over `num` frames: 0, new, 2 new, ..., the last window
    ending at the last frame (full size where the sequence allows)."""
    if num <= size:
        return [0]
    starts = list(range(0, num - size, new))
    return starts + [num - size]


def window_reconstruction(rec: pycolmap.Reconstruction, frame_ids: list[int]
                          ) -> pycolmap.Reconstruction:
    """A reconstruction of the given frames only: their rigs, cameras, images (all 2D points,
    same ids) and the tie points they see at least twice, with the tracks cut to them (same
    point ids)."""
    sub = pycolmap.Reconstruction()
    cameras: set[int] = set()
    rigs: set[int] = set()
    image_ids: set[int] = set()
    for fid in frame_ids:
        frame = rec.frame(fid)
        rig = rec.rig(frame.rig_id)
        for sensor in rig.sensor_ids():
            if sensor.type == pycolmap.SensorType.CAMERA and sensor.id not in cameras:
                sub.add_camera(rec.camera(sensor.id))
                cameras.add(sensor.id)
        if frame.rig_id not in rigs:
            sub.add_rig(rig)
            rigs.add(frame.rig_id)
    for fid in frame_ids:
        frame = rec.frame(fid)
        new = pycolmap.Frame()
        new.frame_id = fid
        new.rig_id = frame.rig_id
        for data_id in frame.data_ids:
            new.add_data_id(data_id)
        new.rig_from_world = frame.rig_from_world
        sub.add_frame(new)
        for data_id in frame.image_ids:
            image = rec.image(data_id.id)
            keypoints = np.array([p.xy for p in image.points2D]).reshape(-1, 2)
            copied = pycolmap.Image(name=image.name, keypoints=keypoints,
                                    camera_id=image.camera_id, image_id=image.image_id)
            copied.frame_id = fid
            sub.add_image(copied)
            image_ids.add(image.image_id)
        sub.register_frame(fid)
    seen: set[int] = set()
    for image_id in image_ids:
        for point2D in rec.image(image_id).get_observation_points2D():
            seen.add(point2D.point3D_id)
    for point_id in seen:
        point = rec.point3D(point_id)
        elements = [e for e in point.track.elements if e.image_id in image_ids]
        if len(elements) < 2:
            continue
        sub.add_point3D_with_id(point_id, pycolmap.Point3D(
            xyz=point.xyz, track=pycolmap.Track(elements), color=point.color))
    return sub


def similarity_between(before: list[pycolmap.Rigid3d], after: list[pycolmap.Rigid3d]
                       ) -> pycolmap.Sim3d:
    """The similarity S of the world that carries the poses `before` (rig_from_world) to
    `after`: rotation the chordal mean of the rotation changes, scale from the spread of the
    centres, shift from their centroids."""
    q = np.zeros((3, 3))
    c0, c1 = [], []
    for a, b in zip(before, after):
        q += np.asarray(b.rotation.matrix()).T @ np.asarray(a.rotation.matrix())
        c0.append(np.asarray(a.inverse().translation))
        c1.append(np.asarray(b.inverse().translation))
    u, _, vt = np.linalg.svd(q)
    rotation = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    c0, c1 = np.array(c0), np.array(c1)
    spread0 = np.sum((c0 - c0.mean(0)) ** 2)
    spread1 = np.sum((c1 - c1.mean(0)) ** 2)
    scale = float(np.sqrt(spread1 / spread0)) if spread0 > 1e-12 and spread1 > 1e-12 else 1.0
    shift = c1.mean(0) - scale * rotation @ c0.mean(0)
    return pycolmap.Sim3d(scale, pycolmap.Rotation3d(rotation), shift)


def moved_pose(pose: pycolmap.Rigid3d, sim3: pycolmap.Sim3d) -> pycolmap.Rigid3d:
    """rig_from_world of a rig whose world moved by `sim3` (rig frame scaled with it)."""
    q = np.asarray(sim3.rotation.matrix())
    rotation = np.asarray(pose.rotation.matrix()) @ q.T
    translation = sim3.scale * np.asarray(pose.translation) - rotation @ np.asarray(
        sim3.translation)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation)


#: Projection centres closer than this (m) count as one station when the held images are
#: chosen (the cameras of one rig or one stop).
STATION_DISTANCE = 0.1


def held_stations(rec: pycolmap.Reconstruction, kept: list[int], count: int) -> list[int]:
    """The oldest kept frames at `count` distinct stations (and every frame at those
    stations): three poses at one spot would leave the window's scale free."""
    held: list[int] = []
    stations: list[np.ndarray] = []
    for fid in kept:
        centre = np.asarray(rec.frame(fid).rig_from_world.inverse().translation)
        near = any(np.linalg.norm(centre - c) < STATION_DISTANCE for c in stations)
        if not near:
            if len(stations) == count:
                break
            stations.append(centre)
        held.append(fid)
    return held


def _window_priors(priors: GNSSPriors | None, image_ids: set[int]) -> GNSSPriors | None:
    """The GNSS priors of the window's images, the offset held at its current value."""
    if priors is None:
        return None
    keep = np.array([int(i) in image_ids for i in priors.image_ids], bool)
    if not keep.any():
        return None
    return GNSSPriors(image_ids=priors.image_ids[keep], positions=priors.positions[keep],
                      sigmas=priors.sigmas[keep], lever_arm=priors.lever_arm,
                      offset=np.array(priors.offset, dtype=np.float64))


def _window_options(options: RefineOptions, first: bool) -> RefineOptions:
    window = copy.deepcopy(options)
    window.adjustment.refine_intrinsics = False
    # The windows bring the block onto the model; the faces' errors as unknowns are estimated
    # by the global loop after them, from where they left it (adjust.staged).
    window.adjustment.face_weighting = "per_point"
    if not first:  # the window before placed it: no similarity moves of the whole window
        window.workflow.alignment_rounds = 0
    return window


def check_window_options(options: RefineOptions) -> None:
    o = options.workflow
    if o.window_size < 2:
        raise InputError(f"option workflow.window_size must be at least 2, got {o.window_size}")
    if not 1 <= o.window_new < o.window_size:
        raise InputError("option workflow.window_new must be at least 1 and less than "
                         f"workflow.window_size ({o.window_size}), got {o.window_new}")
    if o.window_held_images > o.window_size - o.window_new:
        raise InputError(f"option workflow.window_held_images ({o.window_held_images}) exceeds "
                         "the images a window keeps (window_size - window_new = "
                         f"{o.window_size - o.window_new})")


def sliding_window(rec: pycolmap.Reconstruction, store: PlaneStore, priors: GNSSPriors | None,
                   options: RefineOptions, surface, *, exclude_point_ids: set[int] | None = None,
                   progress: bool = True) -> SlidingWindowResult:
    """Adjust `rec` (modified in place; local frame) window by window with the model `store`.
    `surface` is the model's align.coarse.SurfaceDistance (for each window's objective)."""
    check_window_options(options)
    o_w, o_adj = options.workflow, options.adjustment
    start = time.perf_counter()
    order = capture_order(rec)
    starts = window_starts(len(order), o_w.window_size, o_w.window_new)
    initial = {fid: _copy_pose(rec.frame(fid).rig_from_world) for fid in order}
    adjusted: set[int] = set()
    touched: set[int] = set()  # tie points already moved or adjusted by a window
    result = SlidingWindowResult()
    sigma_rotation = np.radians(o_w.sigma_window_rotation)
    logger.info("sliding window: %d images in name order, %d windows of %d (%d new each)",
                len(order), len(starts), min(o_w.window_size, len(order)), o_w.window_new)
    bar = tqdm(total=len(order), desc="sliding window", unit="img", disable=not progress)
    for index, first in enumerate(starts):
        t0 = time.perf_counter()
        frames = order[first:first + o_w.window_size]
        kept = [f for f in frames if f in adjusted]
        new = [f for f in frames if f not in adjusted]
        if kept:
            sim3 = similarity_between([initial[f] for f in kept],
                                      [rec.frame(f).rig_from_world for f in kept])
            _move_new(rec, new, sim3, touched)
        else:
            _mark_seen(rec, new, touched)
        sub = window_reconstruction(rec, frames)
        image_ids = set(sub.reg_image_ids())
        window_priors = _window_priors(priors, image_ids)
        held_frames = held_stations(rec, kept, o_w.window_held_images)
        held = _held_poses(rec, held_frames, o_w.sigma_window_position, sigma_rotation)
        window_options = _window_options(options, first=index == 0)
        note = None
        record_rms, iterations, assigned, planes = None, 0, 0, 0
        try:
            ids, _ = tie_points(sub, exclude_point_ids)
            objective = BlockObjective(surface, window_priors, ids, o_adj,
                                       options.workflow.divergence_alpha)
            loop = adjustment_loop(sub, store, window_priors, window_options, objective, ids,
                                   exclude_point_ids=exclude_point_ids, progress=False,
                                   pose_priors=held)
            sub = loop.reconstruction
            last = loop.iterations[-1]
            record_rms, iterations = last.final.rms_total, len(loop.iterations)
            assigned, planes = loop.assignment.num_assigned, loop.assignment.num_faces
        except DatumError as error:
            note = f"kept its predicted poses: {error.message}"
            result.warnings.append(f"window {index}: {note}")
            logger.warning("window %d %s", index, note)
        if note is None:
            _copy_back(rec, sub, frames)
        adjusted.update(frames)
        record = WindowRecord(
            index=index, first_image=rec.image(next(iter(rec.frame(frames[0]).image_ids)).id).name,
            last_image=rec.image(next(iter(rec.frame(frames[-1]).image_ids)).id).name,
            num_images=len(image_ids), num_new=len(new), num_held=len(held_frames),
            num_gnss=0 if window_priors is None else len(window_priors),
            num_points=sub.num_points3D(), iterations=iterations, num_assigned=assigned,
            num_planes=planes, rms=record_rms, seconds=time.perf_counter() - t0, note=note)
        result.windows.append(record)
        logger.info("window %d (%s .. %s): %d images (%d new, %d held, %d with GNSS), %d "
                    "points on %d planes, RMS %s, %d iterations, %.1f s", index,
                    record.first_image, record.last_image, record.num_images, record.num_new,
                    record.num_held, record.num_gnss, assigned, planes,
                    "-" if record_rms is None else f"{record_rms:.4f}", iterations,
                    record.seconds)
        bar.update(len(new))
        bar.set_postfix(window=f"{index + 1}/{len(starts)}", images=len(image_ids),
                        rms="-" if record_rms is None else f"{record_rms:.4f}", planes=planes)
    bar.close()
    result.seconds = time.perf_counter() - start
    return result


def _held_poses(rec: pycolmap.Reconstruction, frames: list[int], sigma_position: float,
                sigma_rotation: float) -> PosePriors | None:
    """The poses of `frames` (kept from the window before) as priors with these sigmas (m,
    rad); None without such frames."""
    if not frames:
        return None
    return PosePriors(image_ids=np.array([next(iter(rec.frame(f).image_ids)).id
                                          for f in frames]),
                      rig_from_world=[_copy_pose(rec.frame(f).rig_from_world) for f in frames],
                      sigma_position=sigma_position, sigma_rotation=sigma_rotation)


def _copy_pose(pose: pycolmap.Rigid3d) -> pycolmap.Rigid3d:
    return pycolmap.Rigid3d(np.asarray(pose.matrix()))


def _mark_seen(rec: pycolmap.Reconstruction, frames: list[int], touched: set[int]) -> None:
    for fid in frames:
        for data_id in rec.frame(fid).image_ids:
            for point2D in rec.image(data_id.id).get_observation_points2D():
                touched.add(point2D.point3D_id)


def _move_new(rec: pycolmap.Reconstruction, frames: list[int], sim3: pycolmap.Sim3d,
              touched: set[int]) -> None:
    """Move the frames new to a window, and the tie points no window has moved yet that they
    see, by `sim3`."""
    matrix = np.asarray(sim3.matrix())
    for fid in frames:
        frame = rec.frame(fid)
        frame.rig_from_world = moved_pose(frame.rig_from_world, sim3)
        for data_id in frame.image_ids:
            for point2D in rec.image(data_id.id).get_observation_points2D():
                point_id = point2D.point3D_id
                if point_id in touched:
                    continue
                touched.add(point_id)
                point = rec.point3D(point_id)
                point.xyz = matrix[:, :3] @ point.xyz + matrix[:, 3]


def _copy_back(rec: pycolmap.Reconstruction, sub: pycolmap.Reconstruction,
               frames: list[int]) -> None:
    """The window's adjusted poses and tie points into the whole block."""
    for fid in frames:
        rec.frame(fid).rig_from_world = sub.frame(fid).rig_from_world
    for point_id, point in sub.points3D.items():
        if rec.exists_point3D(point_id):
            rec.point3D(point_id).xyz = point.xyz
