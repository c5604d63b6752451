"""Precision of image subsets (Mulder Table 5.2) on the synthetic street: counts of the
restricted blocks, more images -> smaller sigmas, the inner-constraint S-transformation against
dense algebra, the CLI's outputs and its errors for bad input."""

from __future__ import annotations

import json
import re
from itertools import combinations

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust.problem import HybridProblem
from colmap_citymodel.block.priors import GNSSPriors
from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.errors import InputError
from colmap_citymodel.options import AdjustmentOptions
from colmap_citymodel.precision.estimate import estimate_precision, image_jacobian, whitened_jacobian
from colmap_citymodel.precision.subsets import SubsetOptions, inner_precision, parse_subset, precision_subsets, restrict, select_images, shared_points, similarity_basis
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene

PNG = b"\x89PNG\r\n\x1a\n"
#: Every other station: half the images over the same stretch of street.
EVEN = "s*[02468]_*.jpg"


@pytest.fixture(scope="module")
def scene():
    # 8 stations x (left, right, forward) = 24 images, ~1 px noise.
    return make_street_scene(StreetSceneOptions(num_stations=8, point_spacing=1.5,
                                                 image_noise_px=1.0, seed=11))


def _priors(rec: pycolmap.Reconstruction, sigma=(0.05, 0.05, 0.08), seed=0) -> GNSSPriors:
    rng = np.random.default_rng(seed)
    ids = np.array(sorted(rec.reg_image_ids()))
    centres = np.array([rec.image(int(i)).projection_center() for i in ids])
    sigma = np.asarray(sigma)
    return GNSSPriors(ids, centres + rng.normal(size=centres.shape) * sigma,
                      np.tile(sigma, (len(ids), 1)))


@pytest.fixture(scope="module")
def results(scene):
    rec = pycolmap.Reconstruction(scene.truth)
    return precision_subsets(rec, ["all=*", f"even={EVEN}", "sides=*_L.jpg,*_R.jpg"],
                             _priors(rec), progress=False)


def _max_angle_deg(centres: np.ndarray, xyz: np.ndarray) -> float:
    rays = centres - xyz
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    return max(np.degrees(np.arccos(np.clip(a @ b, -1, 1))) for a, b in combinations(rays, 2))


def test_restricted_block_keeps_only_the_subset(scene):
    rec = pycolmap.Reconstruction(scene.truth)
    spec = parse_subset(f"even={EVEN}")
    ids = select_images(rec, spec)
    names = {rec.image(i).name for i in ids}
    assert len(ids) == 12 and all(re.match(r"s000[0246]_[LRF]\.jpg$", n) for n in names)
    options = SubsetOptions()
    sub, info = restrict(rec, ids, options)
    assert rec.num_reg_images() == 24  # the input is not modified
    assert sorted(sub.reg_image_ids()) == sorted(info.image_ids) == sorted(ids)
    # Independently: the points with >= 2 rays in the subset and a large enough angle.
    centres = {i: rec.image(i).projection_center() for i in ids}
    expected = set()
    for point_id, point in rec.points3D.items():
        views = sorted({e.image_id for e in point.track.elements if e.image_id in centres})
        if len(views) >= 2 and _max_angle_deg(np.array([centres[v] for v in views]),
                                              point.xyz) >= options.min_triangulation_angle:
            expected.add(point_id)
    assert set(sub.point3D_ids()) == expected
    assert 0 < len(expected) < rec.num_points3D()
    for point_id in expected:  # tracks keep exactly the subset's observations
        kept = sorted(e.image_id for e in sub.point3D(point_id).track.elements)
        assert kept == sorted(e.image_id for e in rec.point3D(point_id).track.elements
                              if e.image_id in centres)
    # Images left with too few tie points are de-registered (and their observations go).
    counts = {i: sub.image(i).num_points3D for i in ids}
    threshold = int(np.percentile(list(counts.values()), 30))
    weak = {rec.image(i).name for i, n in counts.items() if n < threshold}
    strict, info = restrict(rec, ids, SubsetOptions(min_image_points=threshold))
    assert weak and weak <= set(info.dropped_images)
    assert len(info.image_ids) == 12 - len(info.dropped_images)
    assert all(strict.image(i).num_points3D >= threshold for i in strict.reg_image_ids())
    assert all(e.image_id in info.image_ids for p in strict.points3D.values()
               for e in p.track.elements)


