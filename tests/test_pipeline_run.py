"""`run` from an image folder: the matcher chosen from the data, COLMAP's features and matches
that a second run reuses (real photos from tests/data, downscaled for speed), the GNSS as the
database's pose priors that COLMAP's spatial matcher pairs by, the run record, the CLI."""

from __future__ import annotations

import gzip
import json
import logging
import shutil
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.block.image_metadata import ImageMetadata, read_folder_metadata
from colmap_citymodel.cli import build_parser
from colmap_citymodel.errors import InputError
from colmap_citymodel.pipeline.features import extract, images_with_features
from colmap_citymodel.pipeline.images import read_image_folder
from colmap_citymodel.pipeline.matching import (MatcherChoice, candidate_pairs, choose_matcher,
                                                frame_sequence, match, sync_pose_priors)
from colmap_citymodel.pipeline.options import MatchingChoiceOptions, RunOptions
from colmap_citymodel.pipeline.state import RunState
from data_paths import LUND

SMALL = pycolmap.FeatureExtractionOptions()
SMALL.max_image_size = 320  # a quarter of the photos' width: seconds instead of tens


def test_matcher_choice():
    options = MatchingChoiceOptions()
    few = [f"IMG_{k}.jpg" for k in range(12)]
    assert choose_matcher(few, {}).matcher == "exhaustive"
    names = [f"DJI_{k:04d}.JPG" for k in range(1, 61)]
    line = {n: np.array([500000.0 + 30.0 * k, 5700000.0]) for k, n in enumerate(names)}
    spatial = choose_matcher(names, line)
    assert spatial.matcher == "spatial" and "GNSS for all 60" in spatial.reason
    # photos 30 m apart: neighbours up to 10 spacings away, not COLMAP's 100 m
    assert spatial.pairing["max_distance"] == pytest.approx(300.0)
    assert spatial.pairing["max_num_neighbors"] == options.spatial_neighbors
    # one image without GNSS would get no spatial pairs: the names decide
    partial = dict(list(line.items())[1:])
    assert choose_matcher(names, partial).matcher == "sequential"
    frames = [f"frames/frame_{k:06d}.png" for k in range(0, 400, 5)]  # every 5th exported
    video = choose_matcher(frames, {})
    assert video.matcher == "sequential" and video.pairing["overlap"] == 10
    shuffled = [f"{word}_{k}.jpg" for k, word in
                enumerate(["house", "street", "tower", "roof", "door"] * 8)]
    assert choose_matcher(shuffled, {}).matcher == "exhaustive"
    assert choose_matcher(names, {}, matcher="spatial").reason == "--matcher"
    with pytest.raises(InputError, match="--matcher"):
        choose_matcher(names, {}, matcher="vocabtree")


def test_frame_sequence():
    options = MatchingChoiceOptions()
    assert frame_sequence([f"f{k:04d}.jpg" for k in range(100)], options)
    assert not frame_sequence([f"f{k:04d}.jpg" for k in range(0, 5000, 50)], options)
    mixed = [f"a{k}.jpg" for k in range(50)] + [f"b{k}.jpg" for k in range(50)]
    assert not frame_sequence(mixed, options)


def photos(folder, count):
    folder.mkdir(exist_ok=True)
    for k in range(1, count + 1):
        shutil.copyfile(LUND / f"{k:02d}.jpg", folder / f"{k:02d}.jpg")
    return folder


def test_features_and_matches_are_reused(tmp_path):
    """A second run extracts only the new image (into the camera of the others) and matches
    only its pairs; the first images' keypoints stay as they were."""
    folder_path = photos(tmp_path / "images", 3)
    database = tmp_path / "run" / "database.db"
    state = RunState.open(tmp_path / "run")
    first = extract(read_image_folder(folder_path), database, state, extraction=SMALL,
                    progress=False)
    assert (first["extracted"], first["reused"], first["cameras"]) == (3, 0, 1)
    with pycolmap.Database.open(str(database)) as db:
        before = {i.name: db.read_keypoints(i.image_id) for i in db.read_all_images()}
    exhaustive = MatcherChoice("exhaustive", "test")
    done = match(database, exhaustive, database.parent, options=RunOptions(matching_chunk=2),
                 progress=False)
    assert (done["pairs"], done["matched"], done["reused"]) == (3, 3, 0)
    assert done["verified_pairs"] >= 2
    shutil.copyfile(LUND / "04.jpg", folder_path / "04.jpg")
    state = RunState.open(database.parent)  # a new run: the group's camera from run.json
    second = extract(read_image_folder(folder_path), database, state, extraction=SMALL,
                     progress=False)
    assert (second["extracted"], second["reused"], second["cameras"]) == (1, 3, 1)
    with pycolmap.Database.open(str(database)) as db:
        for image in db.read_all_images():
            if image.name in before:
                np.testing.assert_array_equal(db.read_keypoints(image.image_id),
                                              before[image.name])
    again = match(database, exhaustive, database.parent, progress=False)
    assert (again["pairs"], again["matched"], again["reused"]) == (6, 3, 3)
    assert match(database, exhaustive, database.parent, progress=False)["matched"] == 0
    third = extract(read_image_folder(folder_path), database, RunState.open(database.parent),
                    extraction=SMALL, progress=False)
    assert third["extracted"] == 0 and third["reused"] == 4


