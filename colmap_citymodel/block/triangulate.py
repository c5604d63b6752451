"""triangulate: tie points of a known-pose block (COLMAP's point triangulator, poses held).

``pycolmap.triangulate_points`` (``colmap point_triangulator``) builds tracks from the verified
matches of the database and triangulates them with the poses of the input model (import-eo's
``sparse``), then refines the points in bundle adjustments with every frame pose, the rig and the
intrinsics held fixed (`fix_existing_frames`). COLMAP's log goes to OUTPUT/colmap.log. The result is the input of refine (``--gnss`` import-eo's gnss.txt).
"""

from __future__ import annotations

import logging
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from ..errors import InputError
from ..files import quiet_colmap

logger = logging.getLogger(__name__)


@dataclass
class TriangulationResult:
    output_path: Path
    num_images: int
    num_images_with_points: int
    num_points3D: int
    num_observations: int
    mean_track_length: float
    max_pose_change_m: float
    """Largest projection centre change against the input (0 when the poses were held)."""

    def summary(self) -> str:
        return (f"triangulate: {self.num_points3D} tie points, {self.num_observations} "
                f"observations (track length {self.mean_track_length:.2f}) in "
                f"{self.num_images_with_points} of {self.num_images} images; written to "
                f"{self.output_path}")


def images_with_points(rec: pycolmap.Reconstruction, min_points: int = 1) -> int:
    return sum(1 for image in rec.images.values() if image.num_points3D >= min_points)


def main(database, input_path, output_path, *, min_points_per_image: int = 1
         ) -> TriangulationResult:
    """Triangulate the database's verified matches with the poses of `input_path`."""
    database, input_path, output_path = Path(database), Path(input_path), Path(output_path)
    if not database.is_file():
        raise InputError("COLMAP database does not exist", database)
    try:
        rec = pycolmap.Reconstruction(str(input_path))
    except Exception as error:
        raise InputError(f"cannot read COLMAP model: {error}", input_path) from None
    before = {i.name: np.asarray(i.projection_center()) for i in rec.images.values()}
    output_path.mkdir(parents=True, exist_ok=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.fix_existing_frames = True  # the imported poses stay as they are
    options.ba_refine_sensor_from_rig = False
    options.ba_refine_focal_length = False
    options.ba_refine_extra_params = False
    with tempfile.TemporaryDirectory(prefix="colmap_citymodel_images_") as images, \
            quiet_colmap(output_path / "colmap.log"):
        try:
            result = pycolmap.triangulate_points(rec, str(database), images, str(output_path),
                                                 clear_points=True, options=options,
                                                 refine_intrinsics=False)
        except Exception as error:
            raise InputError(f"COLMAP's point triangulator failed: {error}", database) from None
    change = max((float(np.linalg.norm(np.asarray(i.projection_center()) - before[i.name]))
                  for i in result.images.values() if i.name in before), default=0.0)
    return TriangulationResult(output_path, result.num_images(),
                               images_with_points(result, min_points_per_image),
                               result.num_points3D(), result.compute_num_observations(),
                               result.compute_mean_track_length(), change)
