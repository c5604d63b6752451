"""The COLMAP reconstruction: reading it, and the tie points, camera centres and camera axes
that later stages use."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pycolmap


def tie_points(rec: pycolmap.Reconstruction, exclude: set[int] | None = None
               ) -> tuple[np.ndarray, np.ndarray]:
    """(ids ascending, (N, 3) coordinates) of every tie point but `exclude`, read once."""
    ids, xyz = TiePointReader(exclude)(rec)
    return ids.copy(), xyz  # the caller's own ids (the reader keeps its own read-only)


class TiePointReader:
    """The tie points of a reconstruction read again and again as it is adjusted: the points
    (all but `exclude`, or those of `ids` that exist) are looked up once and their coordinates
    kept as views of COLMAP's own, so that each call only copies the current values (a tenth of
    the time of `tie_points`). Another reconstruction, or a changed number of points, is looked
    up anew: for a reconstruction whose points are only moved (an adjustment, a transform), as
    in the refine loop, not one that deletes some points and adds as many."""

    def __init__(self, exclude: set[int] | None = None, ids: np.ndarray | None = None):
        self._exclude, self._wanted = exclude, ids
        self._rec: pycolmap.Reconstruction | None = None
        self._count = -1
        self.ids = np.zeros(0, np.int64)
        self._views: list[np.ndarray] = []

    def __call__(self, rec: pycolmap.Reconstruction) -> tuple[np.ndarray, np.ndarray]:
        """(ids, read-only: ascending, or in the order `ids` gave them; (N, 3) coordinates,
        a copy)."""
        if rec is not self._rec or rec.num_points3D() != self._count:
            self._look_up(rec)
        xyz = (np.concatenate(self._views).reshape(-1, 3) if self._views
               else np.zeros((0, 3)))
        return self.ids, xyz

    def _look_up(self, rec: pycolmap.Reconstruction) -> None:
        if self._wanted is not None:
            ids = np.array([i for i in np.asarray(self._wanted, np.int64).tolist()
                            if rec.exists_point3D(i)], np.int64)
            views = [rec.point3D(i).xyz for i in ids.tolist()]
        else:
            points = rec.points3D
            ids = np.fromiter(points.keys(), np.int64, count=len(points))
            views = [point.xyz for point in points.values()]
            order = np.argsort(ids)  # ascending ids, as point3D_ids() gives them
            ids = ids[order]
            views = [views[k] for k in order.tolist()]
            if self._exclude:
                keep = ~np.isin(ids, np.fromiter(self._exclude, np.int64,
                                                 count=len(self._exclude)))
                ids = ids[keep]
                views = [v for v, k in zip(views, keep.tolist()) if k]
        ids.flags.writeable = False
        self.ids, self._views = ids, views
        self._rec, self._count = rec, rec.num_points3D()


def observations(rec: pycolmap.Reconstruction, point_ids: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Every observation of the tie points `point_ids`: (row of its point in `point_ids`,
    image id), both (O,) int64."""
    point_ids = np.asarray(point_ids, np.int64)
    rows: list[int] = []
    image_ids: list[int] = []
    for row, point_id in enumerate(point_ids.tolist()):
        elements = rec.point3D(point_id).track.elements
        rows.extend([row] * len(elements))
        image_ids.extend(e.image_id for e in elements)
    return np.asarray(rows, np.int64), np.asarray(image_ids, np.int64)


def observer_centres(rec: pycolmap.Reconstruction, image_ids: np.ndarray) -> np.ndarray:
    """(O, 3) the current centre of the image of each observation (nan: image not registered)."""
    image_ids = np.asarray(image_ids, np.int64)
    centres = np.full((len(image_ids), 3), np.nan)
    registered = np.asarray(sorted(rec.reg_image_ids()), np.int64)
    if not len(registered):
        return centres
    table = np.array([rec.image(int(i)).projection_center() for i in registered])
    at = np.minimum(np.searchsorted(registered, image_ids), len(registered) - 1)
    known = registered[at] == image_ids
    centres[known] = table[at[known]]
    return centres


def camera_centres(rec: pycolmap.Reconstruction) -> np.ndarray:
    return np.array([rec.image(i).projection_center() for i in rec.reg_image_ids()])


def camera_up_and_view(rec: pycolmap.Reconstruction, image_ids=None
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Image "up" (-y axis) and viewing direction (z axis) of the cameras (default: every
    registered one) in the world frame."""
    ids = rec.reg_image_ids() if image_ids is None else image_ids
    rows = np.array([np.asarray(rec.image(int(i)).cam_from_world().rotation.matrix())
                     for i in ids])
    return -rows[:, 1], rows[:, 2]


def read_reconstruction(path: str | Path) -> pycolmap.Reconstruction:
    from ..errors import InputError
    from .colmap_files import read_model

    path = Path(path)
    if not path.is_dir():
        raise InputError("COLMAP model directory does not exist", path)
    if not any((path / f"cameras.{ext}").exists() for ext in ("bin", "txt")):
        raise InputError("not a COLMAP model directory (no cameras.bin or cameras.txt)", path)
    rec = read_model(path)  # checks the files first: damage gets a message naming the file
    if rec.num_reg_images() < 3:
        raise InputError(f"the model has only {rec.num_reg_images()} registered images", path)
    return rec


def position_in_rig(rec: pycolmap.Reconstruction, image: pycolmap.Image) -> np.ndarray:
    """The camera's projection centre in its rig frame; zero for the rig's reference camera."""
    if image.is_ref_in_frame():
        return np.zeros(3)
    rig = rec.rig(rec.frame(image.frame_id).rig_id)
    cam_from_rig = rig.sensor_from_rig(image.camera.sensor_id)
    rotation = np.asarray(cam_from_rig.rotation.matrix())
    return -rotation.T @ np.asarray(cam_from_rig.translation)
