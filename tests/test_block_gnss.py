"""GNSS readers: text, EXIF (real Lund photos), COLMAP database pose priors, matching."""

from __future__ import annotations

import logging
import sqlite3
import struct
import warnings

import numpy as np
import pycolmap
import pyproj
import pytest

from colmap_citymodel.block.gnss import GNSSObservations, _crs_info, apply_lever_arm, match_to_reconstruction, read_gnss_database, read_gnss_exif, read_gnss_text, reproject_with_report, rotations_from_reconstruction
from colmap_citymodel.citymodel import crs
from colmap_citymodel.errors import GNSSError
from data_paths import LUND

SWEREF = _crs_info("EPSG:3006")
UTM32_DHHN = _crs_info("EPSG:25832+7837")


def _utm32(lat, lon):
    t = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True)
    return np.array(t.transform(lon, lat))


def test_text_same_crs_with_sigmas_and_comments(tmp_path):
    path = tmp_path / "gnss.txt"
    path.write_text(
        "# name X Y Z [sX sY sZ]\n"
        "a.jpg 691000.5 5336000.25 520.0\n"
        "\n"
        "b.jpg 691010.0 5336001.0 521.5 0.5 0.6 0.9  # RTK\n"
    )
    gnss = read_gnss_text(path, "EPSG:25832+7837", UTM32_DHHN)
    assert gnss.image_names == ["a.jpg", "b.jpg"]
    np.testing.assert_array_equal(gnss.positions[1], [691010.0, 5336001.0, 521.5])
    np.testing.assert_array_equal(gnss.sigmas, [[3, 3, 5], [0.5, 0.6, 0.9]])
    assert gnss.source == "text" and gnss.vertical_applied is None
    np.testing.assert_allclose(gnss.to_local([691000, 5336000, 500])[0], [0.5, 0.25, 20.0])
    sub = gnss.subset(["b.jpg"])
    assert sub.image_names == ["b.jpg"] and sub.positions.shape == (1, 3)
    with pytest.raises(GNSSError, match="c.jpg"):
        gnss.subset(["c.jpg"])


@pytest.fixture
def no_fallback_geoid(monkeypatch):
    """A machine without Debian's proj-data: no EGM96 grid anywhere."""
    monkeypatch.setattr(crs, "fallback_geoid", lambda: None)


def _write_wgs84(tmp_path, lat, lon, h):
    path = tmp_path / "gnss.txt"
    path.write_text(f"img1.jpg {lat} {lon} {h}\nimg2.jpg {lat + 1e-4} {lon} {h + 1}\n")
    return path


def _german_grid_installed() -> bool:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        group = pyproj.transformer.TransformerGroup("EPSG:4979", "EPSG:25832+7837")
    return bool(group.best_available)


def test_text_wgs84_to_utm_without_any_geoid_keeps_heights_ellipsoidal(tmp_path, caplog,
                                                                       no_fallback_geoid):
    lat, lon, h = 48.1489, 11.5680, 560.0  # TUM main campus, Munich
    with caplog.at_level("WARNING", logger="colmap_citymodel"):
        gnss = read_gnss_text(_write_wgs84(tmp_path, lat, lon, h), "EPSG:4979", UTM32_DHHN)
    # Horizontal: lat/lon (EPSG axis order) -> easting/northing, agrees with a 2D transform.
    np.testing.assert_allclose(gnss.positions[0, :2], _utm32(lat, lon), atol=0.01)
    assert 10.5 < gnss.positions[1, 1] - gnss.positions[0, 1] < 11.6  # 1e-4 deg north ~ 11.1 m
    if not _german_grid_installed():
        # No German geoid grid and no EGM96: heights unchanged, clearly reported.
        assert gnss.vertical_applied is False and gnss.geoid is None
        np.testing.assert_allclose(gnss.positions[:, 2], [h, h + 1])
        assert "ELLIPSOIDAL" in caplog.text and "de_bkg_gcg2016" in caplog.text
        assert "proj-data" in caplog.text and "--gnss_height_offset auto" in caplog.text
    assert "ballpark offset" not in caplog.text  # the horizontal datum shift is a real one