def test_spatial_pairs_follow_the_gnss(tmp_path):
    """COLMAP's spatial matcher pairs the images by the positions written as pose priors:
    along a line each image with its nearest (spaced unevenly: no image has two nearest)."""
    database = tmp_path / "run" / "database.db"
    folder = read_image_folder(photos(tmp_path / "images", 4))
    extract(folder, database, RunState.open(database.parent), extraction=SMALL,
            progress=False)
    names = sorted(images_with_features(database))
    order = [names[k] for k in (2, 0, 3, 1)]  # the line's order is not the names'
    gnss = SimpleNamespace(
        image_names=order,
        positions=np.array([[400000.0 + x, 6100000.0, 30.0] for x in (0.0, 40.0, 70.0, 115.0)]),
        sigmas=np.tile([2.0, 2.0, 4.0], (4, 1)))
    assert sync_pose_priors(database, gnss) == 4
    with pycolmap.Database.open(str(database)) as db:
        priors = db.read_all_pose_priors()
        assert len(priors) == 4
        assert all(p.coordinate_system == pycolmap.PosePriorCoordinateSystem.CARTESIAN
                   for p in priors)
        np.testing.assert_allclose(np.diag(priors[0].position_covariance), [4.0, 4.0, 16.0])
        np.testing.assert_allclose(priors[0].gravity, [0, 1, 0])  # COLMAP's, kept
    choice = MatcherChoice("spatial", "test", {"max_num_neighbors": 1, "max_distance": 50.0})
    expected = {tuple(sorted(order[k:k + 2])) for k in range(3)}
    assert set(candidate_pairs(database, choice)) == expected
    # GNSS for three: the fourth keeps no prior (not COLMAP's WGS84 one from its EXIF either)
    three = SimpleNamespace(image_names=order[:3], positions=gnss.positions[:3],
                            sigmas=gnss.sigmas[:3])
    assert sync_pose_priors(database, three) == 3
    with pycolmap.Database.open(str(database)) as db:
        assert db.num_pose_priors() == 3


def test_run_record_and_cli(tmp_path, caplog):
    taken = tmp_path / "taken"
    taken.mkdir()
    (taken / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match="no run.json"):
        RunState.open(taken)
    state = RunState.open(tmp_path / "run")
    with caplog.at_level(logging.INFO, logger="colmap_citymodel"):
        with state.step("features") as step:
            step.details = {"extracted": 3, "summary": "3 images extracted"}
        with pytest.raises(RuntimeError):
            with state.step("matches"):
                raise RuntimeError("interrupted")
    record = json.loads((tmp_path / "run" / "run.json").read_text())
    assert [(s["name"], s["status"]) for s in record["steps"]] == [("features", "done"),
                                                                  ("matches", "failed")]
    assert "step features: done in" in caplog.text
    args = build_parser().parse_args(["run", "--image_path", "img", "--citymodel", "a.gml",
                                      "--output_path", "out", "--single_camera"])
    assert args.camera_mode == "single" and args.matcher == "auto"
    assert not hasattr(args, "exif")


def test_camera_groups_from_exif(tmp_path):
    folder = read_image_folder(photos(tmp_path, 3))
    assert len(folder.camera_groups("auto")) == 1  # one phone, one image size
    assert len(folder.camera_groups("per_image")) == len(folder.names)
    meta = read_folder_metadata(LUND, ["01.jpg"])[0]
    meta.focal_length_mm = 26.0  # another lens
    folder.metadata.append(meta)
    assert len(folder.camera_groups("auto")) == 2 and len(folder.camera_groups("single")) == 1


