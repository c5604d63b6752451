"""The camera's sensor and processing: auto exposure with a metering error, vignetting, read
and shot noise, the sRGB curve and 8-bit quantisation."""

from __future__ import annotations

import numpy as np

from .options import RenderOptions

#: Linear value the auto exposure puts the scene's geometric mean luminance at (18 % grey).
MIDDLE_GREY = 0.18
#: Levels of the lookup table from linear light to 8-bit sRGB.
LUT_LEVELS = 16384


def _srgb_lut() -> np.ndarray:
    c = np.linspace(0.0, 1.0, LUT_LEVELS)
    s = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return np.clip(np.rint(s * 255.0), 0, 255).astype(np.uint8)


_LUT = _srgb_lut()


def expose(radiance: np.ndarray, scene_mask: np.ndarray, options: RenderOptions,
           rng: np.random.Generator) -> np.ndarray:
    """8-bit sRGB image (H,W,3) from linear radiance (H,W,3); the exposure meters the pixels
    in `scene_mask` (what the camera sees of the city, not the sky)."""
    h, w, _ = radiance.shape
    lum = radiance @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    metered = lum[scene_mask] if scene_mask.any() else lum.ravel()
    mean = float(np.exp(np.mean(np.log(np.maximum(metered, 1e-4)))))
    gain = MIDDLE_GREY / mean * 2.0 ** rng.normal(0.0, options.exposure_jitter)
    image = radiance * np.float32(gain)
    if options.vignetting:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r2 = ((xx - w / 2 + 0.5) ** 2 + (yy - h / 2 + 0.5) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
        image *= (1.0 - options.vignetting * r2)[:, :, None]
    if options.read_noise or options.shot_noise:
        sigma = np.sqrt(options.read_noise ** 2 + options.shot_noise * np.clip(image, 0, None))
        image = image + sigma * rng.standard_normal(image.shape, dtype=np.float32)
    index = np.clip(image * (LUT_LEVELS - 1), 0, LUT_LEVELS - 1).astype(np.int32)
    return _LUT[index]
