"""Georegistration: robust Sim3 from camera centres to GNSS, and user-given transforms."""

from __future__ import annotations

import json

import numpy as np
import pycolmap
import pytest
from scipy.spatial.transform import Rotation

from colmap_citymodel.align.georegister import apply_sim3, camera_centres, estimate_georegistration, read_initial_transform, sim3_to_local
from colmap_citymodel.errors import GeoregistrationError, InputError


def _scene(num_frames=20, seed=1):
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_frames_per_rig = num_frames
    options.num_points3D = 50
    pycolmap.set_random_seed(seed)
    return pycolmap.synthesize_dataset(options)


def _true_sim3(scale=8.0):
    rotation = Rotation.from_euler("zyx", [35.0, -12.0, 7.0], degrees=True).as_matrix()
    return pycolmap.Sim3d(np.column_stack([scale * rotation, [120.0, -40.0, 25.0]]))


def _rotation_angle_deg(a, b):
    return np.degrees(Rotation.from_matrix(a @ b.T).magnitude())


def test_recovers_sim3_and_rejects_gnss_outliers():
    rec = _scene()
    ids = np.array(sorted(rec.reg_image_ids()))
    truth = _true_sim3()
    centres = camera_centres(rec, ids)
    rng = np.random.default_rng(0)
    sigma = np.array([0.3, 0.3, 0.5])
    gnss = (centres @ np.asarray(truth.matrix())[:, :3].T + np.asarray(truth.translation)
            + rng.normal(0, sigma, size=centres.shape))
    outliers = np.array([3, 11])
    gnss[outliers] += [[60.0, 0, 0], [0, -45.0, 30.0]]
    result = estimate_georegistration(rec, gnss, ids, sigmas=np.tile(sigma, (len(ids), 1)))
    assert result.max_error == pytest.approx(1.5)  # 3 x the largest per-axis sigma
    np.testing.assert_array_equal(np.flatnonzero(~result.inlier_mask), outliers)
    assert result.sim3.scale == pytest.approx(8.0, rel=0.01)
    assert _rotation_angle_deg(result.sim3.rotation.matrix(), truth.rotation.matrix()) < 0.5
    assert result.rms < 1.0  # ~ sqrt(0.3^2 + 0.3^2 + 0.5^2) = 0.66 m of noise
    assert np.linalg.norm(result.residuals[outliers[0]]) > 40.0
    d = result.todict()
    assert d["num_inliers"] == len(ids) - 2 and sorted(d["outlier_image_ids"]) == sorted(
        ids[outliers].tolist())

    # Applying it brings the camera centres onto the GNSS positions (up to the noise).
    apply_sim3(rec, result.sim3)
    moved = camera_centres(rec, ids)
    inl = result.inlier_mask
    assert np.sqrt(np.mean(np.sum((moved[inl] - gnss[inl]) ** 2, axis=1))) < 1.0


def test_exact_data_recovered_exactly():
    rec = _scene(num_frames=6, seed=3)
    ids = np.array(sorted(rec.reg_image_ids()))
    truth = _true_sim3(scale=25.0)
    gnss = camera_centres(rec, ids) @ np.asarray(truth.matrix())[:, :3].T + np.asarray(
        truth.translation)
    result = estimate_georegistration(rec, gnss, ids)
    np.testing.assert_allclose(np.asarray(result.sim3.matrix()), np.asarray(truth.matrix()),
                               atol=1e-8)
    assert result.inlier_mask.all() and result.rms < 1e-8


def test_too_few_and_collinear_and_no_baseline():
    rec = _scene(num_frames=8)
    ids = np.array(sorted(rec.reg_image_ids()))
    gnss = camera_centres(rec, ids) * 10.0
    with pytest.raises(GeoregistrationError, match="only 2 GNSS"):
        estimate_georegistration(rec, gnss[:2], ids[:2])

    # Camera centres on a line, with random orientations: no cue for the rotation about it
    # is needed to fail clearly; coinciding centres still do.
    for image_id in ids:
        frame = rec.frame(rec.image(int(image_id)).frame_id)
        frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(), np.zeros(3))
    with pytest.raises(GeoregistrationError, match="coincide"):
        estimate_georegistration(rec, camera_centres(rec, ids) + np.arange(len(ids))[:, None],
                                 ids)

    # Non-collinear centres but all GNSS within a metre of each other.
    rec = _scene(num_frames=8)
    tiny = camera_centres(rec, ids) * 0.05
    with pytest.raises(GeoregistrationError, match="baseline"):
        estimate_georegistration(rec, tiny, ids)


def _upright_camera(centre, forward, pitch_deg=0.0, roll_deg=0.0):
    """cam_from_world of a camera at `centre` looking along horizontal `forward`, tilted down by
    `pitch_deg` and rolled by `roll_deg` (x right, y down, z along the view)."""
    f = np.asarray(forward, float) / np.linalg.norm(forward)
    pitch = np.radians(pitch_deg)
    view = np.cos(pitch) * f + np.array([0, 0, -np.sin(pitch)])
    x = np.cross(view, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(view, x)
    roll = np.radians(roll_deg)
    x, y = np.cos(roll) * x + np.sin(roll) * y, -np.sin(roll) * x + np.cos(roll) * y
    rotation = np.stack([x, y, view])
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centre)