def test_more_images_give_smaller_sigmas(results):
    by_name = {r.name: r for r in results}
    full, half, sides = by_name["all"], by_name["even"], by_name["sides"]
    assert (full.num_images, half.num_images, sides.num_images) == (24, 12, 16)
    assert full.gauge == "gnss" and full.num_gnss == 24 and half.num_gnss == 12
    for datum in ("solve", "inner"):
        assert np.all(np.median(full.point_sigmas(datum), 0)
                      < np.median(half.point_sigmas(datum), 0))
        assert np.all(np.median(full.centre_sigmas(datum), 0)
                      < np.median(half.centre_sigmas(datum), 0))
    # The same tie points are better determined with all images (Mulder Fig. 5.10).
    common, in_full, in_half = np.intersect1d(full.precision.point_ids, half.precision.point_ids,
                                              return_indices=True)
    better = np.linalg.norm(full.point_sigmas()[in_full], axis=1) \
        < np.linalg.norm(half.point_sigmas()[in_half], axis=1)
    assert len(common) > 100 and better.mean() > 0.95
    # Image noise 1 px and GNSS with its stated sigmas: s0 near 1.
    assert all(0.85 < r.precision.variance.sigma0 < 1.15 for r in results)
    shared = shared_points(results)
    assert shared["all"]["all"] == full.num_points
    assert shared["even"]["all"] == len(common) == half.num_points  # a subset's points are in all
    summary = half.summary()
    assert summary["num_images"] == 12 and summary["num_points3D"] == half.num_points
    assert summary["median_point_sigma"]["Z"] == pytest.approx(
        float(np.median(half.point_sigmas()[:, 2])))


def test_inner_precision_equals_the_dense_s_transformation(scene):
    # Fixed gauge (no GNSS) on a 12-image block: the inner-constraint covariances of points and
    # projection centres must equal S Sigma S^T formed densely from the full inverse.
    rec = pycolmap.Reconstruction(scene.truth)
    sub, _ = restrict(rec, select_images(rec, parse_subset("first=s000[0-3]_*")), SubsetOptions())
    problem = HybridProblem(sub, None, None, None, AdjustmentOptions(), robust_images=False,
                            robust_planes=False)
    problem.solve()
    precision = estimate_precision(problem)
    inner = inner_precision(problem, precision)
    jacobian, layout = whitened_jacobian(problem)
    dense = jacobian.toarray()
    nc, n, p = layout.num_c, len(precision.image_ids), len(precision.point_ids)
    q = np.linalg.inv(dense.T @ dense) * precision.variance.sigma0_squared
    rows = np.zeros((3 * n + 3 * p, dense.shape[1]))  # centres, then points
    for k, image_id in enumerate(precision.image_ids):
        columns = layout.columns("frame", sub.image(int(image_id)).frame_id)
        rows[3 * k:3 * k + 3, columns] = image_jacobian(sub, int(image_id))[:3]
    rows[3 * n:, nc:] = np.eye(3 * p)
    sigma = rows @ q @ rows.T
    centre = precision.points.mean(0)
    g_points = similarity_basis(precision.points, centre).reshape(-1, 7)
    g_all = np.vstack([similarity_basis(precision.centres, centre).reshape(-1, 7), g_points])
    s = np.eye(len(sigma))
    s[:, 3 * n:] -= g_all @ np.linalg.solve(g_points.T @ g_points, g_points.T)
    expected = s @ sigma @ s.T
    scale = np.abs(expected).max()
    for k in range(n):
        np.testing.assert_allclose(inner.centre_cov[k], expected[3 * k:3 * k + 3, 3 * k:3 * k + 3],
                                   atol=1e-9 * scale)
    for i in range(p):
        j = 3 * n + 3 * i
        np.testing.assert_allclose(inner.point_cov[i], expected[j:j + 3, j:j + 3],
                                   atol=1e-9 * scale)
    # The inner datum removes the gauge: the point sigmas shrink, and no similarity is left.
    assert np.median(inner.point_sigmas) < np.median(precision.point_sigmas)
    flat = np.zeros((3 * p, 3 * p))
    flat[:] = expected[3 * n:, 3 * n:]
    assert np.abs(g_points.T @ flat).max() < 1e-8 * scale * np.abs(g_points).max() * p


def _workspace(tmp_path, scene):
    model = tmp_path / "sparse"
    model.mkdir()
    scene.truth.write(str(model))
    lines = ["# image_name X Y Z sX sY sZ"]
    for image in scene.truth.images.values():
        c = image.projection_center() + scene.store.origin + np.random.default_rng(
            image.image_id).normal(0, 0.05, 3)
        lines.append(f"{image.name} {c[0]:.4f} {c[1]:.4f} {c[2]:.4f} 0.05 0.05 0.08")
    (tmp_path / "gnss.txt").write_text("\n".join(lines) + "\n")
    return model


