"""Render a simulated flight into an image folder: one JPEG per key frame with EXIF GPS and
(optionally) DJI XMP from the simulated GNSS, and `gcp_list.txt` with the check-point targets'
image positions."""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from ..flight import Flight
from ..scene import TrueScene
from .metadata import RenderedTags, dji_angles, exif_bytes, geographic, write_gcp_list, xmp_bytes
from .options import RenderOptions
from .renderer import Renderer
from .sensor import expose
from .targets import Targets

logger = logging.getLogger(__name__)

#: Random streams of the renderer (np.random.default_rng([seed, stage, ...])).
STAGE_SENSOR, STAGE_ATTITUDE = 31, 32
#: Standard deviation (deg) of the aircraft's pitch and roll in flight (wind), written as
#: FlightPitchDegree / FlightRollDegree.
FLIGHT_TILT_SIGMA_DEG = 2.0


def image_metadata(flight: Flight, crs, origin: np.ndarray, gnss_crs: np.ndarray,
                   sigma, takeoff_height: float, options: RenderOptions,
                   seed: int) -> list[RenderedTags]:
    """What each key frame's EXIF and XMP say: the GNSS position (model CRS -> WGS84), the
    heights, the camera's attitude with the gimbal's noise (options.attitude_sigma_deg), the
    aircraft's (heading along the camera's, tilted by wind) and the RTK status."""
    rng = np.random.default_rng([seed, STAGE_ATTITUDE])
    lat, lon, north = geographic(crs, gnss_crs[:, :2])
    sigma = tuple(float(s) for s in sigma)
    rtk = max(sigma[0], sigma[1]) <= options.rtk_sigma_limit
    noise = rng.normal(0.0, 1.0, (len(flight.names), 3)) * np.asarray(options.attitude_sigma_deg)
    tilt = rng.normal(0.0, FLIGHT_TILT_SIGMA_DEG, (len(flight.names), 2))
    out = []
    for k, name in enumerate(flight.names):
        yaw, pitch, roll = dji_angles(flight.rotations[k], float(north[k]))
        gimbal = ((yaw + noise[k, 0] + 180.0) % 360.0 - 180.0, pitch + noise[k, 1],
                  roll + noise[k, 2])
        out.append(RenderedTags(
            name=name, index=k, latitude=float(lat[k]), longitude=float(lon[k]),
            altitude=float(gnss_crs[k, 2]),
            relative_altitude=float(gnss_crs[k, 2] - origin[2] - takeoff_height),
            gimbal=gimbal, flight=(yaw, float(tilt[k, 0]), float(tilt[k, 1])), sigma=sigma,
            rtk=rtk))
    return out


def render_flight(out: Path, *, flight: Flight, scene: TrueScene, footprints,
                  sidewalk_width: float, takeoff_height: float, crs, origin: np.ndarray,
                  gnss_crs: np.ndarray, gnss_sigma, checkpoints, options: RenderOptions,
                  seed: int, progress: bool = True, threads: int = 0) -> dict:
    """Render every key frame of `flight` into `out`/images/ (see the module docstring);
    returns statistics (seconds per image, targets seen). `checkpoints`: the simulator's
    CheckPoints (local coordinates), painted as targets; `takeoff_height`: the local ground
    height RelativeAltitude counts from."""
    from PIL import Image
    from tqdm import tqdm

    seed = seed if options.seed is None else options.seed
    images = Path(out) / "images"
    images.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    renderer = Renderer(scene, flight, footprints, sidewalk_width, options, seed,
                        threads=threads)
    raycaster = renderer.raycaster
    targets = Targets.on_scene(checkpoints.ids, checkpoints.xyz, raycaster, scene.triangles,
                               options.target_radius)
    renderer.targets = targets
    metadata = image_metadata(flight, crs, origin, gnss_crs, gnss_sigma, takeoff_height,
                              options, seed)
    set_up = time.perf_counter() - start
    cpu, wall = [], []
    for k in tqdm(range(len(flight.names)), desc="render", unit="img",
                  disable=None if progress else True):
        t0, c0 = time.perf_counter(), time.process_time()
        radiance, mask = renderer.render(k)
        pixels = expose(radiance, mask, options, np.random.default_rng([seed, STAGE_SENSOR, k]))
        _save(images / flight.names[k], Image.fromarray(pixels), metadata[k], flight, options)
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    seen = targets.observations(flight, raycaster)
    lines = write_gcp_list(images / "gcp_list.txt", crs, origin, targets, seen, flight.names)
    stats = {"num_images": len(flight.names), "image_size": [flight.width, flight.height],
             "set_up_seconds": set_up, "seconds_per_image": float(np.mean(wall)),
             "cpu_seconds_per_image": float(np.mean(cpu)), "threads": threads,
             "num_targets": int(len(targets.ids)), "num_target_observations": lines,
             "rtk": bool(metadata[0].rtk) if metadata else False, "xmp": options.xmp}
    (Path(out) / "render.json").write_text(json.dumps(stats, indent=2))
    logger.info("rendered %d images (%.1f s each, %.1f s CPU), %d target observations in "
                "gcp_list.txt", len(flight.names), stats["seconds_per_image"],
                stats["cpu_seconds_per_image"], lines)
    return stats


def _save(path: Path, image, meta: RenderedTags, flight: Flight,
          options: RenderOptions) -> None:
    extra = {}
    if options.xmp == "dji":
        extra["xmp"] = xmp_bytes(meta, flight.width, flight.height, flight.focal)
    image.save(path, "JPEG", quality=options.jpeg_quality,
               exif=exif_bytes(meta, flight.width, flight.height, flight.focal), **extra)