@pytest.mark.skipif(crs.fallback_geoid() is None, reason="EGM96 grid (proj-data) not installed")
def test_text_wgs84_to_utm_falls_back_to_egm96_and_says_so(tmp_path, caplog):
    lat, lon, h = 48.1489, 11.5680, 560.0
    with caplog.at_level("WARNING", logger="colmap_citymodel"):
        gnss = read_gnss_text(_write_wgs84(tmp_path, lat, lon, h), "EPSG:4979", UTM32_DHHN)
    np.testing.assert_allclose(gnss.positions[0, :2], _utm32(lat, lon), atol=0.01)
    if _german_grid_installed():
        pytest.skip("the German grid is installed: PROJ applies it, no fallback")
    undulation = crs.geoid_undulation([lon, lon], [lat, lat + 1e-4], crs.fallback_geoid())
    assert 44.0 < undulation[0] < 49.0  # EGM96 in Munich
    np.testing.assert_allclose(gnss.positions[:, 2], np.array([h, h + 1]) - undulation,
                               atol=1e-6)
    assert gnss.vertical_applied is True
    assert gnss.geoid["name"] == "EGM96" and gnss.geoid["missing_grids"] == ["de_bkg_gcg2016.tif"]
    assert gnss.geoid["mean_undulation_m"] == pytest.approx(undulation.mean())
    # The warning names the grid used, its accuracy and the national grid that was missing.
    assert "EGM96" in caplog.text and crs.fallback_geoid().grid in caplog.text
    assert "de_bkg_gcg2016.tif" in caplog.text and "within 2 m" in caplog.text


@pytest.mark.skipif(crs.fallback_geoid() is None, reason="EGM96 grid (proj-data) not installed")
def test_fallback_geoid_for_a_model_crs_without_height_system(tmp_path):
    # City models hold physical heights even where the CRS names none (EPSG:25832 alone).
    lat, lon, h = 48.1489, 11.5680, 560.0
    gnss = read_gnss_text(_write_wgs84(tmp_path, lat, lon, h), "EPSG:4979",
                          _crs_info("EPSG:25832"))
    undulation = crs.geoid_undulation([lon], [lat], crs.fallback_geoid())[0]
    assert gnss.positions[0, 2] == pytest.approx(h - undulation)
    assert gnss.vertical_applied is True and gnss.geoid["missing_grids"] == []


def test_a_grid_proj_has_wins_over_the_fallback(tmp_path, monkeypatch):
    # A fake EGM96 grid (constant undulation 40 m) in GTX format where PROJ looks: PROJ applies
    # it itself (the national grid of the model's height system, here EGM96 height), and the
    # fallback is not used. Without it: the fallback (the real EGM96, if installed) or nothing.
    grid_dir = tmp_path / "grids"
    grid_dir.mkdir()
    rows, cols = 181, 361
    with open(grid_dir / "egm96_15.gtx", "wb") as f:
        f.write(struct.pack(">4d2i", -90.0, -180.0, 1.0, 1.0, rows, cols))
        f.write(np.full(rows * cols, 40.0, dtype=">f4").tobytes())
    target = _crs_info("EPSG:32633+5773")  # UTM 33N + EGM96 height
    lla = np.array([[55.7, 13.19, 100.0]])
    with monkeypatch.context() as patch:
        patch.setattr(crs, "fallback_geoid", lambda: None)
        before, report = reproject_with_report(lla, "EPSG:4979", target)
    assert report.vertical_applied is False and before[0, 2] == pytest.approx(100.0)
    if crs.fallback_geoid() is not None:
        fallback, report = reproject_with_report(lla, "EPSG:4979", target)
        assert report.vertical_applied is True and report.geoid["name"] == "EGM96"
        assert 30.0 < 100.0 - fallback[0, 2] < 40.0  # EGM96 near Lund: ~35 m
    original = pyproj.datadir.get_data_dir()
    try:
        pyproj.datadir.append_data_dir(str(grid_dir))
        after, report = reproject_with_report(lla, "EPSG:4979", target)
    finally:
        pyproj.datadir.set_data_dir(original)
    assert report.vertical_applied is True and report.geoid is None
    assert after[0, 2] == pytest.approx(60.0, abs=1e-6)
    assert any("undulation 40.00 m" in n for n in report.notes)
    np.testing.assert_allclose(after[0, :2], before[0, :2], atol=1e-6)


