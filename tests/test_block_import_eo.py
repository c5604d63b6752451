"""import-eo: GNSS/IMU exposures of a five-head camera into a COLMAP database and model, and back
out again (positions within 1 mm, angles within 0.001 deg)."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from colmap_citymodel.block.eo import FLIP, angles_opk, angles_rpy, read_eo, read_rig, rotation_opk, rotation_rpy
from colmap_citymodel.block.import_eo import exposures_from_block, main, read_back
from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.errors import InputError

#: Mulder Table 3.3: the oblique heads' eccentricities from the nadir head (mm, degrees), here
#: as lever arms in metres and boresight (omega, phi, kappa).
MULDER_HEADS = {
    "N": ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
    "B": ((-0.106712, -0.021692, -0.007892), (-44.993, 0.029, -0.077)),
    "F": ((-0.106878, -0.099972, -0.129667), (44.968, 0.029, 0.030)),
    "L": ((-0.035468, -0.086232, 0.005913), (-0.078, 44.992, 0.014)),
    "R": ((-0.115159, -0.085854, -0.144906), (0.056, -44.995, -0.009)),
}
CAMERA = {"model": "PINHOLE", "width": 4000, "height": 3000, "params": [6000, 6000, 2000, 1500]}
ORIGIN_E, ORIGIN_N = 389_000.0, 5_819_000.0


def _rig(tmp_path, gnss_lever_arm=(0.0, 0.0, 0.0), nadir_boresight=(0.0, 0.0, 0.0), camera=True):
    heads = []
    for name, (lever, boresight) in MULDER_HEADS.items():
        head = {"name": name, "image_name": f"{name}/{{exposure}}.jpg", "lever_arm": list(lever),
                "boresight": list(nadir_boresight if name == "N" else boresight)}
        if camera:
            head["camera"] = CAMERA
        heads.append(head)
    heads[0]["reference"] = True
    path = tmp_path / "rig.json"
    path.write_text(json.dumps({"heads": heads, "gnss_lever_arm": list(gnss_lever_arm)}))
    return path


def _exposures(rng, n, attitude):
    positions = np.c_[ORIGIN_E + rng.uniform(0, 2000, n), ORIGIN_N + rng.uniform(0, 2000, n),
                      rng.uniform(550, 650, n)]
    if attitude == "opk":
        angles = np.c_[rng.uniform(-3, 3, (n, 2)), rng.uniform(-180, 180, n)]
    else:
        angles = np.c_[rng.uniform(-3, 3, (n, 2)), rng.uniform(0, 360, n)]
    return positions.round(4), angles.round(6)  # as written to the EO file


def _write_eo(path, ids, positions, angles, sigmas=None):
    lines = ["id,X,Y,Z,a1,a2,a3"]
    for k, i in enumerate(ids):
        row = [i, *(f"{v:.4f}" for v in positions[k]), *(f"{v:.6f}" for v in angles[k])]
        if sigmas is not None:
            row += [f"{v}" for v in sigmas[k]]
        lines.append(",".join(row))
    path.write_text("\n".join(lines) + "\n")
    return path


def _angle_error(a, b):
    return np.abs((np.asarray(a) - np.asarray(b) + 180.0) % 360.0 - 180.0)


@pytest.mark.parametrize("attitude", ["opk", "rpy"])
def test_round_trip_through_database_and_model(tmp_path, attitude):
    rng = np.random.default_rng(3)
    ids = [f"{k:04d}" for k in range(12)]
    positions, angles = _exposures(rng, len(ids), attitude)
    sigmas = np.tile([0.03, 0.04, 0.08], (len(ids), 1))
    eo = _write_eo(tmp_path / "eo.csv", ids, positions, angles, sigmas)
    boresight = (0.0, 0.0, 0.0) if attitude == "opk" else (180.0, 0.0, -90.0)
    rig_path = _rig(tmp_path, gnss_lever_arm=(0.2, -0.1, -1.3), nadir_boresight=boresight)
    database = tmp_path / "database.db"
    pycolmap.Database.open(str(database)).close()
    result = main(database, eo, rig_path, "EPSG:25833", tmp_path / "out", attitude=attitude)
    assert result.num_images == 60 and result.num_images_added == 60
    origin = np.asarray(json.loads((tmp_path / "out" / "origin.json").read_text())["origin"])
    assert origin[0] % 100 == 0 and origin[1] % 100 == 0 and origin[2] == 0

    rig = read_rig(rig_path)
    back = read_back(database, tmp_path / "out" / "sparse")
    got_positions, got_angles = exposures_from_block(rig, back, ids, attitude)
    assert np.max(np.abs(got_positions + origin - positions)) < 1e-3
    assert np.max(_angle_error(got_angles, angles)) < 1e-3

    # every image independently of the package's rotation code (scipy: intrinsic XYZ is
    # Rx Ry Rz): centre = P - R a + R l, R_cam_from_world = F (R_body R_boresight)^T
    enu_from_ned = np.array([[0, 1, 0], [1, 0, 0], [0, 0, -1.0]])
    for k, exposure in enumerate(ids):
        if attitude == "opk":
            body = Rotation.from_euler("XYZ", angles[k], degrees=True).as_matrix()
        else:
            body = enu_from_ned @ Rotation.from_euler("ZYX", angles[k][::-1],
                                                      degrees=True).as_matrix()
        for name, (lever, bore) in MULDER_HEADS.items():
            bore = boresight if name == "N" else bore
            image = f"{name}/{exposure}.jpg"
            centre = (positions[k] - body @ np.array([0.2, -0.1, -1.3]) + body @ np.array(lever))
            cam = FLIP @ (body @ Rotation.from_euler("XYZ", bore, degrees=True).as_matrix()).T
            assert np.linalg.norm(back.centres[image] + origin - centre) < 1e-3
            assert np.linalg.norm(back.model_centres[image] + origin - centre) < 1e-3
            angle = np.degrees(Rotation.from_matrix(back.cam_rotations[image] @ cam.T)
                               .magnitude())
            assert angle < 1e-3
            # the database's gravity (camera frame) and rig calibration agree with the model
            assert np.linalg.norm(back.gravity[image] - cam @ [0, 0, -1.0]) < 1e-8
            r_rig, t_rig = back.sensor_from_rig[image]
            ref = f"N/{exposure}.jpg"
            r_ref = back.cam_rotations[ref]
            c_ref = back.centres[ref]
            assert np.degrees(Rotation.from_matrix(r_rig @ r_ref @ cam.T).magnitude()) < 1e-3
            centre_from_rig = -(r_rig @ r_ref).T @ (t_rig - r_rig @ r_ref @ c_ref)
            assert np.linalg.norm(centre_from_rig + origin - centre) < 1e-3


def test_conventions_point_the_cameras_where_they_say():
    # opk zero: looking down, image x to the east, image top (-y in COLMAP) to grid north
    cam = FLIP @ rotation_opk(0, 0, 0).T
    assert np.allclose(cam.T @ [0, 0, 1], [0, 0, -1])
    assert np.allclose(cam.T @ [1, 0, 0], [1, 0, 0])
    assert np.allclose(cam.T @ [0, -1, 0], [0, 1, 0])
    # rpy: heading 90 deg = flying east; nadir head boresight (180, 0, -90): looking down with
    # the top of the image forward (east), pitch up raises the body's x axis
    body = rotation_rpy(0, 0, 90)
    assert np.allclose(body @ [1, 0, 0], [1, 0, 0], atol=1e-12)
    assert np.allclose(body @ [0, 0, 1], [0, 0, -1], atol=1e-12)
    head = body @ rotation_opk(180, 0, -90)
    cam = FLIP @ head.T
    assert np.allclose(cam.T @ [0, 0, 1], [0, 0, -1], atol=1e-12)
    assert np.allclose(cam.T @ [0, -1, 0], [1, 0, 0], atol=1e-12)
    assert rotation_rpy(0, 10, 0)[2] @ [1, 0, 0] > 0
    # right side down: the body's y (right) axis points below the horizon
    assert (rotation_rpy(10, 0, 0) @ [0, 1, 0])[2] < 0
    rng = np.random.default_rng(0)
    for _ in range(50):
        a = np.r_[rng.uniform(-80, 80, 2), rng.uniform(-179, 179)]
        assert np.max(_angle_error(angles_opk(rotation_opk(*a)), a)) < 1e-9
        b = np.r_[rng.uniform(-80, 80, 2), rng.uniform(0, 359)]
        assert np.max(_angle_error(angles_rpy(rotation_rpy(*b)), b)) < 1e-9


def test_existing_images_keep_their_ids_and_get_one_rig(tmp_path):
    """feature_extractor's database: one camera, a trivial rig and a frame per image."""
    ids = ["a", "b", "c"]
    database = tmp_path / "database.db"
    db = pycolmap.Database.open(str(database))
    names = [f"{h}/{e}.jpg" for e in ids for h in MULDER_HEADS]
    image_ids = {}
    for name in names:
        cam = pycolmap.Camera(model="PINHOLE", width=4000, height=3000,
                              params=[6000, 6000, 2000, 1500])
        cam_id = db.write_camera(cam)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(db.read_camera(cam_id).sensor_id)
        rig_id = db.write_rig(rig)
        image_ids[name] = db.write_image(pycolmap.Image(name=name, camera_id=cam_id))
        frame = pycolmap.Frame()
        frame.rig_id = rig_id
        frame.add_data_id(db.read_image(image_ids[name]).data_id)
        db.write_frame(frame)
    db.close()
    rng = np.random.default_rng(1)
    positions, angles = _exposures(rng, 3, "opk")
    eo = _write_eo(tmp_path / "eo.txt", ids, positions, angles)
    result = main(database, eo, _rig(tmp_path, camera=False), "EPSG:25833", tmp_path / "out")
    assert result.num_images_added == 0
    db = pycolmap.Database.open(str(database))
    try:
        assert db.num_rigs() == 1 and db.num_frames() == 3 and db.num_pose_priors() == 15
        assert {i.name: i.image_id for i in db.read_all_images()} == image_ids
        assert all(len(f.data_ids) == 5 for f in db.read_all_frames())
    finally:
        db.close()
    rec = pycolmap.Reconstruction(str(tmp_path / "out" / "sparse"))
    assert rec.num_reg_images() == 15 and rec.num_frames() == 3


