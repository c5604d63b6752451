"""A small synthetic street with known truth, built directly as pycolmap objects.

For unit tests, the refine benchmark and quick experiments: two rows of gabled and flat-roofed
buildings along a street (the LOD2 model), tie points on the facades and roofs of the *true*
scene (the model plus facade relief and balconies/clutter the model does not have), a UAV flying
along the street looking left and right, image observations with noise, GNSS with a bias of
metres. The "SfM" input is the truth moved into an arbitrary frame with a smooth drift.

The drift is a rate per metre of street, the same for every length: the block is bent upwards
along the street (z += drift * x^2 / length, x from the first station, length = stations x
spacing), so that its far end is about `drift` x length off (1 % by default: 0.44 m on the
default 48 m street, 6.6 m on the 666 m of 333 stations) and the bend's slope there is about
2 x drift whatever the length. That is the order of an image sequence's relative drift (a few
per mille to a few per cent of the distance travelled). A fixed curvature instead (z += c x^2)
would bend the block by a fraction of its length that grows with the length: tens of metres
on a street of a few hundred metres, more than a real block registered to GNSS, and enough
for the georegistration to reject the GNSS of many images as outliers. The cameras keep their
true rotations while their centres and the points are bent, so the input is not a bundle
adjustment optimum: its reprojection errors grow with the bend's slope (about 6-7 px RMS at
1 %, the same at every length).

The full simulator with COLMAP's own mapper is `simulate.sequence`; this module stays tiny and fast.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pycolmap

from ..citymodel.raw_model import CRSInfo
from ..citymodel.store import PlaneStore
from ..citymodel.build import store_from_polygons

# An ETRS89 / UTM 32N-like origin so that every test exercises 6-7 digit CRS coordinates.
DEFAULT_CRS_ORIGIN = (691000.0, 5335000.0, 500.0)


@dataclass
class StreetSceneOptions:
    num_stations: int = 24  # camera positions along the street (three images each)
    station_spacing: float = 2.0  # metres between stations
    street_half_width: float = 10.0  # facade to street centre
    flight_height: float = 18.0
    tilt_deg: float = 25.0  # side-looking cameras pitched down
    forward_tilt_deg: float = 10.0  # the forward-looking camera pitched down
    point_spacing: float = 1.0  # metres between sampled tie points on surfaces
    relief_sigma: float = 0.03  # facade/roof relief the model does not have (m)
    clutter_fraction: float = 0.05  # points on balconies/clutter 0.3-1.0 m off the planes
    image_noise_px: float = 0.5
    min_track_length: int = 3
    max_view_distance: float = 60.0
    width: int = 1280
    height: int = 800
    focal_length: float = 700.0
    gnss_sigma: tuple[float, float, float] = (1.0, 1.0, 1.5)  # white noise of the simulated GNSS
    gnss_bias: tuple[float, float, float] = (1.5, -1.0, 1.2)  # constant part of the GNSS error
    gnss_bias_wave: float = 0.5  # amplitude of the slowly varying part (m)
    drift: float = 0.01  # bend of the SfM input at the far end per metre of street
    seed: int = 0
    # The ground between the facades (`street_ground`): tie points on it about one per
    # ground_spacing^2 (0: none, the ground is not seen); the street rises by ground_slope
    # per metre along x (each building stands at the height of its centre); pavements
    # sidewalk_width wide along the facades stand kerb_height above the road.
    ground_spacing: float = 0.0
    ground_slope: float = 0.0
    kerb_height: float = 0.0
    sidewalk_width: float = 3.0


@dataclass
class StreetScene:
    store: PlaneStore  # the given LOD2 model (CRS coordinates, local frame inside)
    truth: pycolmap.Reconstruction  # true poses and points in the store's local frame
    sfm: pycolmap.Reconstruction  # the same tracks in an arbitrary, drifted frame
    gnss_names: list[str]
    gnss_positions_crs: np.ndarray  # (N, 3) biased and noisy
    gnss_sigmas: np.ndarray  # (N, 3) the sigmas a user would state (3, 3, 5 m)

    def gnss(self):
        from ..block.gnss import GNSSObservations

        return GNSSObservations(self.gnss_names, self.gnss_positions_crs, self.gnss_sigmas,
                                self.store.crs, "synthetic")


def _outward(ring: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Order the ring counter-clockwise seen from outside (Newell normal along `normal`)."""
    newell = np.cross(ring - ring.mean(0), np.roll(ring, -1, 0) - ring.mean(0)).sum(0)
    return ring if newell @ normal > 0 else ring[::-1]