@pytest.mark.parametrize(
    "content, match",
    [
        ("a.jpg 1 2\n", "line 1: expected"),
        ("# ok\na.jpg 1 2 x\n", "line 2: not a number"),
        ("a.jpg 1 2 3\na.jpg 1 2 3\n", "line 2: image 'a.jpg' already given on line 1"),
        ("a.jpg 1 2 3 1 1\n", "line 1: expected"),
        ("a.jpg 1 2 3 1 0 1\n", "line 1: sigmas must be positive"),
        ("# only comments\n", "no GNSS positions"),
        ("a.jpg 1 2 nan\n", "line 1: non-finite"),
    ],
)
def test_text_malformed(tmp_path, content, match):
    path = tmp_path / "bad.txt"
    path.write_text(content)
    with pytest.raises(GNSSError, match=match) as info:
        read_gnss_text(path, "EPSG:25832", UTM32_DHHN)
    assert "bad.txt" in str(info.value)


def test_text_latitude_out_of_range_names_axis_order(tmp_path):
    path = tmp_path / "swapped.txt"
    path.write_text("a.jpg 148.15 11.57 560\n")  # latitude out of range
    with pytest.raises(GNSSError, match="axis order"):
        read_gnss_text(path, "EPSG:4979", UTM32_DHHN)
    path.write_text("a.jpg 11.57 48.15 560\n")  # lon/lat swapped: lands near Somalia
    with pytest.raises(GNSSError, match="area of the model CRS.*axis order"):
        read_gnss_text(path, "EPSG:4979", UTM32_DHHN)


def test_text_missing_file(tmp_path):
    with pytest.raises(GNSSError, match="cannot read"):
        read_gnss_text(tmp_path / "nope.txt", "EPSG:25832", UTM32_DHHN)


def test_exif_lund_photos():
    files = sorted(p for p in LUND.iterdir() if p.suffix.lower() == ".jpg")
    gnss = read_gnss_exif(LUND, SWEREF)
    assert gnss.image_names == [p.name for p in files] and len(gnss) == 29
    # Lund Cathedral, 55.6975 N 13.1935 E, in SWEREF99 TM.
    t = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:3006", always_xy=True)
    cathedral = np.array(t.transform(13.1935, 55.6975))
    centre = gnss.positions[:, :2].mean(axis=0)
    assert np.linalg.norm(centre - cathedral) < 200.0
    extent = gnss.positions.max(axis=0) - gnss.positions.min(axis=0)
    assert np.all(extent[:2] < 200.0) and extent[2] < 30.0
    assert np.all((gnss.positions[:, 2] > 0) & (gnss.positions[:, 2] < 120))
    # GPSDOP 10 (the photos' accuracy in metres) -> sigma_h 10, sigma_z 10 * 5/3.
    np.testing.assert_allclose(gnss.sigmas[0], [10.0, 10.0, 50.0 / 3.0])
    # UTM 33N agrees with SWEREF99 TM to well below a metre (same ellipsoid/projection family
    # differ only in false easting / central meridian: compare distances, not coordinates).
    utm = read_gnss_exif(LUND, _crs_info("EPSG:32633"))
    d_sweref = np.linalg.norm(gnss.positions[0, :2] - gnss.positions[-1, :2])
    d_utm = np.linalg.norm(utm.positions[0, :2] - utm.positions[-1, :2])
    assert abs(d_sweref - d_utm) < 0.05 * max(d_sweref, 1.0)


def test_exif_directory_without_gps(tmp_path):
    from PIL import Image

    Image.new("RGB", (8, 8)).save(tmp_path / "plain.jpg")
    with pytest.raises(GNSSError, match="none of the 1 images"):
        read_gnss_exif(tmp_path, SWEREF)
    with pytest.raises(GNSSError, match="does not exist"):
        read_gnss_exif(tmp_path / "missing", SWEREF)


