"""The image folder of a run: its images as COLMAP names them, what their EXIF and XMP say
(block.image_metadata), the cameras they share, and `images.csv` with one row per image."""

from __future__ import annotations

import csv
import io
import logging
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..block.image_metadata import ImageMetadata, image_files, read_folder_metadata
from .state import write_text_atomic

logger = logging.getLogger(__name__)

CAMERA_MODES = ("auto", "single", "per_image")


@dataclass
class ImageFolder:
    """The images of a run and their metadata, in name order."""

    path: Path
    metadata: list[ImageMetadata]

    @property
    def names(self) -> list[str]:
        return [m.name for m in self.metadata]

    def with_position(self) -> list[str]:
        return [m.name for m in self.metadata if m.has_position]

    def camera_groups(self, mode: str = "auto") -> dict[str, list[str]]:
        """Image names by the camera COLMAP gives them: "auto" one camera per camera body and
        image size (EXIF make, model, serial number, focal length, width x height; images
        without EXIF by their size alone, as frames of one video), "single" one for all,
        "per_image" one each."""
        if mode == "single":
            return {"all images": self.names}
        if mode == "per_image":
            return {name: [name] for name in self.names}
        groups: dict[str, list[str]] = {}
        for meta in self.metadata:
            groups.setdefault(camera_label(meta), []).append(meta.name)
        return groups

    def summary(self) -> dict:
        """What the metadata holds, for the run's report: positions, their sources and sigmas,
        RTK solutions, attitude."""
        located = [m for m in self.metadata if m.has_position]
        sigma_sources = Counter(m.sigma()[1] or "default" for m in located)
        rtk = Counter(m.rtk_status for m in self.metadata if m.rtk_status is not None)
        out = {"images": len(self.metadata), "with_position": len(located),
               "position_sources": dict(Counter(m.position_source for m in located)),
               "altitude_sources": dict(Counter(m.altitude_source for m in located)),
               "sigma_sources": dict(sigma_sources), "rtk": dict(rtk),
               "with_gimbal_attitude": sum(m.gimbal is not None for m in self.metadata),
               "with_flight_attitude": sum(m.flight is not None for m in self.metadata),
               "altitude_types": dict(Counter(m.altitude_type for m in self.metadata
                                              if m.altitude_type))}
        rtk_sigmas = np.array([m.sigma()[0] for m in located if m.sigma()[1] == "rtk"])
        if len(rtk_sigmas):
            out["rtk_sigma_median_m"] = np.round(np.median(rtk_sigmas, axis=0), 4).tolist()
        return out


def camera_label(meta: ImageMetadata) -> str:
    """A readable name of the camera `meta` was taken with (ImageMetadata.camera_key)."""
    make, model, serial, focal, width, height = meta.camera_key()
    parts = [p for p in (make, model, f"#{serial}" if serial else "") if p]
    if focal is not None:
        parts.append(f"{focal:g} mm")
    parts.append(f"{width}x{height}")
    return " ".join(parts)


def read_image_folder(image_path: str | Path, progress: bool = True) -> ImageFolder:
    """The images below `image_path` and their metadata (GNSSError for a missing folder or one
    without images)."""
    image_path = Path(image_path)
    names = image_files(image_path)
    return ImageFolder(image_path, read_folder_metadata(image_path, names, progress))


#: images.csv columns: ImageMetadata fields, tuples split into their parts.
CSV_COLUMNS = ("name", "width", "height", "make", "model", "serial", "focal_length_mm",
               "latitude", "longitude", "altitude", "position_source", "altitude_source",
               "altitude_type", "relative_altitude", "rtk_flag", "rtk_status", "sigma_east",
               "sigma_north", "sigma_up", "sigma_source", "gimbal_yaw", "gimbal_pitch",
               "gimbal_roll", "flight_yaw", "flight_pitch", "flight_roll", "camera")


def write_images_csv(folder: ImageFolder, path: Path) -> None:
    """One row per image: position, its sources, sigma (ImageMetadata.sigma; empty: the
    default), RTK status, gimbal and flight attitude (degrees), camera."""
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(CSV_COLUMNS)
    for meta in folder.metadata:
        row = meta.todict()
        sigma, source = meta.sigma()
        row.update(zip(("sigma_east", "sigma_north", "sigma_up"),
                       sigma if sigma is not None else (None,) * 3))
        row["sigma_source"] = source
        for what in ("gimbal", "flight"):
            angles = getattr(meta, what) or (None,) * 3
            row.update(zip((f"{what}_yaw", f"{what}_pitch", f"{what}_roll"), angles))
        row["camera"] = camera_label(meta)
        writer.writerow([_cell(row.get(c)) for c in CSV_COLUMNS])
    write_text_atomic(path, buffer.getvalue())


def _cell(value) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    if isinstance(value, (float, np.floating)):
        return f"{float(value):.10g}"
    return str(value)
