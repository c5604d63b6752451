"""COLMAP's SIFT feature extraction (`pycolmap.extract_features`, CPU) of a run's images into
its database, resumable: images whose keypoints the database holds are not extracted again.

COLMAP's image reader takes the camera model and parameters (`--camera_model`,
`--camera_params`); the cameras follow the camera groups of pipeline.images (one COLMAP
camera per camera body and image size by default, `--single_camera` one for all). Each group
is extracted with COLMAP's single-camera mode, in chunks of `RunOptions.extraction_chunk`
images; a group that has a camera in the database (from an earlier chunk or run) adds its new
images to that camera (`ImageReaderOptions.existing_camera_id`)."""

from __future__ import annotations

import logging
from contextlib import contextmanager
from pathlib import Path

import pycolmap
from tqdm import tqdm

from ..errors import InputError
from .images import ImageFolder
from .options import RunOptions
from .state import RunState

logger = logging.getLogger(__name__)


@contextmanager
def colmap_warnings_only(min_level: int = 1):
    """COLMAP's log at warnings and above (its per-image lines would flood the console);
    `min_level` 2: errors only."""
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = max(level, min_level)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = level


def images_with_features(database_path: Path) -> dict[str, int]:
    """Image name -> camera id of the database's images whose extraction finished (their
    keypoints are written, none for an image without texture; an image whose extraction was
    interrupted has none written)."""
    if not Path(database_path).exists():
        return {}
    with pycolmap.Database.open(str(database_path)) as db:
        return {image.name: int(image.camera_id) for image in db.read_all_images()
                if db.exists_keypoints(image.image_id)}


def images_without_keypoints(database_path: Path) -> list[str]:
    """The database's images whose extraction found no keypoint (no texture, all sky)."""
    with pycolmap.Database.open(str(database_path)) as db:
        return [image.name for image in db.read_all_images()
                if db.num_keypoints_for_image(image.image_id) == 0]


def reader_options(camera_model: str | None, camera_params: str | None
                   ) -> pycolmap.ImageReaderOptions:
    """COLMAP's image reader options (`colmap feature_extractor --ImageReader.*`); InputError
    for a camera model COLMAP does not know or parameters that do not fit it."""
    reader = pycolmap.ImageReaderOptions()
    models = pycolmap.CameraModelId.__members__
    if camera_model:
        if camera_model not in models or camera_model == "INVALID":
            known = ", ".join(m for m in models if m != "INVALID")
            raise InputError(f"--camera_model {camera_model!r} is not one of COLMAP's: {known}")
        reader.camera_model = camera_model
    if camera_params:
        camera = pycolmap.Camera.create_from_model_name(1, reader.camera_model, 1.0, 1, 1)
        values = camera_params.split(",")
        try:
            [float(v) for v in values]
        except ValueError:
            raise InputError(f"--camera_params: not numbers: {camera_params!r}") from None
        if len(values) != len(camera.params):
            raise InputError(f"--camera_params: {reader.camera_model} takes "
                             f"{len(camera.params)} comma-separated values "
                             f"({camera.params_info}), got {camera_params!r}")
        reader.camera_params = camera_params
    return reader


def extract(folder: ImageFolder, database_path: Path, state: RunState, *,
            camera_mode: str = "auto", camera_model: str | None = None,
            camera_params: str | None = None,
            extraction: pycolmap.FeatureExtractionOptions | None = None,
            options: RunOptions | None = None, progress: bool = True) -> dict:
    """SIFT features of the folder's images that the database lacks. Returns the step's
    details: images extracted and reused, cameras."""
    options = options or RunOptions()
    extraction = extraction or pycolmap.FeatureExtractionOptions()
    reader = reader_options(camera_model, camera_params)
    done = images_with_features(database_path)
    groups = folder.camera_groups(camera_mode)
    todo = {label: [n for n in names if n not in done] for label, names in groups.items()}
    todo = {label: names for label, names in todo.items() if names}
    count = sum(len(names) for names in todo.values())
    if done and count and (camera_model or camera_params):
        logger.warning("the camera options apply to the %d new images only; the %d images "
                       "already in %s keep their cameras", count, len(done), database_path)
    bar = tqdm(total=count, desc="features", unit="img", disable=not progress or not count)
    try:
        # errors only: COLMAP warns of the memory of CPU SIFT on every call (every chunk); an
        # image it cannot read is found below
        with colmap_warnings_only(2):
            for label, names in todo.items():
                _extract_group(folder, database_path, state, label, names, groups[label], done,
                               reader, extraction, camera_mode, options, bar)
    finally:
        bar.close()
    extracted = images_with_features(database_path)
    unread = [n for n in folder.names if n not in extracted]
    if unread:
        logger.warning("COLMAP could not read %d image(s), e.g. %s: they are left out",
                       len(unread), unread[:3])
    empty = images_without_keypoints(database_path) if database_path.exists() else []
    if empty:
        logger.warning("%d image(s) without a SIFT keypoint (no texture), e.g. %s", len(empty),
                       empty[:3])
    cameras = len(set(extracted.values()))
    return {"extracted": count - len(unread), "reused": len(done), "unreadable": unread,
            "without_keypoints": empty, "cameras": cameras, "camera_mode": camera_mode,
            "summary": f"{count - len(unread)} images extracted, {len(done)} reused, "
                       f"{cameras} camera(s)"}


def _extract_group(folder, database_path, state, label, names, members, done, reader,
                   extraction, camera_mode, options, bar) -> None:
    """One camera group's missing images, in chunks; its camera from the database when an
    earlier chunk or run made it."""
    camera_id = state.cameras.get(label)
    if camera_id is None:  # an image of the group extracted by a run that kept no record
        camera_id = next((done[n] for n in members if n in done), None)
    for start in range(0, len(names), options.extraction_chunk):
        chunk = names[start:start + options.extraction_chunk]
        per_image = camera_mode == "per_image"
        reader.existing_camera_id = -1 if camera_id is None or per_image else int(camera_id)
        pycolmap.extract_features(
            database_path, folder.path, image_names=chunk,
            camera_mode=pycolmap.CameraMode.PER_IMAGE if per_image else
            pycolmap.CameraMode.SINGLE,
            reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
        extracted = images_with_features(database_path)
        first = next((n for n in chunk if n in extracted), None)
        if first is not None and not per_image:
            camera_id = extracted[first]
            state.cameras[label] = int(camera_id)
        bar.update(len(chunk))
        state.save()
