"""The simulator's renderer (simulate --render): targets where the camera model projects them,
EXIF and DJI XMP from the simulated GNSS, gcp_list.txt, the scene's parts, and COLMAP's own
SIFT, matching and mapping on a small rendered set against the truth."""

import math
import re
from pathlib import Path

import numpy as np
import pycolmap
import pytest
import shapely
from PIL import Image
from scipy import ndimage, optimize

from colmap_citymodel.block.gnss import read_gnss_exif
from colmap_citymodel.simulate.flight import Flight
from colmap_citymodel.simulate.render.metadata import dji_angles
from colmap_citymodel.simulate.render.options import RenderOptions
from colmap_citymodel.simulate.render.renderer import Renderer
from colmap_citymodel.simulate.render.sensor import expose
from colmap_citymodel.simulate.render.targets import Targets
from colmap_citymodel.simulate.scenario import SimulationOptions, sequence_key
from colmap_citymodel.simulate.scene import LABEL_WALL, PART_FURNITURE, PART_WINDOW, \
    building_footprints
from colmap_citymodel.simulate.sequence import plan_sequence, render_sequence, simulate_sequence


def small_options(frames: int = 10) -> SimulationOptions:
    """Four procedural buildings, a UAV flying along them at 16 m, 800 x 600 images with a
    distorting lens, street furniture and dormers, kerbs."""
    o = SimulationOptions(name="render_small", seed=3)
    o.scene.procedural.num_buildings = 4
    o.flight.num_key_frames = frames
    o.flight.spacing = 2.0
    o.flight.flight_height = 16.0
    o.flight.pitch_deg = 30.0
    o.flight.image_width, o.flight.image_height, o.flight.focal_length = 800, 600, 620.0
    o.flight.radial_k1 = o.flight.calibrated_radial_k1 = -0.03
    o.details.furniture_spacing = 8.0
    o.details.dormer_probability = 0.5
    o.details.kerb_height = 0.15
    o.details.ground_cell = 1.0
    o.checkpoints.count = 8
    o.render.enabled = True
    return o


def _footprints(store):
    return shapely.unary_union(list(building_footprints(store).values()))


def _saddle(grey: np.ndarray, start: np.ndarray, half: float = 5.0) -> np.ndarray:
    """The point of a black-white quadrant target's centre: where the image is most nearly
    point-symmetric (I(c + d) = I(c - d) over a disc of `half` px), found from `start`."""
    dy, dx = np.mgrid[-half:half + 0.5:0.5, -half:half + 0.5:0.5]
    keep = (dx ** 2 + dy ** 2 <= half ** 2) & ((dx != 0) | (dy != 0))
    dx, dy = dx[keep], dy[keep]

    def asymmetry(c):
        # COLMAP pixel coordinates: the pixel (row i, column j) is centred at (j + .5, i + .5)
        x, y = c[0] - 0.5, c[1] - 0.5
        a = ndimage.map_coordinates(grey, [y + dy, x + dx], order=3)
        b = ndimage.map_coordinates(grey, [y - dy, x - dx], order=3)
        return float(np.sum((a - b) ** 2))

    simplex = np.asarray(start) + np.array([[0.0, 0.0], [0.5, 0.0], [0.0, 0.5]])
    return optimize.minimize(asymmetry, start, method="Nelder-Mead",
                             options={"xatol": 1e-3, "fatol": 1e-9,
                                      "initial_simplex": simplex}).x


