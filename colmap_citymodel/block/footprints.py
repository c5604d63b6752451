"""Image footprints on the ground: where each camera of a known-pose block looks.

A footprint is found by casting rays through points of the image border (the four corners and
`border_points` more along each edge, distortion included through the camera model) onto the
city model's triangle mesh and a horizontal terrain plane, whichever is hit first. A ray that
hits neither within `max_distance` (above the horizon) ends at that distance and is dropped
vertically onto the terrain plane. The footprint is the convex hull of the hits in plan view
(x, y of the local frame), a shapely polygon: an oblique image over buildings sees roofs in
front of the terrain, and its hull stays one simple polygon.

Rays are cast with Open3D's `RaycastingScene` (float32; at a local frame's coordinates of a few
kilometres, centimetres). Mulder (4.1.1) moves each oblique camera along its principal ray to
the ground and pairs images by the distance of those points; the footprint polygons used here
hold the same idea and also the images' extent, so the overlap can be measured.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap
import shapely
from shapely.geometry import MultiPoint, Polygon


@dataclass
class FootprintOptions:
    border_points: int = 4
    """Extra points per image edge besides the corners."""
    max_distance: float = 5000.0
    """Metres; rays hitting neither model nor terrain end here (then dropped onto the terrain)."""


def border_pixels(width: int, height: int, border_points: int) -> np.ndarray:
    """(K, 2) pixel positions around the image border, corners included, in order."""
    t = np.linspace(0.0, 1.0, border_points + 2)[:-1]
    w, h = float(width), float(height)
    top = np.c_[t * w, np.zeros_like(t)]
    right = np.c_[np.full_like(t, w), t * h]
    bottom = np.c_[w - t * w, np.full_like(t, h)]
    left = np.c_[np.zeros_like(t), h - t * h]
    return np.vstack([top, right, bottom, left])


def image_rays(image: pycolmap.Image, camera: pycolmap.Camera, pixels: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
    """(origin (3,), unit directions (K, 3)) in the model's frame of rays through `pixels`."""
    pose = image.cam_from_world()
    rotation = np.asarray(pose.rotation.matrix())
    normalised = np.asarray(camera.cam_from_img(np.asarray(pixels, float)))
    directions = np.c_[normalised, np.ones(len(normalised))] @ rotation  # R^T d, row-wise
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    return np.asarray(image.projection_center()), directions


class GroundSurface:
    """The terrain plane z = `terrain_height` and, if given, a triangle mesh above it."""

    def __init__(self, terrain_height: float, vertices: np.ndarray | None = None,
                 triangles: np.ndarray | None = None):
        self.terrain_height = float(terrain_height)
        self.scene = None
        if vertices is not None and triangles is not None and len(triangles):
            import open3d as o3d

            self.scene = o3d.t.geometry.RaycastingScene()
            self.scene.add_triangles(o3d.core.Tensor(np.asarray(vertices, np.float32)),
                                     o3d.core.Tensor(np.asarray(triangles, np.uint32)))

    def hit(self, origins: np.ndarray, directions: np.ndarray, max_distance: float
            ) -> np.ndarray:
        """(K, 3) first hits of the rays (origins (K,3) or (3,), unit directions (K,3))."""
        origins = np.broadcast_to(np.asarray(origins, float), directions.shape)
        with np.errstate(divide="ignore", invalid="ignore"):
            t_plane = (self.terrain_height - origins[:, 2]) / directions[:, 2]
        t_plane = np.where((t_plane > 0) & np.isfinite(t_plane), t_plane, np.inf)
        t = t_plane
        if self.scene is not None:
            import open3d as o3d

            rays = o3d.core.Tensor(np.c_[origins, directions].astype(np.float32))
            t_mesh = self.scene.cast_rays(rays)["t_hit"].numpy().astype(float)
            t = np.minimum(t, t_mesh)
        far = ~(t <= max_distance)
        points = origins + np.where(far, max_distance, t)[:, None] * directions
        points[far, 2] = self.terrain_height
        return points


def footprint(image: pycolmap.Image, camera: pycolmap.Camera, ground: GroundSurface,
              options: FootprintOptions | None = None) -> Polygon:
    """The image's footprint: convex hull (plan view) of its border rays' hits."""
    options = options or FootprintOptions()
    pixels = border_pixels(camera.width, camera.height, options.border_points)
    origin, directions = image_rays(image, camera, pixels)
    hits = ground.hit(origin, directions, options.max_distance)
    hull = MultiPoint(hits[:, :2]).convex_hull
    return hull if isinstance(hull, Polygon) else Polygon()


def footprints(rec: pycolmap.Reconstruction, ground: GroundSurface,
               options: FootprintOptions | None = None) -> dict[str, Polygon]:
    """Footprint of every registered image of `rec`, by image name."""
    options = options or FootprintOptions()
    out = {}
    for image_id in sorted(rec.reg_image_ids()):
        image = rec.image(image_id)
        out[image.name] = footprint(image, rec.camera(image.camera_id), ground, options)
    return out


def overlapping_pairs(polygons: dict[str, Polygon], min_overlap: float
                      ) -> list[tuple[str, str, float]]:
    """(name1, name2, share) of every pair whose footprints overlap by more than `min_overlap`
    of the smaller footprint's area (name1 < name2)."""
    names = sorted(n for n, p in polygons.items() if not p.is_empty and p.area > 0)
    geoms = np.empty(len(names), dtype=object)
    geoms[:] = [polygons[n] for n in names]
    tree = shapely.STRtree(geoms)
    left, right = tree.query(geoms, predicate="intersects")
    keep = left < right
    left, right = left[keep], right[keep]
    areas = np.array([g.area for g in geoms])
    inter = shapely.area(shapely.intersection(np.take(geoms, left), np.take(geoms, right)))
    share = inter / np.minimum(areas[left], areas[right])
    ok = share > min_overlap
    return [(names[i], names[j], float(s)) for i, j, s in zip(left[ok], right[ok], share[ok])]