def building_polygons(x0, x1, y0, y1, eave, ridge, street_side_y):
    """Walls, roof(s) and ground of one building; a gable ridge runs across the street (along
    y) so that roof slopes face +-x, a flat roof when ridge <= eave. Returns (rings, semantics,
    is_visible_side) where visible means facing the street or the sky."""
    xm = 0.5 * (x0 + x1)
    rings, semantics = [], []
    gable = ridge > eave + 1e-6
    for y, ny in ((y0, -1.0), (y1, 1.0)):  # front and back walls (pentagons under a gable)
        pts = [(x0, y, 0), (x1, y, 0), (x1, y, eave)] + ([(xm, y, ridge)] if gable else []) \
            + [(x0, y, eave)]
        rings.append(_outward(np.array(pts, float), np.array([0, ny, 0]))); semantics.append("WallSurface")
    for x, nx in ((x0, -1.0), (x1, 1.0)):  # side walls
        pts = [(x, y0, 0), (x, y1, 0), (x, y1, eave), (x, y0, eave)]
        rings.append(_outward(np.array(pts, float), np.array([nx, 0, 0]))); semantics.append("WallSurface")
    if gable:
        for xa, nx in ((x0, -1.0), (x1, 1.0)):
            pts = [(xa, y0, eave), (xm, y0, ridge), (xm, y1, ridge), (xa, y1, eave)]
            n = np.array([nx * (ridge - eave), 0, abs(xm - xa)])
            rings.append(_outward(np.array(pts, float), n)); semantics.append("RoofSurface")
    else:
        pts = [(x0, y0, eave), (x1, y0, eave), (x1, y1, eave), (x0, y1, eave)]
        rings.append(_outward(np.array(pts, float), np.array([0, 0, 1.0]))); semantics.append("RoofSurface")
    pts = [(x0, y0, 0), (x1, y0, 0), (x1, y1, 0), (x0, y1, 0)]
    rings.append(_outward(np.array(pts, float), np.array([0, 0, -1.0]))); semantics.append("GroundSurface")
    return rings, semantics


def street_polygons(options: StreetSceneOptions, rng: np.random.Generator):
    length = options.num_stations * options.station_spacing
    rings, semantics, buildings = [], [], []
    for side in (1.0, -1.0):
        x = -15.0
        k = 0
        while x < length + 15.0:
            size = rng.uniform(10.0, 16.0)
            eave = rng.uniform(9.0, 14.0)
            ridge = eave + (rng.uniform(3.0, 5.0) if k % 2 == 0 else 0.0)
            near = side * options.street_half_width
            far = side * (options.street_half_width + rng.uniform(9.0, 12.0))
            y0, y1 = sorted((near, far))
            r, s = building_polygons(x, x + size, y0, y1, eave, ridge, near)
            rings += r
            semantics += s
            buildings += [f"b{'L' if side > 0 else 'R'}{k}"] * len(r)
            x += size + rng.uniform(2.5, 5.0)
            k += 1
    return rings, semantics, buildings


def sample_surface_points(rings, spacing, rng):
    """Points on convex polygons (fan triangles), about one per spacing^2; with face index."""
    points, faces = [], []
    for f, ring in enumerate(rings):
        for i in range(1, len(ring) - 1):
            a, b, c = ring[0], ring[i], ring[i + 1]
            area = 0.5 * np.linalg.norm(np.cross(b - a, c - a))
            n = rng.poisson(area / spacing ** 2)
            u, v = rng.random(n), rng.random(n)
            flip = u + v > 1
            u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
            points.append(a + u[:, None] * (b - a) + v[:, None] * (c - a))
            faces.append(np.full(n, f))
    return np.vstack(points), np.concatenate(faces)


def look_rotation(forward: np.ndarray) -> np.ndarray:
    """cam_from_world rotation for a camera looking along `forward` with the image up = +z."""
    z = forward / np.linalg.norm(forward)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.vstack([x, y, z])


