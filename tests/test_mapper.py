"""`colmap-citymodel map` on the synthetic street: a COLMAP database of its true tracks (keypoints,
verified matches) is mapped incrementally; once enough images with GNSS are registered, every
global adjustment is the hybrid one with the model. GNSS (biased by about 2 m) only for the
first half of the images, as in a flight that loses GNSS between buildings.
"""

import subprocess
import sys

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.adjust import problem as problem_module
from colmap_citymodel.errors import InputError
from colmap_citymodel.mapper import ModelGlobalAdjustment, map_block, parse_option_values
from colmap_citymodel.options import MapperOptions, RefineOptions
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, centre_errors, make_street_scene

NUM_STATIONS = 14
NUM_GNSS = 24  # the first 8 stations (24.5 m: enough baseline for the 3 m GNSS sigma)


def write_database(scene, path):
    """Camera, images, the true tracks' keypoints, and for every pair of images sharing tie
    points their matches as verified two-view geometry (E, F from the true poses)."""
    truth = scene.truth
    camera = truth.camera(1)
    K = camera.calibration_matrix()
    Kinv = np.linalg.inv(K)
    with pycolmap.Database.open(str(path)) as db:
        camera_id = db.write_camera(camera, use_camera_id=True)
        camera = db.read_camera(camera_id)
        rig = pycolmap.Rig()
        rig.add_ref_sensor(camera.sensor_id)
        rig_id = db.write_rig(rig)
        ids = sorted(truth.reg_image_ids())
        for image_id in ids:
            image = truth.image(image_id)
            db.write_image(pycolmap.Image(name=image.name, camera_id=camera_id,
                                          image_id=image_id), use_image_id=True)
            frame = pycolmap.Frame()
            frame.rig_id = rig_id
            frame.add_data_id(db.read_image(image_id).data_id)
            db.write_frame(frame)
            db.write_keypoints(image_id, np.array([p.xy for p in image.points2D], np.float32))
        rows = {i: {p.point3D_id: k for k, p in enumerate(truth.image(i).points2D)}
                for i in ids}
        for a, i in enumerate(ids):
            for j in ids[a + 1:]:
                common = sorted(set(rows[i]) & set(rows[j]))
                if len(common) < 15:
                    continue
                m = np.array([[rows[i][p], rows[j][p]] for p in common], np.uint32)
                db.write_matches(i, j, m)
                pose_i, pose_j = truth.image(i).cam_from_world(), truth.image(j).cam_from_world()
                rel = pose_j * pose_i.inverse()
                R, t = np.asarray(rel.rotation.matrix()), np.asarray(rel.translation)
                tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
                tvg = pycolmap.TwoViewGeometry()
                if np.linalg.norm(t) < 1e-6:  # two cameras of one station: a rotation only
                    tvg.config = pycolmap.TwoViewGeometryConfiguration.PANORAMIC
                    tvg.H = K @ R @ Kinv
                else:
                    E = tx @ R
                    F = Kinv.T @ E @ Kinv
                    tvg.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                    tvg.E = E / np.linalg.norm(E)
                    tvg.F = F / np.linalg.norm(F)
                tvg.inlier_matches = m
                db.write_two_view_geometry(i, j, tvg)


@pytest.fixture(scope="module")
def street(tmp_path_factory):
    scene = make_street_scene(StreetSceneOptions(num_stations=NUM_STATIONS, station_spacing=3.5, seed=5))
    path = tmp_path_factory.mktemp("map") / "database.db"
    write_database(scene, path)
    gnss = scene.gnss()
    first = type(gnss)(gnss.image_names[:NUM_GNSS], gnss.positions[:NUM_GNSS],
                       gnss.sigmas[:NUM_GNSS], gnss.crs, "synthetic")
    return scene, path, first


def map_options():
    options = RefineOptions()
    options.precision.covariances = "off"
    return options


@pytest.fixture(scope="module")
def mapped(street):
    """The street mapped with the model; the hybrid problems the global adjustments built."""
    scene, path, gnss = street
    built = []
    original = problem_module.HybridProblem.__init__

    def spy(self, *args, **kwargs):
        original(self, *args, **kwargs)
        built.append(self)

    problem_module.HybridProblem.__init__ = spy
    try:
        mapper_options = MapperOptions(hybrid_iterations=2)
        adjust = ModelGlobalAdjustment(scene.store, gnss, map_options(), mapper_options)
        pipeline = pycolmap.IncrementalPipelineOptions()
        pipeline.multiple_models = False
        pipeline.num_threads = 1
        pipeline.random_seed = 1
        pipeline.ba_global_frames_ratio = 1.3  # fewer global adjustments than COLMAP's 1.1
        block = map_block(path, scene.store, gnss, map_options(), mapper_options, pipeline,
                          progress=False, global_adjustment=adjust)
    finally:
        problem_module.HybridProblem.__init__ = original
    return block, adjust, built


