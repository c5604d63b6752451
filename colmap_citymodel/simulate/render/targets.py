"""Check-point targets: black-white quadrant discs painted on the true surfaces at the
simulator's check points, and where each one appears in each image.

The quadrants meet at the check point itself, so the target's centre in an image (the saddle
point of its four quadrants) is the check point's projection through the true camera (with its
lens distortion). That is what `gcp_list.txt` lists per image where the target is seen.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..flight import Flight
from .noise import edge
from .surfaces import Hits, plane_axes

#: A target's surface may deviate this far (m) from the plane through its centre and still be
#: painted (the true surfaces are exactly planar; this only absorbs rounding).
PLANE_TOLERANCE = 0.03
#: A target counts as seen in an image if it is not occluded (the ray to its centre ends within
#: this of it, m), seen at most MAX_INCIDENCE_DEG off its normal and at least MIN_RADIUS_PX
#: pixels across (its radius), its centre at least MARGIN_PX inside the image.
OCCLUSION_TOLERANCE, MAX_INCIDENCE_DEG, MIN_RADIUS_PX, MARGIN_PX = 0.02, 75.0, 3.0, 8.0
#: Reflectance of the white and black quadrants.
WHITE, BLACK = 0.85, 0.04


@dataclass
class Targets:
    ids: np.ndarray  # (C,)
    centres: np.ndarray  # (C,3) local
    normals: np.ndarray  # (C,3) unit, the surface's
    u: np.ndarray  # (C,3) the quadrants' axes in the surface
    v: np.ndarray
    radius: float
    near: np.ndarray  # (T,) bool: triangles a target may lie on

    @classmethod
    def on_scene(cls, ids, centres: np.ndarray, raycaster, triangles: np.ndarray,
                 radius: float) -> Targets:
        """Targets at `centres` (local) on the true mesh (its RaycastingScene and (T,3,3)
        triangles): each takes the normal of the nearest triangle."""
        import open3d as o3d

        centres = np.asarray(centres, np.float64).reshape(-1, 3)
        near = np.zeros(len(triangles), bool)
        if not len(centres):
            z = np.zeros((0, 3))
            return cls(np.asarray(ids), centres, z, z, z, radius, near)
        closest = raycaster.compute_closest_points(o3d.core.Tensor(centres.astype(np.float32)))
        normals = closest["primitive_normals"].numpy().astype(np.float64)
        normals /= np.linalg.norm(normals, axis=1, keepdims=True)
        u, v = plane_axes(normals)
        lo, hi = triangles.min(1), triangles.max(1)
        for c in centres:
            near |= np.all((lo <= c + radius) & (hi >= c - radius), axis=1)
        return cls(np.asarray(ids), centres, normals, u, v, float(radius), near)

    def paint(self, h: Hits, albedo: np.ndarray, gloss: np.ndarray) -> None:
        """Paint the targets over the hits' reflectance (in place)."""
        if not self.near.any():
            return
        cand = np.flatnonzero(self.near[h.tri])
        if not len(cand):
            return
        p = h.p[cand].astype(np.float64)
        for c, n, u, v in zip(self.centres, self.normals, self.u, self.v):
            d = p - c
            du, dv = d @ u, d @ v
            on = (np.abs(d @ n) < PLANE_TOLERANCE) & (du * du + dv * dv < (1.5 * self.radius) ** 2)
            if not on.any():
                continue
            i = cand[on]
            w = h.footprint[i]
            disc = edge(self.radius - np.hypot(du[on], dv[on]), 0.0, w)
            sign = (2 * edge(du[on], 0.0, w) - 1) * (2 * edge(dv[on], 0.0, w) - 1)
            paint = (0.5 * (WHITE + BLACK) + 0.5 * (WHITE - BLACK) * sign)[:, None]
            albedo[i] = albedo[i] * (1 - disc)[:, None] + paint * disc[:, None]
            gloss[i] *= 1 - disc

    def observations(self, flight: Flight, raycaster) -> list[tuple[int, int, np.ndarray]]:
        """(frame index, target id, pixel (COLMAP convention: the top-left pixel's corner is
        0, 0)) of every target seen in every key frame."""
        import open3d as o3d

        out = []
        cos_max = np.cos(np.radians(MAX_INCIDENCE_DEG))
        for k in range(len(flight.names)):
            uv, z = flight.project(k, self.centres)
            ray = self.centres - flight.centres[k]
            dist = np.linalg.norm(ray, axis=1)
            ray /= dist[:, None]
            ok = (z > 0.5) & (uv[:, 0] >= MARGIN_PX) & (uv[:, 0] < flight.width - MARGIN_PX) \
                & (uv[:, 1] >= MARGIN_PX) & (uv[:, 1] < flight.height - MARGIN_PX) \
                & (np.abs(np.einsum("ij,ij->i", ray, self.normals)) >= cos_max) \
                & (flight.focal * self.radius / np.maximum(z, 1e-9) >= MIN_RADIUS_PX)
            idx = np.flatnonzero(ok)
            if not len(idx):
                continue
            rays = np.c_[np.repeat(flight.centres[k][None], len(idx), 0), ray[idx]]
            hit = raycaster.cast_rays(o3d.core.Tensor(rays.astype(np.float32)))["t_hit"].numpy()
            for j in idx[hit >= dist[idx] - OCCLUSION_TOLERANCE]:
                out.append((k, int(self.ids[j]), uv[j]))
        return out