def make_street_scene(options: StreetSceneOptions | None = None,
                      crs_origin=DEFAULT_CRS_ORIGIN, crs: CRSInfo | None = None) -> StreetScene:
    o = options or StreetSceneOptions()
    rng = np.random.default_rng(o.seed)
    rings, semantics, buildings = street_polygons(o, rng)
    crs_origin = np.asarray(crs_origin, float)
    rings = _on_slope(rings, buildings, o.ground_slope)
    store = store_from_polygons([r + crs_origin for r in rings], semantics=semantics,
                                building_ids=buildings, crs=crs)
    shift = crs_origin - store.origin  # model (street) frame -> store local frame
    rings_local = [r + shift for r in rings]

    # True surface points: relief and clutter the LOD2 model does not have. Ground is not seen.
    candidates = [i for i, s in enumerate(semantics) if s != "GroundSurface"]
    points, face_of_point = sample_surface_points([rings_local[i] for i in candidates],
                                                  o.point_spacing, rng)
    face_of_point = np.array(candidates)[face_of_point]
    normals = np.array([_ring_normal(r) for r in rings_local])[face_of_point]
    offsets = rng.normal(0.0, o.relief_sigma, len(points))
    clutter = rng.random(len(points)) < o.clutter_fraction
    offsets[clutter] = rng.uniform(0.3, 1.0, clutter.sum())
    points = points + normals * offsets[:, None]
    if o.ground_spacing > 0:
        ground = street_ground(o, rng)
        points = np.vstack([points, ground + shift])
        normals = np.vstack([normals, np.tile([0.0, 0.0, 1.0], (len(ground), 1))])

    camera = pycolmap.Camera(model="PINHOLE", width=o.width, height=o.height,
                             params=[o.focal_length, o.focal_length, o.width / 2, o.height / 2],
                             camera_id=1)
    tilt = np.radians(o.tilt_deg)
    o_forward_tilt = np.radians(o.forward_tilt_deg)
    poses, names = [], []
    for s in range(o.num_stations):
        centre = np.array([s * o.station_spacing, 0.0, o.flight_height]) + shift
        centre[2] += 1.5 * np.sin(s / 5.0)  # height profile
        # Left, right and a forward view: the forward one sees both facade rows, so the
        # block is one connected reconstruction, as COLMAP would need it.
        for forward, tag in (((0.0, np.cos(tilt), -np.sin(tilt)), "L"),
                             ((0.0, -np.cos(tilt), -np.sin(tilt)), "R"),
                             ((np.cos(o_forward_tilt), 0.0, -np.sin(o_forward_tilt)), "F")):
            rotation = look_rotation(np.array(forward))
            poses.append((rotation, -rotation @ centre, centre))
            names.append(f"s{s:04d}_{tag}.jpg")

    # Visibility: in front, inside the image, not too far, on the side of the face it faces.
    observations = []  # per image: (point indices, xy)
    for rotation, translation, centre in poses:
        cam = points @ rotation.T + translation
        depth = cam[:, 2]
        xy = cam[:, :2] / np.maximum(depth, 1e-9)[:, None] * o.focal_length \
            + [o.width / 2, o.height / 2]
        facing = np.einsum("ij,ij->i", normals, centre - points) > 0
        visible = (depth > 1.0) & (depth < o.max_view_distance) & facing \
            & (xy[:, 0] >= 0) & (xy[:, 0] < o.width) & (xy[:, 1] >= 0) & (xy[:, 1] < o.height)
        idx = np.flatnonzero(visible)
        noisy = xy[idx] + rng.normal(0.0, o.image_noise_px, (len(idx), 2))
        observations.append((idx, noisy))
    track_length = np.bincount(np.concatenate([idx for idx, _ in observations]),
                               minlength=len(points))
    keep = track_length >= o.min_track_length

    truth = _build_reconstruction(camera, names, poses, points, observations, keep)
    length = o.num_stations * o.station_spacing
    sfm = _drifted_copy(truth, o.drift / length, rng)

    centres = np.array([c for _, _, c in poses])
    t = np.arange(len(centres)) / max(len(centres) - 1, 1)
    bias = np.array(o.gnss_bias) + o.gnss_bias_wave * np.stack(
        [np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), np.sin(np.pi * t)], axis=1)
    gnss = centres + bias + rng.normal(0.0, 1.0, centres.shape) * np.array(o.gnss_sigma)
    return StreetScene(store=store, truth=truth, sfm=sfm, gnss_names=names,
                       gnss_positions_crs=gnss + store.origin,
                       gnss_sigmas=np.tile([3.0, 3.0, 5.0], (len(names), 1)))


def ground_height(options: StreetSceneOptions, xy: np.ndarray) -> np.ndarray:
    """The true ground (street frame: x along the street, y across, z up) at `xy` (N, 2): the
    street's slope along x plus the kerb of the pavements along both facades."""
    xy = np.asarray(xy, float).reshape(-1, 2)
    pavement = np.abs(xy[:, 1]) > options.street_half_width - options.sidewalk_width
    return options.ground_slope * xy[:, 0] + options.kerb_height * pavement


def street_ground(options: StreetSceneOptions, rng: np.random.Generator) -> np.ndarray:
    """Tie points on the ground between the facades (street frame), one per ground_spacing^2
    on average, with the facades' relief sigma as their roughness."""
    length = options.num_stations * options.station_spacing
    x0, x1 = -15.0, length + 15.0
    half = options.street_half_width - 0.2
    n = rng.poisson((x1 - x0) * 2 * half / options.ground_spacing ** 2)
    xy = np.c_[rng.uniform(x0, x1, n), rng.uniform(-half, half, n)]
    z = ground_height(options, xy) + rng.normal(0.0, options.relief_sigma, n)
    return np.c_[xy, z]


