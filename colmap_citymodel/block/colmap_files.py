"""Read a COLMAP model directory, checking its files first so that damage gets a clear message.

COLMAP's binary reader trusts every count in the file: a truncated or damaged images.bin makes
it read past the end without noticing, loop over a garbage count, wait forever for the end of an
image name, or stop at an id that matches nothing ("unordered_map::at"). Its text reader stops at
"Check failed: line_stream >> ...". So before pycolmap reads the model, every file is walked
here: sizes and counts against the file length, camera models and parameter counts, numbers
that are not finite or beyond any frame, and the ids each file refers to (images -> cameras and
frames, frames -> rigs, rigs -> cameras, tracks -> images and their 2D points, 2D points -> 3D
points). A damaged model fails with an `InputError` naming the file and the record.

Formats (COLMAP 3.12 / 4.x, as pycolmap writes them): cameras, images, points3D and, optionally,
rigs and frames, either all `.bin` or all `.txt`; the binary set wins when both are complete, as
in COLMAP. Without rigs and frames (older models) every camera is its own rig.
"""

from __future__ import annotations

import math
import mmap
import struct
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import numpy as np

from ..errors import InputError

REQUIRED = ("cameras", "images", "points3D")
OPTIONAL = ("rigs", "frames")
INVALID_POINT3D_ID = 2**64 - 1
MAX_ID32 = 2**32 - 1
#: Largest coordinate (model units, usually metres) of a camera or point: far beyond any
#: reconstruction, also one in ECEF coordinates; larger values are damaged numbers.
MAX_COORDINATE = 1e9
#: Largest image side (pixels) a camera can have.
MAX_IMAGE_SIDE = 10**6
#: 2D points lie within this many image sides of the image (keypoints lie inside it).
MAX_POINT2D_SIDES = 10
SENSOR_TYPES = {0: "CAMERA", 1: "IMU"}
_CHUNK = 1 << 16  # points per chunk of track elements

_P2D = np.dtype([("xy", "<f8", (2,)), ("id", "<u8")])
_TRACK = np.dtype([("image", "<u4"), ("idx", "<u4")])
_U64 = struct.Struct("<Q")


class _Damaged(Exception):
    """A problem in one file of the model (becomes an InputError naming that file)."""

    def __init__(self, path: Path, message: str):
        super().__init__(message)
        self.path = path
        self.message = message


@lru_cache(maxsize=1)
def camera_models() -> dict[int, tuple[str, int, tuple[int, ...]]]:
    """{model id: (name, number of parameters, indices of the focal lengths)} from pycolmap."""
    import pycolmap

    table = {}
    for name, model in pycolmap.CameraModelId.__members__.items():
        if int(model) < 0:
            continue
        camera = pycolmap.Camera.create_from_model_id(1, model, 100.0, 100, 100)
        table[int(model)] = (name, len(camera.params), tuple(camera.focal_length_idxs()))
    return table


@dataclass
class _Model:
    """What the walk over the files learned, for the checks across files."""

    kind: str  # "bin" or "txt"
    files: dict[str, Path]
    cameras: dict[int, int] = field(default_factory=dict)  # camera -> longer image side
    rigs: dict[int, set[tuple[int, int]]] = field(default_factory=dict)  # rig -> sensors
    image_frame: dict[int, tuple[int, int]] = field(default_factory=dict)  # image -> frame, camera
    has_rigs_or_frames: bool = False
    image_ids: list[int] = field(default_factory=list)
    image_names: list[str] = field(default_factory=list)
    image_refs: list[np.ndarray] = field(default_factory=list)  # point3D id of each 2D point
    point_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint64))  # sorted


# ---------------------------------------------------------------------------------------------
# Finding the files


def model_files(path: str | Path) -> tuple[str, dict[str, Path]]:
    """("bin" or "txt", {name: file}) of the COLMAP model in directory `path`, chosen as COLMAP
    chooses (the complete binary set first). Raises InputError when there is no model."""
    path = Path(path)
    if not path.exists():
        raise InputError("COLMAP model directory does not exist", path)
    if not path.is_dir():
        raise InputError("not a COLMAP model directory (a file, not a directory)", path)
    for kind in ("bin", "txt"):
        if all((path / f"{name}.{kind}").is_file() for name in REQUIRED):
            files = {name: path / f"{name}.{kind}" for name in REQUIRED + OPTIONAL
                     if (path / f"{name}.{kind}").is_file()}
            return kind, files
    present = sorted(p.name for p in path.iterdir()
                     if p.stem in REQUIRED + OPTIONAL and p.suffix in (".bin", ".txt"))
    if not any(p.startswith("cameras.") for p in present):
        raise InputError("not a COLMAP model directory (no cameras.bin or cameras.txt)", path)
    kind = "bin" if "cameras.bin" in present else "txt"
    missing = [f"{name}.{kind}" for name in REQUIRED if f"{name}.{kind}" not in present]
    raise InputError(f"incomplete COLMAP model: {' and '.join(missing)} missing (found "
                     f"{', '.join(present)})", path)


