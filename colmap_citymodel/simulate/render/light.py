"""Sun and sky: direct sunlight with cast shadows (a second ray from each lit surface towards
the sun), light from the sky dome, the sky seen through glass, the sky itself and aerial haze.

Radiance is in relative linear units: a white surface facing the sun is about 1; the camera's
exposure (sensor.py) scales the image afterwards.
"""

from __future__ import annotations

import math

import numpy as np

from .options import RenderOptions

#: Colour of direct sunlight and of the sky's light (linear RGB, relative): a clear day.
SUN_COLOUR = np.array([1.0, 0.96, 0.9], np.float32)
SKY_LIGHT_COLOUR = np.array([0.78, 0.87, 1.05], np.float32)
#: Radiance of the sky at the horizon and at the zenith (linear RGB).
SKY_HORIZON = np.array([0.82, 0.88, 0.98], np.float32)
SKY_ZENITH = np.array([0.30, 0.46, 0.86], np.float32)
#: Light bounced from the ground onto surfaces that face down, relative to the sky's.
BOUNCE = 0.25
#: Offset (m) of a shadow ray's start from its surface, against self-shadowing.
SHADOW_OFFSET = 0.01


class Light:
    def __init__(self, options: RenderOptions):
        az = math.radians(options.sun_azimuth_deg)
        el = math.radians(options.sun_elevation_deg)
        self.sun = np.array([math.sin(az) * math.cos(el), math.cos(az) * math.cos(el),
                             math.sin(el)], np.float32)
        self.sky_light = float(options.sky_light)
        self.haze = float(options.haze_distance)

    def sky(self, dirs: np.ndarray) -> np.ndarray:
        """Radiance of the sky in unit directions `dirs` (N,3); below the horizon its
        horizon colour (what haze fades distant things into)."""
        up = np.clip(dirs[:, 2], 0.0, 1.0)
        k = np.sqrt(up)[:, None]
        colour = SKY_HORIZON * (1 - k) + SKY_ZENITH * k
        glow = np.exp((dirs @ self.sun - 1.0) * 12.0)[:, None] * 0.6
        return (colour + glow * SUN_COLOUR).astype(np.float32)

    def sunlit(self, raycaster, points: np.ndarray, normals: np.ndarray,
               threads: int = 0) -> np.ndarray:
        """(N,) 1 where the sun reaches the surface, 0 in shadow or facing away (open3d's
        ray caster on `threads` threads, 0: all)."""
        import open3d as o3d

        facing = normals @ self.sun > 0.0
        lit = np.zeros(len(points), np.float32)
        idx = np.flatnonzero(facing)
        if len(idx):
            start = points[idx] + normals[idx] * SHADOW_OFFSET
            rays = np.concatenate([start, np.broadcast_to(self.sun, start.shape)], 1)
            hit = raycaster.cast_rays(o3d.core.Tensor(rays.astype(np.float32, copy=False)),
                                      nthreads=threads)["t_hit"].numpy()
            lit[idx] = ~np.isfinite(hit)
        return lit

    def shade(self, albedo: np.ndarray, gloss: np.ndarray, normals: np.ndarray,
              views: np.ndarray, lit: np.ndarray) -> np.ndarray:
        """Radiance leaving each surface towards the camera: diffuse sun and sky light, plus
        the sky mirrored by glossy surfaces (Schlick's Fresnel term)."""
        cos_sun = np.clip(normals @ self.sun, 0.0, None) * lit
        nz = normals[:, 2:3]
        sky = self.sky_light * ((0.5 + 0.5 * nz) + BOUNCE * (0.5 - 0.5 * nz))
        irradiance = cos_sun[:, None] * SUN_COLOUR + sky * SKY_LIGHT_COLOUR
        radiance = albedo * irradiance
        if np.any(gloss > 0):
            g = np.flatnonzero(gloss > 0)
            cos = np.abs(np.einsum("ij,ij->i", views[g], normals[g]))
            fresnel = 0.04 + 0.96 * (1.0 - cos) ** 5
            mirrored = views[g] - 2.0 * (views[g] * normals[g]).sum(1, keepdims=True) * normals[g]
            reflected = self.sky(mirrored) * (mirrored[:, 2:3] > 0) + 0.1 * (
                mirrored[:, 2:3] <= 0)
            radiance[g] += (gloss[g] * fresnel)[:, None] * reflected * 0.8
        return radiance

    def hazy(self, radiance: np.ndarray, distance: np.ndarray) -> np.ndarray:
        """Aerial perspective: contrast fades with distance into the horizon's colour."""
        keep = np.exp(-distance / self.haze).astype(np.float32)[:, None]
        return radiance * keep + SKY_HORIZON * (1 - keep)