def test_cli_writes_the_table_and_outputs(tmp_path, scene, capsys):
    model = _workspace(tmp_path, scene)
    out = tmp_path / "out"
    code = cli_main(["precision", "--input_path", str(model), "--subset", "all=*",
                     "--subset", f"even={EVEN}", "--gnss", str(tmp_path / "gnss.txt"),
                     "--gnss_crs", "EPSG:25832", "--output_path", str(out), "--no_progress"])
    assert code == 0
    printed = capsys.readouterr().out
    table = [line.split() for line in printed.splitlines() if line.startswith(("all ", "even "))]
    assert [row[:2] for row in table] == [["all", "24"], ["even", "12"]]
    assert float(table[0][4]) < float(table[1][4])  # median sigma X in cm
    report = json.loads((out / "precision_subsets.json").read_text())
    assert report["gauge"] == "gnss" and report["units"] == "m"
    subsets = {s["name"]: s for s in report["subsets"]}
    assert subsets["even"]["num_images"] == 12
    assert int(table[1][2]) == subsets["even"]["num_points3D"]
    assert float(table[1][4]) == pytest.approx(100 * subsets["even"]["median_point_sigma"]["X"],
                                               abs=0.006)
    markdown = (out / "precision_subsets.md").read_text()
    assert "| even | 12 |" in markdown and "Shared tie points" in markdown
    for name in ("all_sigma_map.png", "even_sigma_map.png", "sigma_histograms.png"):
        data = (out / name).read_bytes()
        assert data[:8] == PNG and len(data) > 10_000
    assert len((out / "even_images.csv").read_text().splitlines()) == 1 + 12
    # Without GNSS: COLMAP's gauge, the table in the inner datum, JSON on stdout.
    code = cli_main(["precision", "--input_path", str(model), "--subset", "all=*",
                     "--datum", "inner", "--json", "--no_progress"])
    assert code == 0
    report = json.loads(capsys.readouterr().out)
    (only,) = report["subsets"]
    assert report["gauge"] == "fixed" and report["units"] == "model units"
    assert only["num_images_with_covariance"] == 22  # the two gauge images have none
    assert only["median_point_sigma_inner"]["X"] < only["median_point_sigma"]["X"]


@pytest.mark.parametrize("arguments, message", [
    (["--subset", "all"], r"--subset: malformed subset 'all'"),
    (["--subset", "a b=*"], r"subset name 'a b'"),
    (["--subset", "all=*", "--subset", "all=s0*"], r"subset 'all' given twice"),
    (["--subset", "nadir=nadir/*"], r"sparse: subset 'nadir': glob 'nadir/\*' matches no"),
    (["--subset", "one=s0000_L.jpg,s0000_R.jpg"], r"sparse: subset 'one' is too small"),
    (["--subset", "all=*", "--max_images", "10"], r"subset 'all' has 24 images, more than "
                                                  r"--max_images 10"),
])
def test_bad_input_is_one_clear_error(tmp_path, scene, capsys, arguments, message):
    model = _workspace(tmp_path, scene)
    code = cli_main(["precision", "--input_path", str(model), "--no_progress", *arguments])
    err = capsys.readouterr().err
    assert code == 2 and "Traceback" not in err
    assert err.startswith("error: ") and re.search(message, err), err


def test_missing_model_and_taken_output(tmp_path, scene, capsys):
    code = cli_main(["precision", "--input_path", str(tmp_path / "nope"), "--subset", "all=*"])
    assert code == 2 and "nope: COLMAP model directory does not exist" in capsys.readouterr().err
    model = _workspace(tmp_path, scene)
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "x").write_text("")
    code = cli_main(["precision", "--input_path", str(model), "--subset", "all=*",
                     "--output_path", str(taken)])
    assert code == 2 and "output path exists" in capsys.readouterr().err
    with pytest.raises(InputError, match="GNSS for only"):
        rec = pycolmap.Reconstruction(scene.truth)
        priors = _priors(rec)
        keep = np.isin(priors.image_ids, [1, 2])
        few = GNSSPriors(priors.image_ids[keep], priors.positions[keep], priors.sigmas[keep])
        precision_subsets(rec, ["all=*"], few, progress=False)


def test_geographic_gnss_goes_to_its_utm_zone(tmp_path, scene, capsys):
    from pyproj import Transformer

    from colmap_citymodel.citymodel.crs import fallback_geoid
    from colmap_citymodel.precision.subsets import main

    model = _workspace(tmp_path, scene)
    projected = main(model, [f"even={EVEN}"], gnss=tmp_path / "gnss.txt", gnss_crs="EPSG:25832",
                     progress=False)
    # The same positions as latitude, longitude, ellipsoidal height (EPSG order).
    to_geographic = Transformer.from_crs("EPSG:25832", "EPSG:4326", always_xy=True)
    lines = []
    for line in (tmp_path / "gnss.txt").read_text().splitlines()[1:]:
        name, x, y, z, *sigma = line.split()
        lon, lat = to_geographic.transform(float(x), float(y))
        lines.append(f"{name} {lat:.10f} {lon:.10f} {z} {' '.join(sigma)}")
    (tmp_path / "gnss_wgs84.txt").write_text("\n".join(lines) + "\n")
    geographic = main(model, [f"even={EVEN}"], gnss=tmp_path / "gnss_wgs84.txt",
                      gnss_crs="EPSG:4979", progress=False)
    capsys.readouterr()
    assert "EPSG:32632" in geographic["gauge_note"]  # UTM zone 32N, as ETRS89 / UTM 32N
    a, b = projected["subsets"][0], geographic["subsets"][0]
    assert a["num_points3D"] == b["num_points3D"]
    # The geographic file's ellipsoidal heights go through the geoid (EGM96, where installed)
    # into the UTM frame, the projected file's stay as given: the frames differ by the geoid's
    # height and slope, and the sigmas by a few per mille.
    tolerance = 2e-3 if fallback_geoid() is None else 1e-2
    for key in ("median_point_sigma", "median_centre_sigma", "median_point_sigma_inner"):
        for axis, value in a[key].items():
            assert b[key][axis] == pytest.approx(value, rel=tolerance), (key, axis)