def _database_with_priors(tmp_path):
    db_path = tmp_path / "database.db"
    database = pycolmap.Database.open(str(db_path))
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_frames_per_rig = 4
    options.num_points3D = 20
    reconstruction = pycolmap.synthesize_dataset(options, database)
    images = sorted(database.read_all_images(), key=lambda im: im.image_id)
    lat0, lon0 = 48.1489, 11.5680
    truth = {}
    for k, image in enumerate(images):
        prior = pycolmap.PosePrior()
        prior.corr_data_id = image.data_id
        if k < 2:
            prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.WGS84
            prior.position = np.array([lat0 + 1e-4 * k, lon0, 560.0 + k])
            prior.position_covariance = np.diag([0.25, 0.36, 1.0])
            truth[image.name] = ("wgs", prior.position.copy())
        else:
            prior.coordinate_system = pycolmap.PosePriorCoordinateSystem.CARTESIAN
            prior.position = np.array([691000.0 + k, 5336000.0, 520.0])
            truth[image.name] = ("xyz", prior.position.copy())
        database.write_pose_prior(prior)
    database.close()
    return db_path, reconstruction, truth


def test_database_pose_priors_round_trip(tmp_path):
    db_path, _, truth = _database_with_priors(tmp_path)
    with sqlite3.connect(db_path) as connection:  # as the simulator's and COLMAP's databases
        connection.execute("PRAGMA journal_mode=WAL")
    before = db_path.read_bytes()
    gnss = read_gnss_database(db_path, UTM32_DHHN)
    assert db_path.read_bytes() == before  # the user's database is never rewritten
    assert gnss.source == "database" and sorted(gnss.image_names) == sorted(truth)
    for i, name in enumerate(gnss.image_names):
        kind, value = truth[name]
        if kind == "wgs":
            np.testing.assert_allclose(gnss.positions[i, :2], _utm32(value[0], value[1]),
                                       atol=0.01)
            # No German grid here: the fallback geoid, if installed, else ellipsoidal.
            geoid = crs.fallback_geoid()
            undulation = (0.0 if geoid is None else
                          crs.geoid_undulation([value[1]], [value[0]], geoid)[0])
            assert gnss.positions[i, 2] == pytest.approx(value[2] - undulation)
            np.testing.assert_allclose(gnss.sigmas[i], [0.5, 0.6, 1.0])
        else:
            np.testing.assert_array_equal(gnss.positions[i], value)
            np.testing.assert_array_equal(gnss.sigmas[i], [3, 3, 5])  # NaN covariance


def test_database_without_priors(tmp_path):
    db_path = tmp_path / "empty.db"
    database = pycolmap.Database.open(str(db_path))
    pycolmap.synthesize_dataset(pycolmap.SyntheticDatasetOptions(), database)
    database.close()
    with pytest.raises(GNSSError, match="no pose priors"):
        read_gnss_database(db_path, UTM32_DHHN)
    with pytest.raises(GNSSError, match="does not exist"):
        read_gnss_database(tmp_path / "missing.db", UTM32_DHHN)


def test_synthesized_priors_are_linked_by_image_data_id(tmp_path):
    # COLMAP's own synthesizer writes priors linked through image.data_id; they must come back
    # as the projection centres of the same images.
    db_path = tmp_path / "synth.db"
    database = pycolmap.Database.open(str(db_path))
    options = pycolmap.SyntheticDatasetOptions()
    options.prior_position = True
    options.num_rigs = 2
    options.num_cameras_per_rig = 2
    options.num_frames_per_rig = 3
    reconstruction = pycolmap.synthesize_dataset(options, database)
    database.close()
    gnss = read_gnss_database(db_path, UTM32_DHHN)
    centres = {im.name: im.projection_center() for im in reconstruction.images.values()}
    assert len(gnss) == len(centres)
    for name, position in zip(gnss.image_names, gnss.positions):
        np.testing.assert_allclose(position, centres[name], atol=1e-9)