def _on_slope(rings: list, buildings: list, slope: float) -> list:
    """Each building's rings raised to the street's height at its centre (x * slope)."""
    if not slope:
        return rings
    out = []
    centre = {b: np.mean([r[:, 0].mean() for r, c in zip(rings, buildings) if c == b])
              for b in set(buildings)}
    for ring, b in zip(rings, buildings):
        out.append(ring + [0.0, 0.0, slope * centre[b]])
    return out


def _ring_normal(ring: np.ndarray) -> np.ndarray:
    n = np.cross(ring - ring.mean(0), np.roll(ring, -1, 0) - ring.mean(0)).sum(0)
    return n / np.linalg.norm(n)


def _build_reconstruction(camera, names, poses, points, observations, keep):
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(camera)
    point_to_row: list[dict[int, int]] = []
    for image_id, (name, (rotation, translation, _), (idx, xy)) in enumerate(
            zip(names, poses, observations), start=1):
        mask = keep[idx]
        idx, xy = idx[mask], xy[mask]
        image = pycolmap.Image(name=name, keypoints=xy, camera_id=camera.camera_id,
                               image_id=image_id)
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation))
        point_to_row.append({int(p): k for k, p in enumerate(idx)})
    tracks: dict[int, list] = {}
    for image_id, rows in enumerate(point_to_row, start=1):
        for p, k in rows.items():
            tracks.setdefault(p, []).append(pycolmap.TrackElement(image_id, k))
    for p in np.flatnonzero(keep):
        rec.add_point3D(points[p], pycolmap.Track(tracks[int(p)]))
    return rec


def _drifted_copy(truth: pycolmap.Reconstruction, curvature: float, rng
                  ) -> pycolmap.Reconstruction:
    """The truth bent smoothly (z += curvature x^2, x from the first camera) and then moved
    into an arbitrary SfM frame by a random similarity."""
    sfm = pycolmap.Reconstruction(truth)
    x_ref = min(im.projection_center()[0] for im in sfm.images.values())

    def bend(xyz):
        out = np.array(xyz, float)
        out[2] += curvature * (out[0] - x_ref) ** 2
        return out

    for frame in sfm.frames.values():
        image = sfm.image(next(iter(frame.image_ids)).id)
        centre = bend(image.projection_center())
        rotation = np.asarray(image.cam_from_world().rotation.matrix())
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centre)
    for point in sfm.points3D.values():
        point.xyz = bend(point.xyz)
    axis = rng.normal(size=3)
    axis *= rng.uniform(0.3, 2.5) / np.linalg.norm(axis)
    sfm.transform(pycolmap.Sim3d(rng.uniform(0.2, 0.6), pycolmap.Rotation3d(axis),
                                 rng.normal(0, 50, 3)))
    return sfm


def centre_errors(estimate: pycolmap.Reconstruction, truth: pycolmap.Reconstruction) -> np.ndarray:
    """Per image distance (m) between estimated and true projection centres, matched by name."""
    true = {im.name: im.projection_center() for im in truth.images.values()}
    return np.array([np.linalg.norm(im.projection_center() - true[im.name])
                     for im in estimate.images.values() if im.has_pose])


def street_marks(scene: StreetScene, count: int, noise_px: float = 0.7, seed: int = 0,
                 min_views: int = 3) -> list[tuple[str, np.ndarray, list]]:
    """`count` ground marks of a street scene with known truth: true surface points seen in at
    least `min_views` true images, spread along the block (farthest point sampling), each with
    its true position in the model CRS and its measurements in the true images (COLMAP pixels
    with Gaussian noise of `noise_px`). Returns [(name, xyz CRS, [(image name, x, y)])]."""
    rng = np.random.default_rng([seed, 63])
    truth = scene.truth
    ids = np.array([i for i in truth.point3D_ids()
                    if truth.point3D(i).track.length() >= min_views], np.int64)
    xyz = np.array([truth.point3D(int(i)).xyz for i in ids]).reshape(-1, 3)
    chosen = [int(np.argmin(xyz[:, 0]))]
    distance = np.linalg.norm(xyz - xyz[chosen[0]], axis=1)
    while len(chosen) < min(count, len(ids)):
        chosen.append(int(np.argmax(distance)))
        distance = np.minimum(distance, np.linalg.norm(xyz - xyz[chosen[-1]], axis=1))
    chosen.sort(key=lambda k: xyz[k, 0])
    out = []
    for n, k in enumerate(chosen, start=1):
        point = xyz[k]
        measured = []
        for element in truth.point3D(int(ids[k])).track.elements:
            image = truth.image(element.image_id)
            xy = image.project_point(point)
            if xy is not None:
                measured.append((image.name, *(np.asarray(xy) + rng.normal(0.0, noise_px, 2))))
        out.append((f"M{n}", point + scene.store.origin, measured))
    return out