@pytest.mark.parametrize("look", ["forward", "sideways"])
def test_straight_line_takes_the_roll_from_upright_cameras(look):
    """Centres on a straight line: GNSS fixes the line, the upright cameras the rotation about
    it. Looking along the line (a vehicle), the horizontal image x axis fixes it to the
    cameras' roll jitter; looking sideways, the image up direction fixes it to their tilt."""
    rec = _scene(num_frames=16)
    ids = np.array(sorted(rec.reg_image_ids()))
    rng = np.random.default_rng(2)
    direction = np.array([np.cos(0.4), np.sin(0.4), 0.0])
    centres = np.array([k * 3.0 * direction + [0, 0, 2.0] for k in range(len(ids))])
    forward = direction if look == "forward" else np.array([-direction[1], direction[0], 0.0])
    pitch = 3.0 if look == "forward" else 20.0
    for k, image_id in enumerate(ids):
        frame = rec.frame(rec.image(int(image_id)).frame_id)
        frame.rig_from_world = _upright_camera(centres[k], forward, pitch + rng.normal(0, 1),
                                               rng.normal(0, 1))
    truth = _true_sim3(scale=4.0)  # model frame -> the "SfM" frame of the test
    rec.transform(truth)
    gnss = centres + rng.normal(0, [3.0, 3.0, 5.0], centres.shape)
    result = estimate_georegistration(rec, gnss, ids)
    assert result.cues["roll_about_line"].startswith("images")
    recovered = np.asarray(result.sim3.rotation.matrix()) @ np.asarray(truth.rotation.matrix())
    error = _rotation_angle_deg(recovered, np.eye(3))
    # Heading and pitch of the line come from 16 GNSS positions over 45 m (~3-6 deg here);
    # what matters is the roll about the line.
    line = np.asarray(result.sim3.rotation.matrix()) @ np.asarray(truth.rotation.matrix())
    roll = np.degrees(abs(Rotation.from_matrix(line).as_rotvec() @ direction))
    assert roll < (2.0 if look == "forward" else 25.0), (roll, error)
    assert result.sim3.scale * truth.scale == pytest.approx(1.0, rel=0.1)


def test_mostly_outliers_fails_clearly():
    rec = _scene(num_frames=10)
    ids = np.array(sorted(rec.reg_image_ids()))
    rng = np.random.default_rng(5)
    gnss = rng.uniform(-500, 500, size=(len(ids), 3))
    with pytest.raises(GeoregistrationError, match="agree with a similarity|no similarity"):
        estimate_georegistration(rec, gnss, ids, min_inliers=6)


def test_read_initial_transform_formats(tmp_path):
    truth = _true_sim3(scale=2.5)
    matrix4 = np.vstack([np.asarray(truth.matrix()), [0, 0, 0, 1]])
    text = tmp_path / "t.txt"
    text.write_text("# input -> model CRS\n" + "\n".join(" ".join(f"{v:.17g}" for v in row)
                                                      for row in matrix4) + "\n")
    np.testing.assert_allclose(read_initial_transform(text).matrix(), truth.matrix(), atol=1e-9)

    xyzw = truth.rotation.quat
    as_json = tmp_path / "t.json"
    as_json.write_text(json.dumps({
        "scale": 2.5,
        "rotation": [xyzw[3], xyzw[0], xyzw[1], xyzw[2]],  # qw qx qy qz
        "translation": np.asarray(truth.translation).tolist(),
    }))
    np.testing.assert_allclose(read_initial_transform(as_json).matrix(), truth.matrix(), atol=1e-9)
    as_json.write_text(json.dumps({"scale": 2.5, "rotation": truth.rotation.matrix().tolist(),
                                   "translation": [120.0, -40.0, 25.0]}))
    sim3 = read_initial_transform(as_json)
    np.testing.assert_allclose(sim3.matrix(), truth.matrix(), atol=1e-9)

    origin = np.array([100.0, -50.0, 20.0])
    local = sim3_to_local(sim3, origin)
    x = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(local * x, sim3 * x - origin, atol=1e-9)


