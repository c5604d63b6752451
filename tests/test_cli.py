"""`colmap-citymodel refine` through its CLI: files in, files out, clear errors on bad input."""

import json
import subprocess
import sys

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.citymodel.write_citygml import raw_from_store, write_citygml
from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """The synthetic street written as a user would have it: sparse/0, gnss.txt, model.gml."""
    root = tmp_path_factory.mktemp("ws")
    scene = make_street_scene(StreetSceneOptions(seed=11), crs=user_crs("EPSG:25832"))
    (root / "sparse" / "0").mkdir(parents=True)
    scene.sfm.write_binary(str(root / "sparse" / "0"))
    write_citygml(root / "model.gml", raw_from_store(scene.store))
    lines = ["# image_name X Y Z sX sY sZ"] + [
        f"{n} {x:.4f} {y:.4f} {z:.4f} 3 3 5"
        for n, (x, y, z) in zip(scene.gnss_names, scene.gnss_positions_crs)]
    (root / "gnss.txt").write_text("\n".join(lines) + "\n")
    return root, scene


def run_cli(args, capsys):
    code = cli_main(args)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def refine_args(root, out, **overrides):
    args = {"--input_path": root / "sparse" / "0", "--citymodel": root / "model.gml",
            "--output_path": out, "--gnss": root / "gnss.txt", "--gnss_crs": "EPSG:25832"}
    args.update(overrides)
    flat = ["refine", "--no_progress"]
    for key, value in args.items():
        if value is not None:
            flat += [key, str(value)]
    return flat


def test_refine_cli_end_to_end(workspace, tmp_path, capsys):
    root, scene = workspace
    out = tmp_path / "refined"
    before = sorted(p.name for p in root.rglob("*"))
    code, stdout, _ = run_cli(refine_args(root, out), capsys)
    assert code == 0
    assert str(out) in stdout
    assert sorted(p.name for p in root.rglob("*")) == before  # inputs untouched
    rec = pycolmap.Reconstruction(str(out))
    truth = {im.name: im.projection_center() + scene.store.origin
             for im in scene.truth.images.values()}
    errors = [np.linalg.norm(im.projection_center() - truth[im.name]) for im in rec.images.values()]
    assert np.sqrt(np.mean(np.square(errors))) < 0.10
    geo = json.loads((out / "georeference.json").read_text())
    assert geo["crs"]["horizontal_epsg"] == 25832
    for name in ("report.json", "report.md", "assignments.ply", "model_mesh.ply"):
        assert (out / name).is_file()


@pytest.mark.parametrize("case, expected", [
    ("missing_model", "COLMAP model directory does not exist"),
    ("not_a_model", "not a COLMAP model directory"),
    ("missing_citymodel", "no such file or directory"),
    ("unknown_images", "match a registered image"),
    ("too_few_gnss", "at least 3"),
    ("no_gnss", "no GNSS positions and no initial transform"),
    ("gnss_without_crs", "--gnss needs --gnss_crs"),
    ("far_model", "does not overlap"),
])
def test_refine_cli_bad_input(workspace, tmp_path, capsys, case, expected):
    root, scene = workspace
    out = tmp_path / "out"
    overrides = {}
    if case == "missing_model":
        overrides["--input_path"] = tmp_path / "nope"
    elif case == "not_a_model":
        (tmp_path / "empty").mkdir()
        overrides["--input_path"] = tmp_path / "empty"
    elif case == "missing_citymodel":
        overrides["--citymodel"] = tmp_path / "missing.gml"
    elif case == "unknown_images":
        bad = tmp_path / "gnss.txt"
        # Priors of images the reconstruction lacks are normal; none that match is an error.
        bad.write_text("".join(f"ghost_{k}.jpg 691000 5335000 500\n" for k in range(5)))
        overrides["--gnss"] = bad
    elif case == "too_few_gnss":
        few = tmp_path / "gnss.txt"
        few.write_text("\n".join((root / "gnss.txt").read_text().splitlines()[:3]) + "\n")
        overrides["--gnss"] = few
    elif case == "no_gnss":
        overrides["--gnss"] = None
        overrides["--gnss_crs"] = None
    elif case == "gnss_without_crs":
        overrides["--gnss_crs"] = None
    elif case == "far_model":
        far = make_street_scene(StreetSceneOptions(seed=11), crs_origin=(695000.0, 5335000.0, 500),
                                crs=user_crs("EPSG:25832"))
        write_citygml(tmp_path / "far.gml", raw_from_store(far.store))
        overrides["--citymodel"] = tmp_path / "far.gml"
    code, stdout, stderr = run_cli(refine_args(root, out, **overrides), capsys)
    assert code == 2
    assert expected in stderr
    assert stderr.startswith("error: ") and "Traceback" not in stderr
    assert len(stderr.strip().splitlines()) == 1
    assert not out.exists()  # nothing written


def test_refine_cli_refuses_an_existing_output(workspace, tmp_path, capsys):
    root, _ = workspace
    out = tmp_path / "taken"
    out.mkdir()
    (out / "mine.txt").write_text("keep")
    code, _, stderr = run_cli(refine_args(root, out), capsys)
    assert code == 2 and "not an empty directory" in stderr
    assert (out / "mine.txt").read_text() == "keep"


def test_refine_cli_subprocess_reports_errors_without_traceback(tmp_path):
    result = subprocess.run(
        [sys.executable, "-m", "colmap_citymodel", "refine", "--input_path", str(tmp_path / "x"),
         "--citymodel", str(tmp_path / "y.gml"), "--output_path", str(tmp_path / "o")],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "does not exist" in result.stderr


@pytest.mark.parametrize("value, expected", [("auto", "auto"), ("AUTO", "auto"),
                                             ("-47.5", -47.5), ("12", 12.0)])
def test_gnss_height_offset_takes_metres_or_auto(value, expected):
    from colmap_citymodel.cli import _offset_value

    assert _offset_value(value) == expected


@pytest.mark.parametrize("value", ["abc", "nan", "inf"])
def test_gnss_height_offset_rejects_anything_else(tmp_path, capsys, value):
    with pytest.raises(SystemExit) as exit_info:  # argparse's usage error
        cli_main(["refine", "--input_path", str(tmp_path), "--citymodel", str(tmp_path),
                  "--output_path", str(tmp_path / "out"), "--gnss_height_offset", value])
    assert exit_info.value.code == 2 and "metres or auto" in capsys.readouterr().err
