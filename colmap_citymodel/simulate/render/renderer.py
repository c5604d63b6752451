"""The ray-casting renderer: one ray per pixel through the true lens (COLMAP's camera model
with the flight's true distortion), the first hit's material lit by the sun (with a shadow ray)
and the sky, aerial haze; pixels on edges of the geometry supersampled.

All rays of an image are cast at once with open3d's RaycastingScene (Embree on the CPU, no GPU
or display): one cast for the primary hits, one for the shadows, a small one for the edges.
"""

from __future__ import annotations

import numpy as np

from .. import scene as sc
from ..flight import Flight
from ..mapping import make_camera
from . import palette as pal
from .ground import GroundPaint
from .light import Light
from .materials import Materials
from .noise import Noise
from .options import RenderOptions
from .palette import Styles
from .surfaces import Hits, SceneTables
from .targets import Targets

#: Keys of pixels that hit no triangle of the scene: the sky, and the distant ground beyond
#: the scene's terrain (a plane at the terrain's median height); the terrain's own key.
KEY_SKY, KEY_TERRAIN, KEY_FAR_GROUND = -1, -2, -3
#: Reflectance of the distant ground (a muted mix of fields, roofs and streets).
FAR_GROUND = pal.linear((112, 116, 98))


class Renderer:
    """Renders the key frames of `flight` in the true scene (local coordinates)."""

    def __init__(self, scene: sc.TrueScene, flight: Flight, footprints, sidewalk_width: float,
                 options: RenderOptions, seed: int, targets: Targets | None = None,
                 threads: int = 0):
        self.flight = flight
        self.options = options
        self.threads = threads
        self.raycaster = scene.raycasting_scene()
        self.tables = SceneTables.of(scene)
        num_objects = int(self.tables.objects.max()) + 1 if len(self.tables.objects) else 0
        self.noise = Noise(seed)
        ground = scene.triangles[scene.labels == sc.LABEL_GROUND].reshape(-1, 3)
        extent = ground if len(ground) else scene.triangles.reshape(-1, 3)
        self.far_ground_z = float(np.median(extent[:, 2]))
        paint = GroundPaint(footprints, extent.min(0), extent.max(0), sidewalk_width,
                            options.road_width)
        self.materials = Materials(Styles.draw(num_objects, seed), self.noise, paint)
        self.light = Light(options)
        self.targets = targets
        self.camera = make_camera(flight, true=True)
        jj, ii = np.meshgrid(np.arange(flight.width) + 0.5, np.arange(flight.height) + 0.5)
        self.pixel_dirs = self._directions(np.stack([jj.ravel(), ii.ravel()], axis=1))
        self.pixel_angle = 1.0 / flight.focal

    def _directions(self, pixels: np.ndarray) -> np.ndarray:
        """Unit viewing directions in the camera frame of pixel positions (COLMAP's
        convention), through the true lens."""
        xy = self.camera.cam_from_img(np.asarray(pixels, dtype=np.float64))
        d = np.c_[xy, np.ones(len(xy))]
        return (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)

    def shade(self, centre: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Radiance (N,3) seen along the unit rays `dirs` (N,3, world) from `centre`, and each
        ray's key (the face it hit, or KEY_*) for finding edges."""
        import open3d as o3d

        origin = np.asarray(centre, np.float32)
        rays = np.concatenate([np.broadcast_to(origin, dirs.shape), dirs], axis=1)
        cast = self.raycaster.cast_rays(o3d.core.Tensor(rays), nthreads=self.threads)
        t = cast["t_hit"].numpy()
        tri = cast["primitive_ids"].numpy()
        hit = np.isfinite(t)
        radiance = np.empty((len(dirs), 3), np.float32)
        key = np.full(len(dirs), KEY_SKY, np.int64)
        if hit.any():
            h = Hits.of(self.tables, origin, dirs[hit], t[hit], tri[hit], self.pixel_angle)
            radiance[hit] = self._surface(h)
            key[hit] = np.where(h.label == sc.LABEL_GROUND, KEY_TERRAIN, h.face)
        miss = np.flatnonzero(~hit)
        if len(miss):
            radiance[miss], far = self._background(origin, dirs[miss])
            key[miss[far]] = KEY_FAR_GROUND
        return radiance, key

    def _surface(self, h: Hits) -> np.ndarray:
        albedo, gloss = self.materials(h)
        if self.targets is not None:
            self.targets.paint(h, albedo, gloss)
        lit = self.light.sunlit(self.raycaster, h.p, h.normal, self.threads)
        radiance = self.light.shade(albedo, gloss, h.normal, h.view, lit)
        return self.light.hazy(radiance, h.distance)

    def _background(self, origin: np.ndarray, dirs: np.ndarray):
        """The sky, or below the horizon the distant ground: a plane at the terrain's median
        height, grass and fields in full sun, mostly lost in the haze."""
        radiance = self.light.sky(dirs)
        down = dirs[:, 2] < -1e-3
        height = origin[2] - self.far_ground_z
        far = down & (height > 0)
        if far.any():
            d = dirs[far]
            t = height / -d[:, 2]
            p = origin + d * t[:, None]
            w = t * self.pixel_angle / np.sqrt(np.maximum(-d[:, 2], 0.05))
            fields = self.noise.fbm(p[:, 0], p[:, 1], w, largest=40.0, smallest=3.0, gain=0.7,
                                    layer=40)
            albedo = FAR_GROUND * (1.0 + 0.4 * fields)[:, None]
            up = np.tile(np.array([0.0, 0.0, 1.0], np.float32), (len(d), 1))
            lit = self.light.shade(albedo, np.zeros(len(d), np.float32), up, d,
                                   np.ones(len(d), np.float32))
            radiance[far] = self.light.hazy(lit, t)
        return radiance, far

    def render(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """Linear radiance (H,W,3) of key frame k and the mask of pixels that see the ground or
        the city (not the sky)."""
        f = self.flight
        dirs = np.einsum("ij,jk->ik", self.pixel_dirs, f.rotations[k].astype(np.float32))
        radiance, key = self.shade(f.centres[k], dirs)
        image = radiance.reshape(f.height, f.width, 3)
        key = key.reshape(f.height, f.width)
        if self.options.edge_samples > 1:
            self._antialias(k, image, key)
        return image, key != KEY_SKY

    def _antialias(self, k: int, image: np.ndarray, key: np.ndarray) -> None:
        """Pixels whose key differs from a neighbour's: the mean of a stratified grid of
        sub-pixel rays (about edge_samples of them) instead of the centre ray."""
        edges = np.zeros(key.shape, bool)
        horizontal = key[:, 1:] != key[:, :-1]
        vertical = key[1:, :] != key[:-1, :]
        edges[:, 1:] |= horizontal
        edges[:, :-1] |= horizontal
        edges[1:, :] |= vertical
        edges[:-1, :] |= vertical
        ii, jj = np.nonzero(edges)
        if not len(ii):
            return
        m = max(int(round(np.sqrt(self.options.edge_samples))), 2)
        offsets = (np.arange(m) + 0.5) / m - 0.5
        ox, oy = np.meshgrid(offsets, offsets)
        px = (jj[:, None] + 0.5 + ox.ravel()[None]).ravel()
        py = (ii[:, None] + 0.5 + oy.ravel()[None]).ravel()
        f = self.flight
        dirs = np.einsum("ij,jk->ik", self._directions(np.stack([px, py], axis=1)),
                         f.rotations[k].astype(np.float32))
        radiance, _ = self.shade(f.centres[k], dirs)
        image[ii, jj] = radiance.reshape(len(ii), m * m, 3).mean(axis=1)