def test_target_centre_is_where_the_distorting_camera_projects_it():
    """A target on a wall seen obliquely near the image's corner through a lens with strong
    barrel distortion: its rendered centre lies within 0.15 px of the projection through the
    true camera, while the undistorted projection is pixels away."""
    o = small_options(frames=3)
    sim = plan_sequence(o)
    scene = sim.scene
    walls = np.flatnonzero((scene.labels == LABEL_WALL) & (np.abs(scene.normals[:, 2]) < 0.1))
    big = walls[np.argmax(scene.areas[walls])]
    point = scene.triangles[big].mean(0)
    normal = scene.normals[big]
    width, height, focal, k1 = 640, 480, 500.0, -0.08
    # a camera 9 m in front of the wall, 30 deg off its normal, turned so that the point lands
    # near the image's lower-right corner
    side = np.cross([0.0, 0.0, 1.0], normal)
    centre = point + 9.0 * (math.cos(math.radians(30)) * normal +
                            math.sin(math.radians(30)) * side) + [0.0, 0.0, 1.5]
    look = point - centre
    want = np.array([0.33 * width, 0.3 * height]) / focal  # normalised, pinhole
    forward = look / np.linalg.norm(look)
    x = np.cross(forward, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(forward, x), forward])  # cam_from_world looking at the point
    turn = _rotation_to(np.array([0.0, 0.0, 1.0]),
                        np.array([*want, 1.0]) / np.linalg.norm([*want, 1.0]))
    rotation = turn @ rot
    flight = Flight(["target.jpg"], centre[None], rotation[None], np.zeros(1), width, height,
                    focal, k1, k1)
    options = RenderOptions(enabled=True, read_noise=0.0, shot_noise=0.0, exposure_jitter=0.0,
                            target_radius=0.4)
    renderer = Renderer(scene, flight, _footprints(sim.store), o.details.sidewalk_width,
                        options, seed=5)
    renderer.targets = Targets.on_scene([1], point[None], renderer.raycaster, scene.triangles,
                                        options.target_radius)
    radiance, mask = renderer.render(0)
    pixels = expose(radiance, mask, options, np.random.default_rng(0))
    grey = pixels.astype(np.float64).mean(axis=2)
    projected, depth = flight.project(0, point[None])
    pinhole = focal * ((point - centre) @ rotation.T)[:2] / depth[0] + [width / 2, height / 2]
    assert np.linalg.norm(pinhole - projected[0]) > 4.0  # the lens matters here
    found = _saddle(grey, projected[0] + [0.8, -0.7])
    print("target found", found, "projected", projected[0], "pinhole", pinhole)
    assert np.linalg.norm(found - projected[0]) < 0.15
    assert np.linalg.norm(found - pinhole) > 3.5