def check_model(path: str | Path) -> str:
    """Walk every file of the COLMAP model in `path`; returns its format ("bin" or "txt").
    Raises InputError naming the damaged file and what is wrong with it."""
    kind, files = model_files(path)
    model = _Model(kind, files)
    try:
        if kind == "bin":
            _check_binary(model)
        else:
            _check_text(model)
    except _Damaged as damaged:
        raise InputError(damaged.message, damaged.path) from None
    except OSError as error:
        raise InputError(f"cannot read the COLMAP model: {error}", path) from None
    return kind


def read_model(path: str | Path):
    """The pycolmap.Reconstruction in directory `path`, its files checked first (check_model)."""
    import pycolmap

    path = Path(path)
    kind = check_model(path)
    try:
        return pycolmap.Reconstruction(str(path))
    except Exception as error:  # pycolmap raises plain RuntimeError/IndexError for broken files
        first = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        raise InputError(f"cannot read the COLMAP model ({kind}): {first}", path) from None


# ---------------------------------------------------------------------------------------------
# Checks shared by both formats


def _finite_pose(values, path: Path, what: str) -> None:
    """qw qx qy qz tx ty tz: finite, a unit quaternion, a translation within MAX_COORDINATE."""
    if not all(math.isfinite(v) for v in values):
        raise _Damaged(path, f"{what}: pose with a value that is not finite")
    norm = math.sqrt(sum(v * v for v in values[:4]))
    if abs(norm - 1.0) > 1e-2:
        raise _Damaged(path, f"{what}: rotation quaternion of length {norm:.6g}, not 1")
    if max(abs(v) for v in values[4:]) > MAX_COORDINATE:
        raise _Damaged(path, f"{what}: translation beyond {MAX_COORDINATE:.0e}")


def _check_camera(model: _Model, camera_id: int, model_id: int, width: int, height: int,
                  params, where: str) -> None:
    path = model.files["cameras"]
    what = f"{where}camera {camera_id}"
    table = camera_models()
    if model_id not in table:
        raise _Damaged(path, f"{what}: unknown camera model id {model_id}")
    name, num_params, focal = table[model_id]
    if len(params) != num_params:
        raise _Damaged(path, f"{what}: {name} needs {num_params} parameters, got {len(params)}")
    if camera_id in model.cameras:
        raise _Damaged(path, f"{what}: camera id given twice")
    if not (1 <= width <= MAX_IMAGE_SIDE and 1 <= height <= MAX_IMAGE_SIDE):
        raise _Damaged(path, f"{what}: image size {width} x {height} pixels is not plausible")
    if not all(math.isfinite(p) and abs(p) <= MAX_COORDINATE for p in params):
        raise _Damaged(path, f"{what}: a parameter is not finite or beyond {MAX_COORDINATE:.0e}")
    # a focal length below 1/1000 of the image size would be a field of view of ~180 degrees
    shortest = 1e-3 * max(width, height)
    if any(params[i] < shortest for i in focal):
        raise _Damaged(path, f"{what}: focal length {min(params[i] for i in focal):.6g} px is "
                             f"not plausible for a {width} x {height} image")
    model.cameras[camera_id] = max(width, height)


def _add_rig(model: _Model, rig_id: int, sensors: list[tuple[int, int]], where: str) -> None:
    path = model.files["rigs"]
    if rig_id in model.rigs:
        raise _Damaged(path, f"{where}rig {rig_id}: rig id given twice")
    for sensor_type, sensor_id in sensors:
        if sensor_type not in SENSOR_TYPES:
            raise _Damaged(path, f"{where}rig {rig_id}: unknown sensor type {sensor_type}")
        if sensor_type == 0 and sensor_id not in model.cameras:
            raise _Damaged(path, f"{where}rig {rig_id}: camera {sensor_id} is not in "
                                 f"{model.files['cameras'].name}")
    model.rigs[rig_id] = set(sensors)