def test_geographic_eo_is_reprojected_with_the_grid_convergence(tmp_path):
    """EO in latitude/longitude (EPSG:4979 heights taken as the model's): the heading turns by
    the grid convergence, so a camera flying true north flies slightly off grid north."""
    import pyproj

    to_geo = pyproj.Transformer.from_crs("EPSG:25833", "EPSG:4326", always_xy=True)
    lon, lat = to_geo.transform(ORIGIN_E - 150_000, ORIGIN_N)  # 150 km west of the meridian
    eo = tmp_path / "eo.txt"
    eo.write_text(f"x {lat:.9f} {lon:.9f} 600.0 0 0 0\n")
    database = tmp_path / "database.db"
    pycolmap.Database.open(str(database)).close()
    result = main(database, eo, _rig(tmp_path), "EPSG:4326", tmp_path / "out",
                  model_crs="EPSG:25833")
    forward = result.poses.body_rotations[0] @ [0, 1, 0]  # opk: the image top
    azimuth = np.degrees(np.arctan2(forward[0], forward[1]))
    # the direction to true north in the grid, from two projected points
    to_grid = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:25833", always_xy=True)
    e1, n1 = to_grid.transform(lon, lat)
    e2, n2 = to_grid.transform(lon, lat + 0.01)
    expected = np.degrees(np.arctan2(e2 - e1, n2 - n1))
    assert abs(expected) > 1.0  # far from the central meridian: a real convergence
    assert abs(azimuth - expected) < 1e-3
    assert np.allclose(result.poses.antenna[0] + result.origin, [e1, n1, 600.0], atol=1e-3)


def test_bad_inputs_are_input_errors(tmp_path):
    bad = tmp_path / "eo.txt"
    bad.write_text("a 1 2 3 4 5\n")
    with pytest.raises(InputError, match="7 or 10 columns"):
        read_eo(bad)
    (tmp_path / "rig.json").write_text(json.dumps({"heads": []}))
    with pytest.raises(InputError, match="heads"):
        read_rig(tmp_path / "rig.json")
    (tmp_path / "rig.json").write_text(json.dumps({"heads": [{"image_name": "x.jpg"}]}))
    with pytest.raises(InputError, match="exposure"):
        read_rig(tmp_path / "rig.json")
    database = tmp_path / "database.db"
    pycolmap.Database.open(str(database)).close()
    good = tmp_path / "eo2.txt"
    good.write_text("a 389000 5819000 600 0 0 0\n")
    status = cli_main(["import-eo", "--database", str(database), "--eo", str(good), "--rig",
                       str(_rig(tmp_path, camera=False)), "--eo_crs", "EPSG:25833",
                       "--output_path", str(tmp_path / "out")])
    assert status == 2  # no camera in the rig file and no images in the database
    assert not (tmp_path / "out").exists()
