"""refine with model correction on the synthetic street, from a CityGML file whose street
facade is 0.3 m off its true plane, to the corrected file written back: the facade moves back,
the faces the images do not correct keep their coordinates, and only coordinates change."""

from __future__ import annotations

import csv

import numpy as np
import pytest
from lxml import etree

from colmap_citymodel.assign.schedule import assign
from colmap_citymodel.block.reconstruction import tie_points
from colmap_citymodel.citymodel.read import read_city_model
from colmap_citymodel.citymodel.write_citygml import raw_from_store, write_citygml
from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.options import AssignmentOptions, RefineOptions
from colmap_citymodel.output.write import write_refined
from colmap_citymodel.workflow import refine

SHIFT = 0.3


def _street_facade(store, truth) -> int:
    """The wall with the most true tie points on it."""
    point_ids, xyz = tie_points(truth)
    assignment = assign(xyz, point_ids, store, 0.3, AssignmentOptions())
    faces, counts = np.unique(assignment.face_index[assignment.assigned], return_counts=True)
    walls = [(c, f) for f, c in zip(faces.tolist(), counts.tolist())
             if store.faces[f].semantic == "WallSurface"]
    return max(walls)[1]


@pytest.fixture(scope="module")
def run(street_scene, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("correction")
    truth = street_scene.store
    face = _street_facade(truth, street_scene.truth)
    vertices = truth.vertices.copy()
    vertices[truth.face_vertex_ids(face)] += SHIFT * truth.normals[face]
    given_path = tmp / "given.gml"
    write_citygml(given_path, raw_from_store(truth.with_vertices(vertices)),
                  srs_name="EPSG:25832")
    given = read_city_model(given_path)
    options = RefineOptions.preset("correct_model")
    options.precision.covariances = "on"
    result = refine(street_scene.sfm, given, street_scene.gnss(), options, progress=False)
    out = tmp / "refined"
    write_refined(result, out, write_model=True)
    gid = truth.faces.gml_id[face]
    return truth, given, result, out, gid


def _plane(store, gid: str):
    f = list(store.faces.gml_id).index(gid)
    n = store.normals[f]
    return n, float(store.offsets[f] - n @ store.origin), store


def _offset_from_truth(store, truth, gid: str) -> float:
    n, d, _ = _plane(store, gid)
    f = list(truth.faces.gml_id).index(gid)
    return float(n @ (truth.centroids[f] + truth.origin) + d)


def test_the_street_facade_moves_back_to_its_true_plane(run):
    truth, given, result, out, gid = run
    assert result.model_correction is not None and result.handed_back == "refined"
    face = list(given.faces.gml_id).index(gid)
    assert face in result.model_correction.faces
    assert abs(_offset_from_truth(given, truth, gid)) == pytest.approx(SHIFT, abs=1e-6)
    written = read_city_model(out / "corrected_model.gml")
    # the block, adjusted to the given model, leans a little towards the wrong facade (the one
    # with the most tie points); the facade is fitted to the tie points of that block
    assert abs(_offset_from_truth(written, truth, gid)) < SHIFT / 2
    # same faces, same ids, same vertex count
    assert list(written.faces.gml_id) == list(given.faces.gml_id)
    assert len(written.vertices) == len(given.vertices)


def test_only_the_corrected_vertices_change_in_the_file(run):
    truth, given, result, out, gid = run
    parser = etree.XMLParser(huge_tree=True)
    old = list(etree.parse(str(given.source), parser).iter())
    new = list(etree.parse(str(out / "corrected_model.gml"), parser).iter())
    assert len(old) == len(new)
    changed = set()
    for a, b in zip(old, new):
        assert (a.tag, dict(a.attrib), a.tail) == (b.tag, dict(b.attrib), b.tail)
        if a.text != b.text:
            assert a.tag.endswith("posList")
            points = np.array(a.text.split(), float).reshape(-1, 3) - given.origin
            moved = np.any(np.array(b.text.split(), float).reshape(-1, 3) - given.origin
                           != points, axis=1)
            changed |= set(given.provenance.vertex_of(points[moved]).tolist())
    assert changed and changed <= set(result.model_correction.vertex_ids.tolist())


def test_model_changes_and_report(run):
    truth, given, result, out, gid = run
    with open(out / "model_changes.csv") as f:
        rows = list(csv.DictReader(f))
    corrected = [r for r in rows if r["face_id"] == gid]
    assert corrected and all(r["role"] == "corrected" for r in corrected)
    assert all(float(r["shift_m"]) > SHIFT / 2 and r["significant"] == "true"
               and float(r["sigma_m"]) > 0 for r in corrected)
    assert {r["role"] for r in rows} == {"corrected", "kept_plane"}
    assert (out / "model_changes.ply").read_bytes().startswith(b"ply\n")
    report = (out / "report.md").read_text()
    assert "## Model correction" in report and "(model correction)" in report
    assert "corrected_model.gml" in report


def test_cli_write_model_flag_is_parsed(run, tmp_path, monkeypatch):
    captured = {}

    def fake_main(*args, **kwargs):
        captured.update(kwargs)
        raise SystemExit(0)

    monkeypatch.setattr("colmap_citymodel.workflow.main", fake_main)
    with pytest.raises(SystemExit):
        cli_main(["refine", "--input_path", "in", "--citymodel", "m.gml", "--output_path",
                  str(tmp_path / "o"), "--database", "db", "--write_model"])
    assert captured["write_model"] is True


def test_the_corrected_file_loads_in_model_info(run, capsys):
    truth, given, result, out, gid = run
    assert cli_main(["model-info", str(out / "corrected_model.gml"), "--json"]) == 0
    info = capsys.readouterr().out
    assert '"num_faces": %d' % given.num_faces in info


@pytest.mark.slow
def test_the_simulator_builds_a_block_on_the_corrected_file(run, tmp_path, sequence_cache):
    from colmap_citymodel.simulate.sequence import main as simulate

    truth, given, result, out, gid = run
    scenario = tmp_path / "scenario.toml"
    scenario.write_text(
        'name = "on_corrected"\nseed = 14\n\n[scene]\nsource = "%s"\n\n[flight]\n'
        "num_key_frames = 12\nspacing = 1.5\nflight_height = 18.0\npitch_deg = 30.0\n\n"
        "[observations]\npoints_per_m2 = 1.0\n\n[checkpoints]\ncount = 5\n\n[scenario]\n"
        'name = "check"\nmodel = "original"\ngnss = "all"\n' % (out / "corrected_model.gml"))
    workspace = simulate(scenario, tmp_path / "workspace", cache_path=sequence_cache,
                         progress=False)
    assert (workspace / "sparse" / "0").is_dir()
    assert read_city_model(workspace / "models" / "corrected.gml").num_faces == given.num_faces
