"""Dense-point quality: the propagated sigma against a Monte Carlo on a tiny block, visibility
from tie point tracks, PLY in and out, plane extraction."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest
import scipy.sparse as sp
from scipy.spatial.transform import Rotation

from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.files import write_point_ply
from colmap_citymodel.precision.dense import DenseOptions, PlaneOptions, camera_set, count_sigma, extract_planes, propagate, read_ply_vertices, visibility

FOCAL, W, H = 3000.0, 3000, 2000
FLIP = np.diag([1.0, -1.0, -1.0])


def _look_at(centre, target):
    """omega, phi, kappa (rad) of a photogrammetric camera at `centre` looking at `target`."""
    back = centre - target
    z = back / np.linalg.norm(back)
    x = np.cross([0.0, 0.0, 1.0], z)
    if np.linalg.norm(x) < 1e-9:
        x = np.array([1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Rotation.from_matrix(np.c_[x, y, z]).as_euler("XYZ")


def _block():
    centres = np.array([[-60.0, -10.0, 100.0], [60.0, 5.0, 105.0], [0.0, -70.0, 95.0],
                        [5.0, 65.0, 110.0], [0.0, 0.0, 120.0]])
    angles = np.array([_look_at(c, np.zeros(3)) for c in centres])
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(pycolmap.Camera(
        model="PINHOLE", width=W, height=H, params=[FOCAL, FOCAL, W / 2, H / 2], camera_id=1))
    for k, (c, a) in enumerate(zip(centres, angles)):
        r = FLIP @ Rotation.from_euler("XYZ", a).as_matrix().T
        rec.add_image_with_trivial_frame(
            pycolmap.Image(name=f"{k}.jpg", camera_id=1, image_id=k + 1),
            pycolmap.Rigid3d(pycolmap.Rotation3d(r), -r @ c))
    return rec, centres, angles


def _covariances(rng, n):
    out = []
    for _ in range(n):
        scale = np.r_[rng.uniform(0.02, 0.05, 3), np.radians(rng.uniform(0.003, 0.01, 3))]
        corr = np.eye(6)
        q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
        corr = q @ np.diag(rng.uniform(0.3, 1.7, 6)) @ q.T
        d = np.sqrt(np.diag(corr))
        corr = corr / np.outer(d, d)
        out.append(np.outer(scale, scale) * corr)
    return np.array(out)


def _project(rotations, centres, points):
    """pixels (S, C, 2) of points (S, 3) in cameras (S, C, 3, 3) R_cam_from_world, (S, C, 3)."""
    xc = np.einsum("scij,scj->sci", rotations, points[:, None, :] - centres)
    return np.stack([FOCAL * xc[..., 0] / xc[..., 2] + W / 2,
                     FOCAL * xc[..., 1] / xc[..., 2] + H / 2], -1), xc


def _triangulate(rotations, centres, pixels, start):
    """Gauss-Newton forward intersection per sample."""
    x = start.copy()
    for _ in range(8):
        predicted, xc = _project(rotations, centres, x)
        z = xc[..., 2]
        j = np.zeros(xc.shape[:2] + (2, 3))
        j[..., 0, 0] = FOCAL / z
        j[..., 0, 2] = -FOCAL * xc[..., 0] / z ** 2
        j[..., 1, 1] = FOCAL / z
        j[..., 1, 2] = -FOCAL * xc[..., 1] / z ** 2
        a = j @ rotations  # (S, C, 2, 3)
        r = pixels - predicted
        n = np.einsum("scki,sckj->sij", a, a)
        g = np.einsum("scki,sck->si", a, r)
        x = x + np.linalg.solve(n, g[..., None])[..., 0]
    return x


@pytest.mark.parametrize("sigma_image", [0.0, 0.5])
def test_dense_sigma_against_monte_carlo(sigma_image):
    rng = np.random.default_rng(11)
    rec, centres, angles = _block()
    covs = _covariances(rng, len(centres))
    cams = camera_set(rec, {f"{k}.jpg": covs[k] for k in range(len(centres))})
    points = np.array([[0.0, 0.0, 0.0], [12.0, -8.0, 3.0], [-15.0, 10.0, 10.0]])
    seen = sp.csr_matrix(np.ones((len(points), len(centres)), bool))
    options = DenseOptions(sigma_image=sigma_image)
    propagated = propagate(cams, points, seen, options)

    samples = 6000
    for p, point in enumerate(points):
        params = np.c_[centres, angles][None] + np.einsum(
            "cij,scj->sci", np.linalg.cholesky(covs), rng.normal(size=(samples, len(centres), 6)))
        matrices = Rotation.from_euler("XYZ", params[..., 3:].reshape(-1, 3)).as_matrix()
        rotations = (FLIP @ np.transpose(matrices, (0, 2, 1))).reshape(samples, -1, 3, 3)
        true_rot = np.array([FLIP @ Rotation.from_euler("XYZ", a).as_matrix().T for a in angles])
        truth = np.broadcast_to(point, (samples, 3))
        pixels, _ = _project(np.broadcast_to(true_rot, rotations.shape),
                             np.broadcast_to(centres, params[..., :3].shape), truth)
        pixels = pixels + sigma_image * rng.normal(size=pixels.shape)
        estimate = _triangulate(rotations, params[..., :3], pixels, truth.copy())
        empirical = np.cov(estimate.T)
        expected = propagated.covariances[p]
        assert np.allclose(np.sqrt(np.diag(empirical)), np.sqrt(np.diag(expected)), rtol=0.05)
        assert np.linalg.norm(empirical - expected) / np.linalg.norm(expected) < 0.1
    assert np.all(propagated.num_views == len(centres))


def test_visibility_needs_the_image_and_a_tie_point_track():
    rec, centres, _ = _block()
    cams = camera_set(rec, {f"{k}.jpg": np.eye(6) * 1e-4 for k in range(len(centres))})
    # a tie point at the origin seen by images 1, 2, 3 only
    track = pycolmap.Track()
    for image_id in (1, 2, 3):
        image = rec.image(image_id)
        xy = image.project_point(np.zeros(3))
        image.points2D = pycolmap.Point2DList([pycolmap.Point2D(xy)])
        track.add_element(image_id, 0)
    rec.add_point3D(np.zeros(3), track)
    points = np.array([[0.5, 0.5, 0.0],       # near the tie point: its track's cameras
                       [500.0, 500.0, 0.0],   # far from any tie point and every image
                       [30.0, 0.0, 0.0]])     # no tie point within 5 m: every camera it is in
    seen, decided = visibility(rec, cams, points, DenseOptions())
    dense = seen.toarray()
    assert dense[0].tolist() == [True, True, True, False, False]  # images 1-3
    assert not dense[1].any()
    assert decided.tolist() == [True, False, False]
    expected = [bool(np.all(np.abs(rec.image(k + 1).project_point(points[2])
                                   - [W / 2, H / 2]) < [W / 2, H / 2]))
                for k in range(len(centres))]
    assert dense[2].tolist() == expected


def test_count_sigma_follows_the_tie_point_medians():
    views = np.repeat(np.arange(2, 10), 50)
    sigma = 0.2 / np.sqrt(views) + np.random.default_rng(0).normal(0, 0.002, len(views))
    got, _ = count_sigma(sigma, views, np.array([2, 5, 9, 30]))
    assert got[0] > got[1] > got[2]
    assert got[3] == pytest.approx(got[2])  # clamped to the largest observed count
    assert got[1] == pytest.approx(0.2 / np.sqrt(5), rel=0.05)


def test_extract_planes_finds_the_box_faces():
    rng = np.random.default_rng(4)
    roof = np.c_[rng.uniform(0, 10, (800, 2)), np.full(800, 10.0)]
    wall = np.c_[rng.uniform(0, 10, 600), np.zeros(600), rng.uniform(0, 10, 600)]
    points = np.vstack([roof, wall]) + rng.normal(0, 0.02, (1400, 3))
    planes = extract_planes(points, None, PlaneOptions(inlier_distance=0.08), rng)
    assert len(planes) >= 2
    normals = sorted(np.abs(p.normal).argmax() for p in planes[:2])
    assert normals == [1, 2]
    assert max(len(p.inliers) for p in planes[:2]) >= 700


def test_dense_quality_command(tmp_path):
    rec, centres, _ = _block()
    rec.write(str(tmp_path))
    lines = ["image_id,name,sigma_X0_m,sigma_Y0_m,sigma_Z0_m,sigma_omega_deg,sigma_phi_deg,"
             "sigma_kappa_deg"]
    lines += [f"{k + 1},{k}.jpg,0.03,0.03,0.05,0.005,0.005,0.008" for k in range(len(centres))]
    (tmp_path / "image_precision.csv").write_text("\n".join(lines) + "\n")
    xyz = np.random.default_rng(0).uniform(-5, 5, (100, 3)) * [1, 1, 0]
    write_point_ply(tmp_path / "fused.ply", xyz, np.zeros((100, 3), np.uint8))
    out = tmp_path / "dense_quality.ply"
    assert cli_main(["dense-quality", "--input_path", str(tmp_path), "--ply",
                     str(tmp_path / "fused.ply"), "--image_covariance",
                     str(tmp_path / "image_precision.csv"), "--output", str(out)]) == 0
    written = read_ply_vertices(out)
    assert len(written) == 100
    assert np.all(written["num_views"] == 5)
    assert np.all((written["sigma_z"] > written["sigma_x"]) & (written["sigma_x"] > 0.001))
    assert np.allclose(np.c_[written["x"], written["y"], written["z"]], xyz)