def _add_frame(model: _Model, frame_id: int, rig_id: int, data_ids, frames_seen: set,
               where: str) -> None:
    path = model.files["frames"]
    what = f"{where}frame {frame_id}"
    if frame_id in frames_seen:
        raise _Damaged(path, f"{what}: frame id given twice")
    frames_seen.add(frame_id)
    if rig_id not in model.rigs:
        rigs = model.files.get("rigs")
        raise _Damaged(path, f"{what}: rig {rig_id} is not in "
                             f"{rigs.name if rigs else 'the model (no rigs file)'}")
    for sensor_type, sensor_id, data_id in data_ids:
        if sensor_type not in SENSOR_TYPES:
            raise _Damaged(path, f"{what}: unknown sensor type {sensor_type}")
        if sensor_type != 0:
            continue
        if (0, sensor_id) not in model.rigs[rig_id]:
            raise _Damaged(path, f"{what}: camera {sensor_id} is not a sensor of rig {rig_id}")
        if data_id > MAX_ID32:
            raise _Damaged(path, f"{what}: image id {data_id} is out of range")
        if data_id in model.image_frame:
            raise _Damaged(path, f"{what}: image {data_id} is also in frame "
                                 f"{model.image_frame[data_id][0]}")
        model.image_frame[data_id] = (frame_id, sensor_id)


def _add_image(model: _Model, image_id: int, camera_id: int, name: str, refs: np.ndarray,
               xy: np.ndarray, image_index: dict[int, int], where: str) -> None:
    """xy: the 2D points' coordinates (any shape), finite and near the image."""
    path = model.files["images"]
    what = f"{where}image {image_id} ({name!r})"
    if not np.isfinite(xy).all():
        raise _Damaged(path, f"{what}: a 2D point that is not finite")
    if image_id in image_index:
        raise _Damaged(path, f"{what}: image id given twice")
    if not name:
        raise _Damaged(path, f"{where}image {image_id}: no image name")
    if camera_id not in model.cameras:
        raise _Damaged(path, f"{what}: camera {camera_id} is not in {model.files['cameras'].name}")
    if model.has_rigs_or_frames:
        frame = model.image_frame.get(image_id)
        if frame is None:
            frames = model.files.get("frames")
            raise _Damaged(path, f"{what}: no frame holds this image "
                                 f"({frames.name if frames else 'the frames file is missing'})")
        if frame[1] != camera_id:
            raise _Damaged(path, f"{what}: camera {camera_id}, but frame {frame[0]} holds it "
                                 f"with camera {frame[1]}")
    side = model.cameras[camera_id]
    if xy.size and np.abs(xy).max() > MAX_POINT2D_SIDES * side:
        raise _Damaged(path, f"{what}: a 2D point at {np.abs(xy).max():.6g} px, far outside "
                             f"the {side} px image")
    image_index[image_id] = len(model.image_ids)
    model.image_ids.append(image_id)
    model.image_names.append(name)
    model.image_refs.append(refs)