@pytest.mark.parametrize(
    "name, content, match",
    [
        ("a.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n", None),  # 3x4 is accepted
        ("b.txt", "1 0 0\n0 1 0\n0 0 1\n", "4x4"),
        ("c.txt", "1 0 0 0\n0 1 0 0\n0 0 1 x\n0 0 0 1\n", "line 3: not a number"),
        ("d.txt", "1 0 0 0\n0 2 0 0\n0 0 1 0\n0 0 0 1\n", "not scale x rotation"),
        ("e.txt", "-1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "determinant"),
        ("f.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n1 0 0 1\n", "last row"),
        ("g.json", '{"scale": 1, "rotation": [1, 0, 0]', "invalid JSON"),
        ("h.json", '{"scale": 1, "rotation": [1, 0, 0, 0]}', "lacks"),
        ("i.json", '{"scale": -1, "rotation": [1, 0, 0, 0], "translation": [0, 0, 0]}',
         "positive"),
        ("j.json", '{"scale": 1, "rotation": [1, 0], "translation": [0, 0, 0]}', "rotation"),
    ],
)
def test_read_initial_transform_malformed(tmp_path, name, content, match):
    path = tmp_path / name
    path.write_text(content)
    if match is None:
        np.testing.assert_allclose(read_initial_transform(path).matrix(), np.eye(3, 4))
        return
    with pytest.raises(InputError, match=match) as info:
        read_initial_transform(path)
    assert name in str(info.value)


@pytest.mark.parametrize("noise, cue", [(0.05, "gnss"), (3.0, "images")])
def test_nearly_straight_line_trusts_gnss_only_as_far_as_its_scatter_allows(noise, cue):
    """Centres 1 m off a straight line, stated GNSS sigma 3 m: GNSS that scatters 5 cm still
    fixes the rotation about the line (the 7-parameter fit is kept); GNSS that scatters 3 m
    does not (the cameras' upright orientation fixes it)."""
    rec = _scene(num_frames=30)
    ids = np.array(sorted(rec.reg_image_ids()))
    rng = np.random.default_rng(3)
    s = np.linspace(0.0, 90.0, len(ids))
    centres = np.column_stack([s, 1.5 * np.sin(s / 15.0), np.full(len(s), 20.0)])
    for k, image_id in enumerate(ids):
        frame = rec.frame(rec.image(int(image_id)).frame_id)
        frame.rig_from_world = _upright_camera(centres[k], [0.0, 1.0, 0.0], 20.0)
    truth = _true_sim3(scale=4.0)
    rec.transform(truth)
    gnss = centres + rng.normal(0, noise, centres.shape)
    result = estimate_georegistration(rec, gnss, ids, sigmas=np.tile([3.0, 3.0, 5.0],
                                                                      (len(ids), 1)))
    if cue == "gnss":
        assert result.cues == {"translation": "gnss", "scale": "gnss", "rotation": "gnss"}
        recovered = np.asarray(result.sim3.rotation.matrix()) @ np.asarray(
            truth.rotation.matrix())
        assert _rotation_angle_deg(recovered, np.eye(3)) < 1.0
    else:
        assert result.cues["roll_about_line"].startswith("images")


def test_straight_line_of_tilted_sideways_cameras_takes_the_roll_from_walls_and_ground():
    """A UAV strip: cameras looking sideways, pitched 35 deg down, at a facade along the line
    above a level street. Their image "up" would put the block 35 deg off about the line (GNSS
    cannot fix it: the centres lie on a line); the tie points' wall and ground planes fix it to
    a degree, and the cue says so."""
    from colmap_citymodel.align.georegister import LEVEL_ROLL_CUE

    rec = _scene(num_frames=16)
    ids = np.array(sorted(rec.reg_image_ids()))
    rng = np.random.default_rng(4)
    direction = np.array([np.cos(0.4), np.sin(0.4), 0.0])
    side = np.array([-direction[1], direction[0], 0.0])
    centres = np.array([k * 3.0 * direction + [0, 0, 25.0] for k in range(len(ids))])
    for k, image_id in enumerate(ids):
        frame = rec.frame(rec.image(int(image_id)).frame_id)
        frame.rig_from_world = _upright_camera(centres[k], side, 35.0 + rng.normal(0, 1),
                                               rng.normal(0, 1))
    for point_id in list(rec.points3D):
        rec.delete_point3D(point_id)
    along = rng.uniform(-5.0, 50.0, (2, 600))
    facade = (along[0][:, None] * direction + 18.0 * side
              + rng.uniform(0.0, 15.0, 600)[:, None] * [0, 0, 1.0])
    street = along[1][:, None] * direction + rng.uniform(2.0, 17.0, 600)[:, None] * side
    for xyz in np.vstack([facade, street]) + rng.normal(0, 0.05, (1200, 3)):
        rec.add_point3D(xyz, pycolmap.Track(), np.zeros(3, np.uint8))
    truth = _true_sim3(scale=4.0)
    rec.transform(truth)
    gnss = centres + rng.normal(0, [3.0, 3.0, 5.0], centres.shape)
    result = estimate_georegistration(rec, gnss, ids)
    assert result.cues["roll_about_line"] == LEVEL_ROLL_CUE
    line = np.asarray(result.sim3.rotation.matrix()) @ np.asarray(truth.rotation.matrix())
    roll = np.degrees(abs(Rotation.from_matrix(line).as_rotvec() @ direction))
    assert roll < 1.5