def test_run_stops_and_goes_on(tmp_path, capsys):
    """`run` from a folder up to the matches, then again: the features and matches are the
    first run's; the database's pose priors are the EXIF positions in the model's CRS."""
    import pyproj
    from fuzz_inputs import _box_citygml

    from colmap_citymodel.block.gnss import read_gnss_exif
    from colmap_citymodel.citymodel.crs import user_crs
    from colmap_citymodel.pipeline.run import main

    images = photos(tmp_path / "images", 3)
    to_sweref = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:3006", always_xy=True)
    model = tmp_path / "boxes.gml.gz"  # a model as downloaded: gzip-compressed
    model.write_bytes(gzip.compress(
        _box_citygml(to_sweref.transform(13.1954, 55.6982), "EPSG:3006").encode()))
    out = tmp_path / "run"
    small = ["max_image_size=320"]
    first = main(images, model, out, stop_after="matches", extraction_options=small,
                 progress=False)
    assert [(s.name, s.status) for s in first.steps] == [
        ("inputs", "done"), ("features", "done"), ("matches", "done")]
    assert first.matcher.matcher == "exhaustive" and first.verdict is None
    rows = (out / "images.csv").read_text().splitlines()
    assert len(rows) == 4 and rows[1].startswith("01.jpg,1024,768,")
    gnss = read_gnss_exif(images, user_crs("EPSG:3006"))
    with pycolmap.Database.open(str(out / "database.db")) as db:
        names = {i.image_id: i.name for i in db.read_all_images()}
        priors = {names[p.corr_data_id.id]: p.position for p in db.read_all_pose_priors()}
    for name, position in zip(gnss.image_names, gnss.positions):
        np.testing.assert_allclose(priors[name], position)
    (out / "refined").mkdir()  # an earlier refine's result: a run without refine keeps it
    (out / "refined" / "report.json").write_text('{"earlier": true}')
    second = main(images, model, out, stop_after="matches", extraction_options=small,
                  progress=False)
    assert [s.status for s in second.steps] == ["done", "reused", "reused"]
    assert json.loads((out / "refined" / "report.json").read_text()) == {"earlier": True}
    assert not (out / "refined.previous").exists()
    record = json.loads((out / "run.json").read_text())
    assert [s["status"] for s in record["steps"]] == ["done", "reused", "reused"]
    assert "matches    reused" in capsys.readouterr().out


def test_camera_options_fail_first(tmp_path):
    from colmap_citymodel.pipeline.features import reader_options
    from colmap_citymodel.pipeline.run import main

    assert reader_options("OPENCV", "800,790,512,384,0.1,0,0,0").camera_model == "OPENCV"
    with pytest.raises(InputError, match="takes 4 comma-separated values"):
        reader_options(None, "1000,512,384")
    with pytest.raises(InputError, match="not one of COLMAP's"):
        main(photos(tmp_path / "images", 1), "model.gml", tmp_path / "run",
             camera_model="PINHOLE_FISH")
    assert not (tmp_path / "run").exists()  # before any work


def test_attitude_check_against_the_gimbal():
    """Cameras whose pose agrees with the gimbal's yaw and pitch (true north turned to the
    UTM grid: about -1.5 deg at 11 E 48 N in zone 32, whose meridian is 9 E) are 0 deg off;
    one turned by 10 deg is 10 deg off."""
    import pyproj

    from colmap_citymodel.citymodel.crs import user_crs
    from colmap_citymodel.pipeline.images import ImageFolder
    from colmap_citymodel.pipeline.run import attitude_check

    origin = np.array(pyproj.Transformer.from_crs("EPSG:4326", "EPSG:25832", always_xy=True)
                      .transform(11.0, 48.0) + (500.0,))
    store = SimpleNamespace(origin=origin, crs=user_crs("EPSG:25832"))
    rec = pycolmap.Reconstruction()
    rec.add_camera_with_trivial_rig(
        pycolmap.Camera.create_from_model_name(1, "PINHOLE", 1000.0, 1000, 800))
    north = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # looking along grid north, level
    down = np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])  # looking straight down
    turn = np.radians(10.0)
    turned = north @ np.array([[np.cos(turn), -np.sin(turn), 0],
                               [np.sin(turn), np.cos(turn), 0], [0, 0, 1]])
    metadata = []
    for k, (rotation, gimbal) in enumerate([(north, (1.49, 0.0, 0.0)),
                                            (down, (37.0, -90.0, 0.0)),
                                            (turned, (1.49, 0.0, 0.0))], start=1):
        name = f"DJI_{k:04d}.JPG"
        image = pycolmap.Image(image_id=k, name=name, camera_id=1)
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), [0.0, 0.0, 10.0 * k]))
        metadata.append(ImageMetadata(name=name, gimbal=gimbal))
    check = attitude_check(rec, ImageFolder(Path("."), metadata), store)
    assert check["grid_north_turn_deg"] == pytest.approx(-1.49, abs=0.02)
    angles = {a["image"]: a["deg"] for a in check["largest"]}
    assert angles["DJI_0001.JPG"] < 0.05 and angles["DJI_0002.JPG"] < 0.01
    assert angles["DJI_0003.JPG"] == pytest.approx(10.0, abs=0.05)
    assert check["images"] == 3 and check["max_deg"] == pytest.approx(10.0, abs=0.05)