def test_match_to_reconstruction_and_lever_arm():
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_frames_per_rig = 5
    reconstruction = pycolmap.synthesize_dataset(options)
    names = sorted(im.name for im in reconstruction.images.values())
    centres = {im.name: im.projection_center() for im in reconstruction.images.values()}
    origin = np.array([100.0, 200.0, 300.0])
    gnss = GNSSObservations(
        image_names=names,
        positions=np.array([centres[n] for n in names]) + origin,
        sigmas=np.full((len(names), 3), 2.0),
        crs=UTM32_DHHN,
        source="text",
    )
    ids, local, sigmas = match_to_reconstruction(gnss, reconstruction, origin)
    for image_id, position in zip(ids, local):
        np.testing.assert_allclose(position, reconstruction.image(int(image_id)).projection_center())
    assert sigmas.shape == (5, 3)

    with pytest.raises(GNSSError, match="only 2 of the 2 GNSS"):
        match_to_reconstruction(gnss.subset(names[:2]), reconstruction, origin)

    # Lever arm: antenna 0.3 m above the camera (-y in COLMAP's camera frame) -> centres recovered.
    lever = np.array([0.0, -0.3, 0.1])
    rotations = rotations_from_reconstruction(reconstruction)
    antenna = gnss.positions + np.array([rotations[n].T @ lever for n in names])
    with_arm = GNSSObservations(names, antenna, gnss.sigmas, UTM32_DHHN, "text", lever_arm=lever)
    corrected = apply_lever_arm(with_arm, rotations)
    np.testing.assert_allclose(corrected.positions, gnss.positions, atol=1e-12)
    assert corrected.lever_arm is None


def test_match_to_reconstruction_partial_and_no_match(caplog):
    """Priors of images outside the reconstruction are dropped; no match at all is an error."""
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs = 1
    options.num_frames_per_rig = 5
    reconstruction = pycolmap.synthesize_dataset(options)
    names = sorted(im.name for im in reconstruction.images.values())
    by_name = {im.name: im for im in reconstruction.images.values()}
    origin = np.array([100.0, 200.0, 300.0])
    # GNSS of the whole image set (as a database holds it): two images are not in this model.
    all_names = ["other_block_1.png", names[0], names[3], "other_block_2.png", names[1]]
    positions = np.array(
        [[1.0, 2.0, 3.0]]
        + [by_name[names[0]].projection_center()]
        + [by_name[names[3]].projection_center()]
        + [[4.0, 5.0, 6.0]]
        + [by_name[names[1]].projection_center()]
    ) + origin
    sigmas = np.arange(15, dtype=np.float64).reshape(5, 3) + 1.0
    gnss = GNSSObservations(all_names, positions, sigmas, UTM32_DHHN, "database")
    with caplog.at_level(logging.INFO, logger="colmap_citymodel.block.gnss"):
        ids, local, matched_sigmas = match_to_reconstruction(gnss, reconstruction, origin)
    expected = [by_name[n].image_id for n in (names[0], names[3], names[1])]
    np.testing.assert_array_equal(ids, expected)
    for image_id, position in zip(ids, local):
        np.testing.assert_allclose(position, reconstruction.image(int(image_id)).projection_center())
    np.testing.assert_array_equal(matched_sigmas, sigmas[[1, 2, 4]])
    assert "2 of 5 GNSS position(s)" in caplog.text

    # No name matches (e.g. the database stores folder prefixes): error shows both namings.
    ghosts = GNSSObservations(
        [f"seq/{n}" for n in names], positions, sigmas, UTM32_DHHN, "database"
    )
    with pytest.raises(GNSSError, match="none of the 5 GNSS") as info:
        match_to_reconstruction(ghosts, reconstruction, origin)
    message = str(info.value)
    assert f"seq/{names[0]}" in message and repr(names[0]) in message


def test_text_unknown_gnss_crs_names_file(tmp_path):
    from colmap_citymodel.errors import CRSError

    path = tmp_path / "gnss.txt"
    path.write_text("a.jpg 1 2 3\n")
    with pytest.raises(CRSError, match="GNSS CRS 'EPSG:999999'") as info:
        read_gnss_text(path, "EPSG:999999", UTM32_DHHN)
    assert "gnss.txt" in str(info.value)