def test_global_adjustments_take_the_model_once_georegistered(mapped):
    block, adjust, built = mapped
    kinds = [a.kind for a in block.adjustments]
    assert "hybrid" in kinds, kinds
    # COLMAP's until georegistration, the model's after it (never back).
    first = kinds.index("hybrid")
    assert all(k == "hybrid" for k in kinds[first:]), kinds
    assert block.georegistered_at is not None
    assert block.georegistered_at >= MapperOptions().min_gnss_images
    hybrid = [a for a in block.adjustments if a.kind == "hybrid"]
    assert all(a.num_assigned > 100 and a.num_planes >= 4 for a in hybrid), hybrid
    # The model's residuals are in the problems the global adjustments solved.
    assert adjust.last_problem is not None and adjust.last_problem.blocks.faces.size >= 4
    with_planes = [p for p in built if p.blocks is not None and p.blocks.faces.size]
    assert len(with_planes) >= len(hybrid)


def test_mapped_block_lands_on_the_truth(street, mapped):
    scene, _, _ = street
    block, _, _ = mapped
    rec = block.reconstruction
    assert rec.num_reg_images() == scene.truth.num_reg_images()
    errors = centre_errors(rec, scene.truth)
    rms = float(np.sqrt(np.mean(errors ** 2)))
    # GNSS is biased by ~2 m and covers only the first half: the model puts the block on the
    # truth within a few decimetres, all along.
    assert rms < 0.3, rms
    assert np.max(errors) < 0.6


def run_map(tmp_path, database: str) -> subprocess.CompletedProcess:
    """`colmap-citymodel map` on `tmp_path / database`, images and model that do not exist."""
    return subprocess.run(
        [sys.executable, "-m", "colmap_citymodel", "map", "--database_path",
         str(tmp_path / database), "--image_path", str(tmp_path / "images"), "--citymodel",
         str(tmp_path / "m.gml"), "--output_path", str(tmp_path / "out")],
        capture_output=True, text=True, timeout=120)


def test_missing_database_is_one_clear_error(tmp_path):
    result = run_map(tmp_path, "none.db")
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert result.stderr.strip() == f"error: the database {tmp_path / 'none.db'} does not exist"
    assert not (tmp_path / "out").exists()


def test_database_without_features_and_images_is_one_clear_error(tmp_path):
    with pycolmap.Database.open(str(tmp_path / "empty.db")):
        pass
    result = run_map(tmp_path, "empty.db")
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "holds no features and the image directory" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_option_values_parse_as_colmap_takes_them():
    assert parse_option_values(["ba_global_frames_ratio=1.2", "mapper.init_min_num_inliers=50",
                                "ba_refine_focal_length=false", "snapshot_path=/tmp/x"],
                               "--mapper_options") == {
        "ba_global_frames_ratio": 1.2, "mapper": {"init_min_num_inliers": 50},
        "ba_refine_focal_length": False, "snapshot_path": "/tmp/x"}
    with pytest.raises(InputError, match="KEY=VALUE"):
        parse_option_values(["ba_global_frames_ratio"], "--mapper_options")


def test_cli_passes_the_shared_and_the_mapping_options_on(monkeypatch):
    import types

    import colmap_citymodel.mapper as mapper
    from colmap_citymodel import cli

    seen = {}

    def fake_main(*args, **kwargs):
        seen.update(kwargs, args=args)
        return types.SimpleNamespace(quality=types.SimpleNamespace(verdict="ok")), None

    monkeypatch.setattr(mapper, "main", fake_main)
    assert cli.main(["map", "--database_path", "db.db", "--image_path", "images",
                     "--citymodel", "m.gml", "--output_path", "out", "--gnss_bias", "auto",
                     "--workflow", "sliding_window", "--mapper_options",
                     "ba_global_frames_ratio=1.2", "--min_gnss_images", "20",
                     "--matcher", "sequential"]) == 0
    assert seen["args"] == ("db.db", "images")
    assert (seen["gnss_bias"], seen["workflow"], seen["min_gnss_images"], seen["matcher"]) == (
        "auto", "sliding_window", 20, "sequential")
    assert seen["mapper_options"] == ["ba_global_frames_ratio=1.2"]
    assert "database" not in seen and "initial_transform" not in seen