def _check_points(model: _Model, ids: np.ndarray, xyz: np.ndarray, where) -> None:
    """Point ids unique and valid, coordinates finite and within MAX_COORDINATE."""
    path = model.files["points3D"]
    if len(ids) and ids.max() == INVALID_POINT3D_ID:
        raise _Damaged(path, f"{where(int(np.argmax(ids)))}: the invalid point id "
                             f"{INVALID_POINT3D_ID}")
    bad = ~np.isfinite(xyz).all(axis=1)
    with np.errstate(invalid="ignore"):
        bad |= (np.abs(xyz) > MAX_COORDINATE).any(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        text = ", ".join(f"{v:.6g}" for v in xyz[k])
        raise _Damaged(path, f"{where(k)}: position ({text}) is not finite or beyond "
                             f"{MAX_COORDINATE:.0e}")
    model.point_ids = np.unique(ids)
    if len(model.point_ids) != len(ids):
        uniq, counts = np.unique(ids, return_counts=True)
        raise _Damaged(path, f"point {int(uniq[np.argmax(counts > 1)])}: point id given twice")


def _check_tracks(model: _Model, chunks: Iterator[tuple[np.ndarray, np.ndarray, np.ndarray]]
                  ) -> None:
    """Track elements name existing images and 2D points, and the 2D points name the track's
    point; every 3D point named by an image's 2D point is confirmed by that point's track.

    chunks: (owning point id, image id, 2D point index) arrays of track elements, see the format
    walkers."""
    path = model.files["points3D"]
    images_name = model.files["images"].name
    ids = np.asarray(model.image_ids, dtype=np.int64)
    top = int(ids.max()) if len(ids) else 0
    if top <= 8 * len(ids) + (1 << 20):
        # row of each image id (-1: no such image), the last slot for all larger ids
        lut = np.full(top + 2, -1, dtype=np.int64)
        lut[ids] = np.arange(len(ids))
        rows_of = lambda images: lut[np.minimum(images, top + 1)]  # noqa: E731
    else:  # sparse ids: a table would be too large
        order = np.argsort(ids)
        sorted_ids = ids[order]

        def rows_of(images):
            k = np.minimum(np.searchsorted(sorted_ids, images), len(ids) - 1)
            return np.where(sorted_ids[k] == images, order[k], -1)
    offsets = np.zeros(len(ids) + 1, dtype=np.int64)
    np.cumsum([len(r) for r in model.image_refs], out=offsets[1:])
    num_2d = np.diff(offsets)
    refs_all = np.concatenate(model.image_refs) if model.image_refs else np.zeros(0, np.uint64)
    model.image_refs = []
    confirmed = np.zeros(len(refs_all), dtype=bool)

    def image_of(flat: int) -> int:
        return int(np.searchsorted(offsets, flat, side="right")) - 1

    for owners, images, idx in chunks:
        row = rows_of(images)
        if len(row) and row.min() < 0:
            e = int(np.argmin(row))
            raise _Damaged(path, f"point {int(owners[e])}: its track names image "
                                 f"{int(images[e])}, which is not in {images_name}")
        inside = idx < num_2d[row]
        if not inside.all():
            e = int(np.argmin(inside))
            raise _Damaged(path, f"point {int(owners[e])}: its track names 2D point {int(idx[e])} "
                                 f"of image {int(images[e])}, which has {int(num_2d[row[e]])}")
        flat = offsets[row] + idx
        refs = refs_all[flat]
        wrong = (refs != owners) & (refs != INVALID_POINT3D_ID)
        if wrong.any():
            e = int(np.argmax(wrong))
            r = int(row[e])
            if not _known_point(model, refs[e]):
                raise _Damaged(model.files["images"],
                               f"image {model.image_ids[r]} ({model.image_names[r]!r}): 2D "
                               f"point {int(idx[e])} names point {int(refs[e])}, which "
                               f"is not in {model.files['points3D'].name}")
            raise _Damaged(path, f"point {int(owners[e])}: its track names 2D point "
                                 f"{int(idx[e])} of image {model.image_ids[r]}, which "
                                 f"{images_name} gives to point {int(refs[e])}")
        confirmed[flat] = True
    dangling = (refs_all != INVALID_POINT3D_ID) & ~confirmed
    if dangling.any():
        flat = int(np.argmax(dangling))
        r = image_of(flat)
        known = _known_point(model, refs_all[flat])
        raise _Damaged(model.files["images"],
                       f"image {model.image_ids[r]} ({model.image_names[r]!r}): 2D point "
                       f"{flat - int(offsets[r])} names point {int(refs_all[flat])}, "
                       + (f"whose track in {model.files['points3D'].name} does not hold it"
                          if known else f"which is not in {model.files['points3D'].name}"))


def _known_point(model: _Model, point_id) -> bool:
    k = int(np.searchsorted(model.point_ids, np.uint64(point_id)))
    return k < len(model.point_ids) and model.point_ids[k] == np.uint64(point_id)


# ---------------------------------------------------------------------------------------------
# Binary files


class _Binary:
    """A read-only view of one binary file with bounds-checked reads."""

    def __init__(self, path: Path):
        self.path = path
        self._file = open(path, "rb")
        self.size = path.stat().st_size
        self.data = mmap.mmap(self._file.fileno(), 0, access=mmap.ACCESS_READ) if self.size \
            else b""

    def close(self) -> None:
        if isinstance(self.data, mmap.mmap):
            self.data.close()
        self._file.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def unpack(self, fmt: struct.Struct, pos: int, what: str) -> tuple:
        if pos + fmt.size > self.size:
            raise _Damaged(self.path, f"truncated: {what} would end at byte {pos + fmt.size}, "
                                      f"the file has {self.size} bytes")
        return fmt.unpack_from(self.data, pos)

    def count(self, min_record: int, what: str) -> int:
        """The record count at the start of the file, checked against the file length."""
        if self.size == 0:
            raise _Damaged(self.path, "empty file")
        head = bytes(self.data[:64])
        # printable throughout (a binary count of 35 records starts with "#" too)
        printable = all(32 <= c < 127 or c in b"\t\r\n" for c in head)
        if printable and (len(head) >= 8 or head.startswith(b"#")):
            raise _Damaged(self.path, "a text file, not COLMAP's binary format (a .txt model "
                                      "saved as .bin?)")
        (n,) = self.unpack(_U64, 0, f"the number of {what}")
        most = (self.size - 8) // min_record
        if n > most:
            raise _Damaged(self.path, f"the file says {n} {what}, but its {self.size} bytes hold "
                                      f"at most {most} (damaged count, truncated, or not a "
                                      f"COLMAP {self.path.stem} file)")
        return n

    def end(self, pos: int, n: int, what: str) -> None:
        if pos != self.size:
            raise _Damaged(self.path, f"{self.size - pos} bytes after the last of the {n} {what} "
                                      "(damaged count or data, or not a COLMAP "
                                      f"{self.path.stem} file)")


_CAMERA = struct.Struct("<IiQQ")
_RIG = struct.Struct("<II")
_REF_SENSOR = struct.Struct("<iI")
_SENSOR = struct.Struct("<iIB")
_POSE = struct.Struct("<7d")
_FRAME = struct.Struct("<II7dI")
_DATA_ID = struct.Struct("<iIQ")
_IMAGE = struct.Struct("<I7dI")
_POINT = struct.Struct("<Q3d3BdQ")


def _check_binary(model: _Model) -> None:
    files = model.files
    with _Binary(files["cameras"]) as f:
        n = f.count(_CAMERA.size, "cameras")
        pos = 8
        table = camera_models()
        for k in range(n):
            camera_id, model_id, width, height = f.unpack(_CAMERA, pos, f"camera {k + 1} of {n}")
            num_params = table.get(model_id, (None, 0))[1]
            params = f.unpack(struct.Struct(f"<{num_params}d"), pos + _CAMERA.size,
                              f"the parameters of camera {camera_id}")
            _check_camera(model, camera_id, model_id, width, height, params, "")
            pos += _CAMERA.size + 8 * num_params
        f.end(pos, n, "cameras")
    model.has_rigs_or_frames = "rigs" in files or "frames" in files
    if "rigs" in files:
        with _Binary(files["rigs"]) as f:
            n = f.count(_RIG.size, "rigs")
            pos = 8
            for k in range(n):
                rig_id, num_sensors = f.unpack(_RIG, pos, f"rig {k + 1} of {n}")
                pos += _RIG.size
                if num_sensors > (f.size - pos) // _REF_SENSOR.size:
                    raise _Damaged(f.path, f"rig {rig_id}: {num_sensors} sensors cannot fit in "
                                           "the rest of the file")
                sensors = []
                if num_sensors:
                    sensors.append(f.unpack(_REF_SENSOR, pos, f"the sensors of rig {rig_id}"))
                    pos += _REF_SENSOR.size
                for _ in range(max(num_sensors - 1, 0)):
                    sensor_type, sensor_id, has_pose = f.unpack(_SENSOR, pos,
                                                               f"the sensors of rig {rig_id}")
                    pos += _SENSOR.size
                    if has_pose > 1:
                        raise _Damaged(f.path, f"rig {rig_id}: sensor pose flag {has_pose} is not "
                                               "0 or 1")
                    if has_pose:
                        pose = f.unpack(_POSE, pos, f"a sensor pose of rig {rig_id}")
                        _finite_pose(pose, f.path, f"rig {rig_id}, sensor {sensor_id}")
                        pos += _POSE.size
                    sensors.append((sensor_type, sensor_id))
                _add_rig(model, rig_id, sensors, "")
            f.end(pos, n, "rigs")
    if "frames" in files:
        with _Binary(files["frames"]) as f:
            n = f.count(_FRAME.size, "frames")
            pos = 8
            seen: set[int] = set()
            for k in range(n):
                frame_id, rig_id, *pose, num_data = f.unpack(_FRAME, pos, f"frame {k + 1} of {n}")
                pos += _FRAME.size
                _finite_pose(pose, f.path, f"frame {frame_id}")
                if num_data > (f.size - pos) // _DATA_ID.size:
                    raise _Damaged(f.path, f"frame {frame_id}: {num_data} data ids cannot fit in "
                                           "the rest of the file")
                data = [f.unpack(_DATA_ID, pos + j * _DATA_ID.size, f"frame {frame_id}")
                        for j in range(num_data)]
                pos += num_data * _DATA_ID.size
                _add_frame(model, frame_id, rig_id, data, seen, "")
            f.end(pos, n, "frames")
    with _Binary(files["images"]) as f:
        n = f.count(_IMAGE.size + 9, "images")
        pos = 8
        index: dict[int, int] = {}
        for k in range(n):
            image_id, *pose, camera_id = f.unpack(_IMAGE, pos, f"image {k + 1} of {n}")
            pos += _IMAGE.size
            _finite_pose(pose, f.path, f"image {image_id}")
            end = f.data.find(b"\0", pos) if f.size else -1
            if end < 0:
                raise _Damaged(f.path, f"truncated: the name of image {image_id} ({k + 1} of {n}) "
                                       "has no end")
            raw = bytes(f.data[pos:end])
            try:
                name = raw.decode("utf-8")
            except UnicodeDecodeError:
                raise _Damaged(f.path, f"image {image_id}: its name {raw[:60]!r} is not UTF-8 "
                                       "text") from None
            pos = end + 1
            (num_2d,) = f.unpack(_U64, pos, f"the number of 2D points of image {image_id}")
            pos += 8
            if num_2d > (f.size - pos) // _P2D.itemsize:
                raise _Damaged(f.path, f"truncated or damaged: image {image_id} ({name!r}) says "
                                       f"{num_2d} 2D points, the rest of the file holds at most "
                                       f"{(f.size - pos) // _P2D.itemsize}")
            points = np.frombuffer(f.data[pos:pos + num_2d * _P2D.itemsize], dtype=_P2D)
            pos += num_2d * _P2D.itemsize
            _add_image(model, image_id, camera_id, name, points["id"].copy(), points["xy"], index,
                       "")
        f.end(pos, n, "images")
    with _Binary(files["points3D"]) as f:
        n = f.count(_POINT.size, "points")
        pos = 8
        point_ids: list[int] = []
        xyz_list: list[tuple[float, float, float]] = []
        spans: list[tuple[int, int]] = []
        unpack, size, data = _POINT.unpack_from, _POINT.size, f.data
        for k in range(n):
            if pos + size > f.size:
                f.unpack(_POINT, pos, f"point {k + 1} of {n}")  # raises: truncated
            pid, x, y, z, _r, _g, _b, _err, length = unpack(data, pos)
            pos += size
            if length > (f.size - pos) // _TRACK.itemsize:
                raise _Damaged(f.path, f"truncated or damaged: point {pid} says its track has "
                                       f"{length} elements, the rest of the file holds at most "
                                       f"{(f.size - pos) // _TRACK.itemsize}")
            point_ids.append(pid)
            xyz_list.append((x, y, z))
            spans.append((pos, length))
            pos += length * _TRACK.itemsize
        f.end(pos, n, "points")
        ids = np.array(point_ids, dtype=np.uint64)
        xyz = np.array(xyz_list, dtype=np.float64).reshape(-1, 3)
        del point_ids, xyz_list
        _check_points(model, ids, xyz, lambda k: f"point {int(ids[k])}")

        def chunks():
            for a in range(0, n, _CHUNK):
                part = spans[a:a + _CHUNK]
                lengths = np.fromiter((t for _, t in part), np.int64, len(part))
                raw = b"".join(f.data[p:p + t * _TRACK.itemsize] for p, t in part)
                track = np.frombuffer(raw, dtype=_TRACK)
                yield np.repeat(ids[a:a + len(part)], lengths), track["image"], track["idx"]

        _check_tracks(model, chunks())


# ---------------------------------------------------------------------------------------------
# Text files


def _lines(path: Path) -> Iterator[tuple[int, str]]:
    """(line number, stripped line) of the data lines (no blank lines, no '#' comments)."""
    for number, line in _all_lines(path):
        if line and not line.startswith("#"):
            yield number, line


def _all_lines(path: Path) -> Iterator[tuple[int, str]]:
    try:
        with open(path, encoding="utf-8") as f:
            for number, line in enumerate(f, 1):
                if not line.endswith("\n") and line.strip():
                    number = -number  # the file ends in this line: see _where
                yield number, line.strip()
    except UnicodeDecodeError as error:
        raise _Damaged(path, f"not UTF-8 text ({error.reason}): binary data in a text model "
                             "file (a .bin model saved as .txt, or damage)") from None
    except OSError as error:
        raise _Damaged(path, f"cannot read the file: {error}") from None


class _LineFields:
    """The fields of one text line, read in order with a message naming the line."""

    def __init__(self, path: Path, number: int, line: str, layout: str):
        self.path, self.number, self.layout = path, number, layout
        self.parts = line.split()
        self.k = 0

    def fail(self, why: str) -> _Damaged:
        return _Damaged(self.path, f"{_where(self.number)}: {why} (expected {self.layout})")

    def word(self, what: str) -> str:
        if self.k >= len(self.parts):
            raise self.fail(f"{what} missing")
        self.k += 1
        return self.parts[self.k - 1]

    def int(self, what: str, top: int = MAX_ID32) -> int:
        text = self.word(what)
        try:
            value = int(text) if "_" not in text else None
        except ValueError:
            value = None
        if value is None or not 0 <= value <= top:
            raise self.fail(f"{what} {_short(text)} is not an integer in [0, {top}]")
        return value

    def float(self, what: str) -> float:
        text = self.word(what)
        try:
            value = float(text) if "_" not in text else None
        except ValueError:
            value = None
        if value is None:
            raise self.fail(f"{what} {_short(text)} is not a number")
        if not math.isfinite(value):
            raise self.fail(f"{what} {_short(text)} is not finite")
        return value

    def sensor_type(self, what: str) -> int:
        text = self.word(what)
        for code, name in SENSOR_TYPES.items():
            if text == name:
                return code
        raise self.fail(f"{what} {_short(text)} is not CAMERA or IMU")

    def rest(self) -> list[str]:
        return self.parts[self.k:]

    def done(self) -> None:
        if self.k != len(self.parts):
            raise self.fail(f"{len(self.parts) - self.k} extra field(s) from "
                            f"{_short(self.parts[self.k])}")


def _where(number: int) -> str:
    """'line N', noting a last line cut short (_all_lines marks it with a negative number)."""
    if number < 0:
        return f"line {-number} (the file ends in the middle of it: truncated?)"
    return f"line {number}"


def _short(text: str) -> str:
    return repr(text if len(text) <= 40 else text[:37] + "...")


_POSE_FIELDS = ("QW", "QX", "QY", "QZ", "TX", "TY", "TZ")


def _check_text(model: _Model) -> None:
    files = model.files
    path = files["cameras"]
    names = {name: code for code, (name, _, _) in camera_models().items()}
    for number, line in _lines(path):
        t = _LineFields(path, number, line, "CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
        camera_id = t.int("camera id")
        name = t.word("camera model")
        if name not in names:
            raise t.fail(f"unknown camera model {name!r}")
        width, height = t.int("width", 2**63), t.int("height", 2**63)
        params = [t.float("parameter") for _ in t.rest()]
        _check_camera(model, camera_id, names[name], width, height, params, f"{_where(number)}: ")
    model.has_rigs_or_frames = "rigs" in files or "frames" in files
    if "rigs" in files:
        path = files["rigs"]
        for number, line in _lines(path):
            t = _LineFields(path, number, line,
                        "RIG_ID NUM_SENSORS REF_SENSOR_TYPE REF_SENSOR_ID SENSORS[] as "
                        "(TYPE ID HAS_POSE [QW QX QY QZ TX TY TZ])")
            rig_id, num_sensors = t.int("rig id"), t.int("number of sensors")
            sensors = []
            if num_sensors:
                sensors.append((t.sensor_type("sensor type"), t.int("sensor id")))
            for _ in range(max(num_sensors - 1, 0)):
                sensor = (t.sensor_type("sensor type"), t.int("sensor id"))
                if t.int("pose flag", 1):
                    _finite_pose([t.float(f) for f in _POSE_FIELDS], path,
                                 f"{_where(number)}: rig {rig_id}, sensor {sensor[1]}")
                sensors.append(sensor)
            t.done()
            _add_rig(model, rig_id, sensors, f"{_where(number)}: ")
    if "frames" in files:
        path = files["frames"]
        seen: set[int] = set()
        for number, line in _lines(path):
            t = _LineFields(path, number, line, "FRAME_ID RIG_ID QW QX QY QZ TX TY TZ NUM_DATA_IDS "
                                            "DATA_IDS[] as (SENSOR_TYPE SENSOR_ID DATA_ID)")
            frame_id, rig_id = t.int("frame id"), t.int("rig id")
            _finite_pose([t.float(f) for f in _POSE_FIELDS], path,
                         f"{_where(number)}: frame {frame_id}")
            num_data = t.int("number of data ids")
            data = [(t.sensor_type("sensor type"), t.int("sensor id"), t.int("data id", 2**64 - 1))
                    for _ in range(num_data)]
            t.done()
            _add_frame(model, frame_id, rig_id, data, seen, f"{_where(number)}: ")
    path = files["images"]
    index: dict[int, int] = {}
    lines = _all_lines(path)
    layout = "IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME, then a line of X Y POINT3D_ID triples"
    for number, line in lines:
        if not line or line.startswith("#"):
            continue
        t = _LineFields(path, number, line, layout)
        image_id = t.int("image id")
        pose = [t.float(f) for f in _POSE_FIELDS]
        camera_id = t.int("camera id")
        name = t.word("image name")
        t.done()
        _finite_pose(pose, path, f"{_where(number)}: image {image_id}")
        second = next(lines, None)
        if second is None:
            raise _Damaged(path, f"{_where(number)}: image {image_id} ({name!r}) has no line of 2D "
                                 "points after it (truncated file?)")
        number2, points_line = second
        parts = points_line.split()
        where = f"{_where(number2)}: the 2D points of image {image_id}"
        if len(parts) % 3 or (parts and parts[0].startswith("#")):
            raise _Damaged(path, f"{where} are not X Y POINT3D_ID triples ({len(parts)} fields)")
        try:
            if "_" in points_line:
                raise ValueError
            xy = np.array(parts[0::3] + parts[1::3], dtype=np.float64)
            signed = np.array(parts[2::3], dtype=np.int64)
        except (ValueError, OverflowError):
            raise _Damaged(path, f"{where} hold a field that is not a number or an id") from None
        if len(signed) and signed.min() < -1:
            raise _Damaged(path, f"{where} hold a point id below -1")
        refs = signed.astype(np.uint64)  # -1 (no point) becomes INVALID_POINT3D_ID
        _add_image(model, image_id, camera_id, name, refs, xy, index, f"{_where(number)}: ")
    path = files["points3D"]
    ids, xyz, owners, tracks, line_of = [], [], [], [], []
    for number, line in _lines(path):
        t = _LineFields(path, number, line, "POINT3D_ID X Y Z R G B ERROR TRACK[] as "
                                        "(IMAGE_ID POINT2D_IDX)")
        pid = t.int("point id", 2**64 - 1)
        xyz.append((t.float("X"), t.float("Y"), t.float("Z")))
        for channel in "RGB":
            t.int(channel, 2**31 - 1)
        t.float("error")
        track = t.rest()
        if len(track) % 2:
            raise t.fail("the track is not IMAGE_ID POINT2D_IDX pairs")
        try:
            if "_" in line:
                raise ValueError
            pairs = np.array(track, dtype=np.int64).reshape(-1, 2)
        except (ValueError, OverflowError):
            pairs = None
        if pairs is None or (pairs.size and (pairs.min() < 0 or pairs.max() > MAX_ID32)):
            for _ in range(len(track) // 2):  # field by field, to name the bad one
                t.int("track image id")
                t.int("track 2D point index")
        tracks.append(pairs)
        owners.append(np.full(len(pairs), pid, dtype=np.uint64))
        ids.append(pid)
        line_of.append(number)
    ids_arr = np.array(ids, dtype=np.uint64)
    _check_points(model, ids_arr, np.array(xyz, dtype=np.float64).reshape(-1, 3),
                  lambda k: f"{_where(line_of[k])}: point {ids[k]}")
    pairs = np.concatenate(tracks) if tracks else np.zeros((0, 2), dtype=np.int64)
    _check_tracks(model, iter([(np.concatenate(owners) if owners else np.zeros(0, np.uint64),
                                pairs[:, 0], pairs[:, 1])]))