@pytest.mark.slow
def test_run_on_real_photos(tmp_path):
    """The 29 Lund street photos from their folder (EXIF GPS of a phone, 10 m), with run's
    defaults: COLMAP's SIFT, every pair matched, mapping registers most of them (this
    forward-moving sequence maps from some of COLMAP's random seeds only: RunOptions.
    remap_attempts); a second run reuses every step. No city model of Lund: boxes near the
    photos stand in (the model enters mapping; refine is not run). About 130 s of CPU time,
    7 minutes on a shared two-core machine."""
    import pyproj
    from fuzz_inputs import _box_citygml

    from colmap_citymodel.pipeline.run import main

    to_sweref = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:3006", always_xy=True)
    model = tmp_path / "boxes.gml"
    model.write_text(_box_citygml(to_sweref.transform(13.1954, 55.6982), "EPSG:3006"))
    first = main(LUND, model, tmp_path / "run", stop_after="mapping", progress=False)
    assert first.matcher.matcher == "exhaustive" and "29 images" in first.matcher.reason
    assert first.mapping["num_database_images"] == 29
    assert first.mapping["num_registered_images"] >= 20
    assert (tmp_path / "run" / "sparse" / "0" / "images.bin").exists()
    second = main(LUND, model, tmp_path / "run", stop_after="mapping", progress=False)
    assert [s.status for s in second.steps] == ["done", "reused", "reused", "reused"]
    assert second.mapping["num_registered_images"] == first.mapping["num_registered_images"]
    assert sum(s.seconds for s in second.steps) < 0.2 * sum(s.seconds for s in first.steps)


def test_a_mapped_block_rolled_about_its_straight_track_is_refined_from_the_whole_block(
        street_scene):
    """Mapping georegisters the block at its first images with GNSS, where a short, nearly
    straight track leaves the roll about it to the few tie points seen by then. With GNSS,
    `run` lets refine fit the whole mapped block to GNSS itself (start_transform None, also
    where mapping left it in model CRS): the mapped street, rolled 15 deg about its track,
    lands within 0.1 m of the truth. Without GNSS refine starts where mapping placed it."""
    from scipy.spatial.transform import Rotation

    from colmap_citymodel.options import RefineOptions
    from colmap_citymodel.pipeline.run import start_transform
    from colmap_citymodel.workflow import refine

    scene = street_scene
    centres = np.array([im.projection_center() for im in scene.truth.images.values()])
    centre = centres.mean(axis=0)
    track = np.linalg.svd(centres - centre)[2][0]
    turn = Rotation.from_rotvec(np.radians(15.0) * track).as_matrix()
    mapped = pycolmap.Reconstruction(scene.truth)
    mapped.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(turn),
                                    centre - turn @ centre + scene.store.origin))
    read = SimpleNamespace(observations=scene.gnss(), initial_transform=None)
    assert start_transform({"frame": "crs"}, read) is None
    assert start_transform({"frame": "crs"}, SimpleNamespace(
        observations=None, initial_transform=None)) is not None  # placed on the model

    result = refine(mapped, scene.store, scene.gnss(), RefineOptions(),
                    initial_transform=start_transform({"frame": "crs"}, read), progress=False)
    truth = {im.name: im.projection_center() for im in scene.truth.images.values()}
    rec = result.reconstruction
    errors = [rec.image(i).projection_center() - truth[rec.image(i).name]
              for i in rec.reg_image_ids()]
    assert np.sqrt(np.mean(np.sum(np.square(errors), axis=1))) < 0.10
