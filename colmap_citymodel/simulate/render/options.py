"""Options of the renderer (`simulate --render`, the scenario's `[render]` table)."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class RenderOptions:
    """How the simulated flight's images are rendered: light, textures, sensor and metadata.

    The camera itself (image size, focal length, the true lens distortion `radial_k1`) is the
    flight's (`[flight]`); the scene is the sequence's true scene (`[details]`)."""

    enabled: bool = False
    """Render the key frames into `images/` (JPEG with EXIF GPS and DJI XMP) beside the
    simulated tie points; `simulate --render` sets it. Off by default: rendering costs a few
    seconds per image."""
    seed: int | None = None
    """Seed of the textures (colours, noise, curtains, markings) and of the sensor noise and
    metadata noise; None: the sequence's seed."""
    sun_azimuth_deg: float = 135.0
    """Direction of the sun, degrees clockwise from the local grid's north (+y): 135 is the
    south-east of a morning in central Europe."""
    sun_elevation_deg: float = 40.0
    """Sun above the horizon (deg); lower suns cast longer shadows."""
    sky_light: float = 0.35
    """Irradiance from the sky on an upward surface, relative to the sun's on a surface facing
    it: 0.35 is a clear day (shadows a third as bright as sunlit ground, as on a photograph)."""
    haze_distance: float = 5000.0
    """Distance (m) at which aerial haze has taken 63 % of an object's contrast: a clear day
    (meteorological visibility about 20 km, Koschmieder: 3.9 x this)."""
    exposure_jitter: float = 0.15
    """Standard deviation (stops, log2) of the auto exposure's error per image: a camera's
    metering varies by a fraction of a stop between frames."""
    vignetting: float = 0.25
    """Brightness lost in the image corners (fraction): a wide-angle drone lens, uncorrected."""
    read_noise: float = 0.004
    """Sensor read noise, standard deviation relative to white (linear values)."""
    shot_noise: float = 0.0004
    """Photon (shot) noise: variance per unit of linear signal; with read_noise about ISO 100
    on a 1" sensor."""
    jpeg_quality: int = 92
    """JPEG quality (Pillow, 1-95): a drone camera's default "fine" setting."""
    edge_samples: int = 4
    """Rays per pixel where the pixel straddles an edge of the geometry (a different triangle
    in a neighbouring pixel): the edge anti-aliased by supersampling; 1: no supersampling."""
    target_radius: float = 0.35
    """Radius (m) of the check-point targets painted on the true surfaces (black-white
    quadrant discs): about 10 pixels at 30 m with a 1150 px focal length."""
    xmp: str = "dji"
    """"dji": XMP as a DJI drone writes it (drone-dji: GPS, altitudes, gimbal and flight
    attitude, RTK flag and sigmas); "none": EXIF GPS only (a vehicle or hand-held camera)."""
    attitude_sigma_deg: tuple[float, float, float] = (2.0, 0.5, 0.5)
    """Noise (deg) of the gimbal yaw, pitch and roll written to the XMP: a drone's compass
    heading is good to about 2 deg, the gimbal's pitch and roll to a fraction of a degree."""
    rtk_sigma_limit: float = 0.1
    """GNSS whose stated horizontal sigma is at most this (m) is written as RTK fixed
    (RtkFlag 50, RtkStdLon/Lat/Hgt the stated sigmas); else as a single-point fix (RtkFlag
    0, no RTK sigmas), as a DJI drone without RTK writes it."""
    road_width: float = 7.0
    """Width (m) of the asphalt beyond the pavements (DetailOptions.sidewalk_width) along
    the footprints: two lanes with markings; further out the ground is grass."""

    def validate(self) -> list[str]:
        """Problems with these options, as messages (empty: none)."""
        problems = []
        if self.xmp not in ("dji", "none"):
            problems.append(f"render.xmp must be dji or none, got {self.xmp!r}")
        if not 1 <= self.jpeg_quality <= 95:
            problems.append("render.jpeg_quality must be 1..95")
        if not 0.0 < self.sun_elevation_deg <= 90.0:
            problems.append("render.sun_elevation_deg must be in (0, 90]")
        if self.edge_samples < 1:
            problems.append("render.edge_samples must be at least 1")
        if self.target_radius <= 0:
            problems.append("render.target_radius must be positive (metres)")
        return problems