def _rotation_to(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The rotation that turns unit vector a onto unit vector b (Rodrigues)."""
    v, c = np.cross(a, b), float(a @ b)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def test_barrel_lens_does_not_fold_far_points_into_the_image():
    """With k1 < 0 the radial polynomial turns back 76 deg off the axis (k1 = -0.02): a point
    80 deg off is not projected (it would land inside the image), one 40 deg off is, where
    COLMAP's camera model puts it."""
    flight = Flight(["a.jpg"], np.zeros((1, 3)), np.eye(3)[None], np.zeros(1), 1600, 1200,
                    1150.0, -0.02, -0.02)
    angles = np.radians([80.0, 40.0])
    points = np.stack([np.sin(angles), np.zeros(2), np.cos(angles)], axis=1) * 20.0
    uv, _ = flight.project(0, points)
    assert np.isnan(uv[0]).all()
    camera = pycolmap.Camera(model="SIMPLE_RADIAL", width=1600, height=1200,
                             params=[1150.0, 800.0, 600.0, -0.02])
    assert np.allclose(uv[1], camera.img_from_cam(points[1:])[0], atol=1e-9)


def _xmp_fields(path: Path) -> dict[str, str]:
    xmp = Image.open(path).info["xmp"].decode()
    return dict(re.findall(r'drone-dji:(\w+)="([^"]*)"', xmp))


def _from_dji(yaw: float, pitch: float, roll: float, north: float) -> np.ndarray:
    """cam_from_world (local east-north-up) from DJI gimbal angles (deg), grid north at
    `north` deg from true north: the inverse of metadata.dji_angles."""
    y, p, r = np.radians([yaw + north, pitch, roll])
    rz = np.array([[math.cos(y), -math.sin(y), 0], [math.sin(y), math.cos(y), 0], [0, 0, 1]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    body = rz @ ry @ rx  # columns: forward, right, down in north-east-down
    ned_to_enu = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    forward, right, down = (ned_to_enu @ body).T
    return np.stack([right, down, forward])


@pytest.mark.parametrize("pitch", [-30.0, -89.0, -91.0])
def test_dji_angles_give_back_the_camera(pitch):
    """Gimbal yaw, pitch and roll give back the camera's rotation, also at and beyond the
    nadir, and a grid north 1.5 deg off true north turns the yaw by it."""
    rot = _from_dji(40.0, pitch, 3.0, 0.0)
    yaw, p, roll = dji_angles(rot, -1.5)
    assert np.allclose(_from_dji(yaw, p, roll, -1.5), rot, atol=1e-9)
    assert abs(p - pitch) < 1e-9 and abs(roll - 3.0) < 1e-9
    assert abs(yaw - 41.5) < 1e-9


def _render(out: Path, frames: int, width: int, height: int, focal: float):
    o = small_options(frames)
    o.flight.image_width, o.flight.image_height, o.flight.focal_length = width, height, focal
    o.render.attitude_sigma_deg = (0.0, 0.0, 0.0)
    sim = simulate_sequence(o, progress=False, tie_points=False)
    stats = render_sequence(sim, o, out, progress=False)
    return o, sim, out, stats


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Four key frames of the small set, 480 x 360 px (a few seconds)."""
    return _render(tmp_path_factory.mktemp("render"), 4, 480, 360, 372.0)


def test_exif_and_xmp_carry_the_simulated_gnss_and_the_camera(rendered):
    """EXIF GPS read back (the package's own reader) equals the simulated GNSS to a
    millimetre; the XMP's position agrees, its gimbal angles give the true rotation (no
    attitude noise in this set), no RTK for 3 m sigmas."""
    o, sim, out, stats = rendered
    gnss = read_gnss_exif(out / "images", sim.store.crs)
    names = list(sim.flight.names)
    assert gnss.image_names == names
    assert np.abs(gnss.positions - sim.gnss_crs).max() < 1e-3
    from colmap_citymodel.simulate.render.metadata import geographic

    lat, lon, north = geographic(sim.store.crs, sim.gnss_crs[:, :2])
    for k, name in enumerate(names):
        xmp = _xmp_fields(out / "images" / name)
        assert abs(float(xmp["GpsLatitude"]) - lat[k]) < 2e-9
        assert abs(float(xmp["GpsLongitude"]) - lon[k]) < 2e-9
        assert abs(float(xmp["AbsoluteAltitude"]) - sim.gnss_crs[k, 2]) < 1e-3
        assert xmp["RtkFlag"] == "0" and "RtkStdLon" not in xmp
        angles = [float(xmp[f"Gimbal{a}Degree"]) for a in ("Yaw", "Pitch", "Roll")]
        back = _from_dji(*angles, float(north[k]))
        angle = np.degrees(np.arccos(np.clip((np.trace(back @ sim.flight.rotations[k].T) - 1)
                                             / 2, -1, 1)))
        assert angle < 0.01  # the XMP's 2 decimals
    assert stats["num_images"] == len(names)


def test_gcp_list_lists_the_targets_where_they_project(rendered):
    """gcp_list.txt: the CRS, then per seen target its true model-CRS position and its
    projection in OpenSfM's pixel convention (COLMAP's minus half a pixel)."""
    o, sim, out, _ = rendered
    lines = (out / "images" / "gcp_list.txt").read_text().splitlines()
    assert lines[0] == f"EPSG:{sim.store.crs.horizontal_epsg}"
    assert len(lines) > 3
    by_id = {f"cp{i}": xyz for i, xyz in zip(sim.checkpoints.ids, sim.checkpoints.xyz)}
    names = list(sim.flight.names)
    for line in lines[1:]:
        x, y, z, u, v, image, gcp = line.split()
        local = np.array([float(x), float(y), float(z)]) - sim.store.origin
        assert np.abs(local - by_id[gcp]).max() < 1e-3
        uv, _ = sim.flight.project(names.index(image), local[None])
        # 0.1 mm and 0.001 px as written
        assert np.abs(uv[0] - 0.5 - [float(u), float(v)]).max() < 0.01


def test_scene_parts_furniture_and_dormers():
    """Street furniture and dormers are added after everything else (the scene without them
    is the same triangles); furniture stands outside the footprints; every dormer adds a
    window; parts and objects cover every triangle."""
    o = small_options(frames=4)
    with_all = plan_sequence(o).scene
    o.details.furniture_spacing = 0.0
    o.details.dormer_probability = 0.0
    plain = plan_sequence(o).scene
    assert len(with_all.parts) == len(with_all.triangles) == len(with_all.objects)
    furniture = with_all.parts == PART_FURNITURE
    assert furniture.sum() > 0 and not (plain.parts == PART_FURNITURE).any()
    assert (with_all.parts == PART_WINDOW).sum() > (plain.parts == PART_WINDOW).sum()
    footprints = _footprints(plan_sequence(o).store)
    feet = with_all.triangles[furniture].reshape(-1, 3)
    assert not shapely.contains_xy(footprints, feet[:, 0], feet[:, 1]).any()
    same = [t for t, p in zip(with_all.triangles, with_all.parts) if p != PART_FURNITURE]
    assert len(same) >= len(plain.triangles)


def test_render_table_is_checked(tmp_path):
    """A scenario's [render] table: unknown keys and bad values are errors naming the file."""
    from colmap_citymodel.errors import InputError
    from colmap_citymodel.simulate.scenario import load_scenario

    path = tmp_path / "s.toml"
    path.write_text('[render]\nenabled = true\nxmp = "exif"\n')
    with pytest.raises(InputError, match="render.xmp") as caught:
        load_scenario(path)
    assert "s.toml" in str(caught.value)
    path.write_text("[render]\nsun_height = 30\n")
    with pytest.raises(InputError, match="render.sun_height"):
        load_scenario(path)
    path.write_text("[render]\nenabled = true\nsun_elevation_deg = 25\n")
    options = load_scenario(path)
    assert options.render.enabled and options.render.sun_elevation_deg == 25.0


def test_sequence_key_ignores_render_until_enabled():
    """Sequences without images keep their keys; enabling the renderer makes a new one."""
    o = SimulationOptions()
    key = sequence_key(o)
    o.render.sun_elevation_deg = 20.0
    assert sequence_key(o) == key
    o.render.enabled = True
    assert sequence_key(o) != key


@pytest.mark.slow
@pytest.mark.ci
def test_colmap_sift_maps_the_rendered_set(tmp_path):
    """Ten rendered 800 x 600 images (about 20 s), then COLMAP's SIFT, exhaustive matching and
    incremental mapping (the true camera model given, as a calibrated camera): every image
    registered, one model, camera centres within 5 cm of the truth after a similarity
    transform."""
    o, sim, out, _ = _render(tmp_path / "set", 10, 800, 600, 620.0)
    flight = sim.flight
    names = list(flight.names)
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "SIMPLE_RADIAL"
    reader.camera_params = ",".join(str(v) for v in (
        flight.focal, flight.width / 2, flight.height / 2, flight.k1))
    database = tmp_path / "database.db"
    pycolmap.extract_features(database, out / "images", image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              device=pycolmap.Device.cpu)
    pycolmap.match_exhaustive(database, device=pycolmap.Device.cpu)
    options = pycolmap.IncrementalPipelineOptions()
    options.ba_refine_focal_length = False
    options.ba_refine_principal_point = False
    options.ba_refine_extra_params = False
    (tmp_path / "sparse").mkdir()
    models = pycolmap.incremental_mapping(database, out / "images", tmp_path / "sparse", options)
    assert len(models) == 1
    rec = next(iter(models.values()))
    assert rec.num_reg_images() == len(names)
    estimated = {im.name: im.projection_center() for im in rec.images.values() if im.has_pose}
    a = np.array([estimated[n] for n in names])
    b = flight.centres
    sim3 = pycolmap.estimate_sim3d(a, b)
    moved = a @ sim3.matrix()[:, :3].T + sim3.matrix()[:, 3]
    rms = float(np.sqrt(np.mean(np.sum((moved - b) ** 2, axis=1))))
    assert rms < 0.05


def test_run_from_a_rendered_folder_end_to_end(tmp_path):
    """Ten rendered images with their EXIF GPS, `run` from the folder as a user calls it
    (features, matching, mapping with the model, refine): every image registered, and the
    block either nearer the truth than the GNSS-only one or handed back "failed"."""
    from colmap_citymodel.citymodel.write_citygml import raw_from_store, write_citygml
    from colmap_citymodel.pipeline.run import main

    o, sim, out, _ = _render(tmp_path / "set", 10, 800, 600, 620.0)
    flight = sim.flight
    model = tmp_path / "model.gml"
    write_citygml(model, raw_from_store(sim.store), sim.store.crs.label)
    params = ",".join(str(v) for v in (flight.focal, flight.width / 2, flight.height / 2,
                                       flight.k1))
    run = main(out / "images", model, tmp_path / "run", camera_model="SIMPLE_RADIAL",
               camera_params=params, progress=False)
    result = run.result
    assert result is not None and result.reconstruction.num_reg_images() == len(flight.names)
    truth = dict(zip(flight.names, flight.centres + sim.store.origin))

    def error(rec) -> float:
        d = [rec.image(i).projection_center() + result.origin - truth[rec.image(i).name]
             for i in rec.reg_image_ids()]
        return float(np.sqrt(np.mean(np.sum(np.square(d), axis=1))))

    assert (tmp_path / "run" / "refined" / "report.json").exists()
    if run.verdict != "failed":
        assert error(result.reconstruction) < error(result.gnss_only)
