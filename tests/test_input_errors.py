"""Bad inputs found by hand: each ends the CLI with exit 2 and one line naming the file and what is
wrong with it (through `colmap_citymodel.cli.main`, as a user runs it).

Real city model files from tests/data (tum2twin CC BY 4.0, PLATEAU CC BY 4.0, 3DBAG CC BY 4.0);
the COLMAP model, GNSS and city model of the refine cases are the synthetic street of
fuzz_inputs.build_workspace.
"""

from __future__ import annotations

import json
import re
import shutil
import struct

import numpy as np
import pytest
from data_paths import CITYGML, CITYJSON, LUND
from fuzz_inputs import build_workspace

from colmap_citymodel.block.colmap_files import check_model
from colmap_citymodel.citymodel.raw_model import coordinate_problem
from colmap_citymodel.citymodel.read import read_city_model
from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.errors import CityGMLError, InputError

TUM = CITYGML / "tum2twin" / "DEBY_LOD2_4959324.gml"
PLATEAU = CITYGML / "plateau" / "53394517_bldg_6697_op_CityGML2.gml"
BAG = CITYJSON / "3dbag_b2.city.json"


def run(argv, capsys) -> tuple[int, str]:
    """Exit status and stderr of the CLI; stderr must be exactly one 'error:' line on exit 2."""
    code = cli_main([str(a) for a in argv])
    err = capsys.readouterr().err
    if code == 2:
        assert len(err.strip().splitlines()) == 1 and err.startswith("error: "), err
    return code, err.strip()


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    return build_workspace(tmp_path_factory.mktemp("ws"))


def refine_argv(ws, out, **overrides):
    args = {"--input_path": ws / "sparse" / "0", "--citymodel": ws / "model.gml",
            "--output_path": out, "--gnss": ws / "gnss.txt", "--gnss_crs": "EPSG:25832"}
    args.update(overrides)
    argv = ["refine", "--no_progress"]
    for key, value in args.items():
        if value is not None:
            argv += [key, value]
    return argv


def copy_model(ws, tmp_path, kind="bin"):
    model = tmp_path / "model"
    shutil.copytree(ws / ("sparse" if kind == "bin" else "text") / "0", model)
    return model


# --- city models ---------------------------------------------------------------------------


def _first_poslist_number(text: str, after: str = "") -> re.Match:
    """The first number of the first posList after `after` (groups: the tag, the number)."""
    return re.compile(r"(<gml:posList[^>]*>\s*)([-\d.]+)").search(text, text.index(after))


@pytest.mark.parametrize("value, why", [("1e308", "beyond 1e+08 m"), ("nan", "not finite"),
                                         ("-inf", "not finite")])
def test_citygml_coordinate_no_crs_can_hold(tmp_path, capsys, value, why):
    text = TUM.read_text(encoding="utf-8")
    m = _first_poslist_number(text)
    bad = tmp_path / TUM.name
    bad.write_text(text[:m.start(2)] + value + text[m.end(2):], encoding="utf-8")
    code, err = run(["model-info", bad], capsys)
    assert code == 2
    assert str(bad) in err and why in err
    # the message names the polygon (its gml:id) whose ring holds the number
    polygon_id = re.findall(r'<gml:Polygon gml:id="([^"]+)"', text[:m.start()])[-1]
    assert polygon_id in err
    with pytest.raises(CityGMLError, match=re.escape(why)):
        read_city_model(bad)


def test_citygml_height_beyond_any_datum(tmp_path, capsys):
    text = TUM.read_text(encoding="utf-8")
    m = re.search(r"(<gml:posList[^>]*>\s*\S+\s+\S+\s+)([-\d.]+)", text)
    bad = tmp_path / TUM.name
    bad.write_text(text[:m.start(2)] + "250000" + text[m.end(2):], encoding="utf-8")
    code, err = run(["model-info", bad], capsys)
    assert code == 2 and str(bad) in err and "height beyond" in err


def test_citygml_geographic_latitude_out_of_range(tmp_path, capsys):
    # PLATEAU writes latitude first (EPSG:6697); 95 is no latitude
    text = PLATEAU.read_text(encoding="utf-8")
    m = _first_poslist_number(text, after="lod2MultiSurface")
    assert 30 < float(m.group(2)) < 40
    bad = tmp_path / PLATEAU.name
    bad.write_text(text[:m.start(2)] + "95.0" + text[m.end(2):], encoding="utf-8")
    code, err = run(["model-info", bad, "--target_crs", "EPSG:6677"], capsys)
    assert code == 2 and str(bad) in err and "not a latitude/longitude" in err


def test_cityjson_vertex_1e308_names_vertex_and_object(tmp_path, capsys):
    import json

    doc = json.loads(BAG.read_text())
    doc["vertices"][5][1] = 10**308  # an integer vertex: 1e308 * scale + translate
    bad = tmp_path / BAG.name
    bad.write_text(json.dumps(doc))
    code, err = run(["model-info", bad], capsys)
    assert code == 2 and str(bad) in err
    assert "vertex 5" in err and "CityObject" in err and "beyond 1e+08 m" in err


def test_cityjson_float_vertex_index(tmp_path, capsys):
    import json

    doc = json.loads(BAG.read_text())
    building = next(o for o in doc["CityObjects"].values() if o.get("geometry"))
    ring = building["geometry"][0]["boundaries"][0][0][0]
    ring[0] = ring[0] + 0.5  # 12.5 used to be read as vertex 12
    bad = tmp_path / BAG.name
    bad.write_text(json.dumps(doc))
    code, err = run(["model-info", bad], capsys)
    assert code == 2 and str(bad) in err and "bad vertex index" in err


def test_coordinate_problem_limits():
    ok = np.array([[691000.0, 5335000.0, 520.0], [-1e8, 1e8, -1e5]])
    assert coordinate_problem(ok) is None
    row, why = coordinate_problem(np.vstack([ok, [[1e308, 0.0, 0.0]]]))
    assert row == 2 and "beyond" in why
    row, why = coordinate_problem(np.array([[0.0, 0.0, 0.0], [1.0, np.nan, 0.0]]))
    assert row == 1 and "not finite" in why
    assert coordinate_problem(np.array([[48.1, 11.5, 500.0]]), geographic=True) is None
    assert coordinate_problem(np.array([[11.5, 48.1, 500.0]]), geographic=True,
                              lat_first=False) is None
    assert coordinate_problem(np.array([[91.0, 11.5, 0.0]]), geographic=True) is not None
    assert coordinate_problem(np.array([[48.1, 400.0, 0.0]]), geographic=True) is not None


# --- COLMAP models -------------------------------------------------------------------------


def test_truncated_images_bin(workspace, tmp_path, capsys):
    model = copy_model(workspace, tmp_path)
    images = model / "images.bin"
    data = images.read_bytes()
    images.write_bytes(data[:len(data) // 2])
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--input_path": model}), capsys)
    assert code == 2 and str(images) in err and "truncated" in err
    assert "unordered_map" not in err


def test_truncated_image_name_does_not_hang(workspace, tmp_path, capsys):
    # COLMAP's reader waits for the name's terminating 0 byte forever when the file ends in it
    model = copy_model(workspace, tmp_path)
    images = model / "images.bin"
    data = images.read_bytes()
    name_start = 8 + struct.calcsize("<I7dI")
    name_end = data.index(b"\0", name_start)
    # one image, and the file ends just before its name's 0 byte
    images.write_bytes(struct.pack("<Q", 1) + data[8:name_end])
    code, err = run(["evaluate", "--input_path", model, "--checkpoints",
                     workspace / "checkpoints.txt", "--observations",
                     workspace / "checkpoint_obs.txt"], capsys)
    assert code == 2 and str(images) in err and "name of image 1" in err and "truncated" in err


def test_text_model_saved_as_binary(workspace, tmp_path, capsys):
    model = copy_model(workspace, tmp_path)
    shutil.copyfile(workspace / "text" / "0" / "cameras.txt", model / "cameras.bin")
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--input_path": model}), capsys)
    assert code == 2 and str(model / "cameras.bin") in err and "a text file" in err


def test_track_names_missing_image(workspace, tmp_path, capsys):
    model = copy_model(workspace, tmp_path, "txt")
    points = model / "points3D.txt"
    lines = points.read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    parts = lines[k].split()
    parts[8] = "999"  # the first track element's image id
    lines[k] = " ".join(parts)
    points.write_text("\n".join(lines) + "\n")
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--input_path": model}), capsys)
    assert code == 2 and str(points) in err
    assert f"point {parts[0]}: its track names image 999, which is not in images.txt" in err


def test_truncated_text_line(workspace, tmp_path, capsys):
    model = copy_model(workspace, tmp_path, "txt")
    images = model / "images.txt"
    text = images.read_text()
    images.write_text(text[:len(text) // 3])
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--input_path": model}), capsys)
    assert code == 2 and str(images) in err and "truncated" in err
    assert re.search(r"line \d+", err)


def test_frames_missing_while_rigs_exist(workspace, tmp_path, capsys):
    model = copy_model(workspace, tmp_path)
    (model / "frames.bin").unlink()
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--input_path": model}), capsys)
    assert code == 2 and str(model / "images.bin") in err and "no frame holds this image" in err


@pytest.mark.parametrize("case, expected", [
    ("missing", "COLMAP model directory does not exist"),
    ("empty", "not a COLMAP model directory (no cameras.bin or cameras.txt)"),
    ("incomplete", "incomplete COLMAP model: points3D.bin missing"),
])
def test_missing_empty_or_incomplete_model_directory(workspace, tmp_path, capsys, case, expected):
    model = tmp_path / "model"
    if case == "empty":
        model.mkdir()
    elif case == "incomplete":
        model = copy_model(workspace, tmp_path)
        (model / "points3D.bin").unlink()
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--input_path": model}), capsys)
    assert code == 2 and str(model) in err and expected in err


def test_undamaged_models_pass_the_check(workspace):
    assert check_model(workspace / "sparse" / "0") == "bin"
    assert check_model(workspace / "text" / "0") == "txt"


def test_check_model_names_duplicate_point(workspace, tmp_path):
    model = copy_model(workspace, tmp_path, "txt")
    points = model / "points3D.txt"
    lines = [line for line in points.read_text().splitlines() if not line.startswith("#")]
    points.write_text("\n".join(lines + [lines[0]]) + "\n")
    with pytest.raises(InputError, match=f"point {lines[0].split()[0]}: point id given twice"):
        check_model(model)


# --- GNSS, output directory ----------------------------------------------------------------


def test_gnss_names_matching_no_image(workspace, tmp_path, capsys):
    gnss = tmp_path / "gnss.txt"
    gnss.write_text("".join(f"other_{line}" for line in
                            (workspace / "gnss.txt").read_text().splitlines(True)
                            if not line.startswith("#")))
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--gnss": gnss}), capsys)
    assert code == 2 and str(gnss) in err
    assert "none of the" in err and "match a registered image" in err


@pytest.mark.parametrize("crs, expected", [
    ("EPSG:4979", "latitude"),  # easting/northing read as latitude/longitude
    ("EPSG:2056", "no position lies in the area"),  # Swiss LV95: these numbers lie off its area
])
def test_wrong_gnss_crs(workspace, tmp_path, capsys, crs, expected):
    gnss = workspace / "gnss.txt"
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--gnss_crs": crs}), capsys)
    assert code == 2 and str(gnss) in err and expected in err


def test_gnss_position_beyond_any_crs(workspace, tmp_path, capsys):
    gnss = tmp_path / "gnss.txt"
    lines = (workspace / "gnss.txt").read_text().splitlines()
    parts = lines[3].split()
    parts[1] = "1e308"
    lines[3] = " ".join(parts)
    gnss.write_text("\n".join(lines) + "\n")
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--gnss": gnss}), capsys)
    assert code == 2 and str(gnss) in err and "line 4" in err and "beyond" in err


def test_garbage_gnss_file(workspace, tmp_path, capsys):
    gnss = tmp_path / "gnss.txt"
    gnss.write_bytes(bytes(range(256)) * 4)
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--gnss": gnss}), capsys)
    assert code == 2 and str(gnss) in err


def test_existing_output_directory(workspace, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "keep.txt").write_text("not ours\n")
    code, err = run(refine_argv(workspace, out), capsys)
    assert code == 2 and str(out) in err and "output path exists" in err
    assert (out / "keep.txt").read_text() == "not ours\n"


# --- options and transform files -----------------------------------------------------------


@pytest.mark.parametrize("line, expected", [
    ("[adjustment]\nsigma_dtp = nan\n", "adjustment.sigma_dtp must be a finite number"),
    ("[adjustment]\nsigma_gnss = [3.0, 0.0, 5.0]\n", "adjustment.sigma_gnss must be > 0"),
    ("[adjustment]\nsigma_gnss = 3.0\n", "adjustment.sigma_gnss must be a list"),
    ("[workflow]\nmax_iterations = 99999999999999999999\n", "workflow.max_iterations must be"),
    ("[precision]\nalpha = 1.5\n", "precision.alpha must lie between 0 and 1"),
    ("[assignment]\nmin_points_per_plane = true\n", "must be int"),
])
def test_options_numbers_no_setting_can_take(workspace, tmp_path, capsys, line, expected):
    options = tmp_path / "options.toml"
    options.write_text(line)
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--options": options}), capsys)
    assert code == 2 and str(options) in err and expected in err


@pytest.mark.parametrize("content, expected", [
    ('{"matrix": [[1, 0, 0, 1], [0, 1, -1e308, 2], [0, 0, 1, 3], [0, 0, 0, 1]]}',
     "beyond any scale x rotation"),
    ("1 0 0 1e300\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "translation"),
    ('{"scale": 1e999, "rotation": [1, 0, 0, 0], "translation": [0, 0, 0]}', "'scale'"),
])
def test_transform_beyond_any_similarity(workspace, tmp_path, capsys, content, expected):
    transform = tmp_path / "transform.txt"
    transform.write_text(content)
    code, err = run(refine_argv(workspace, tmp_path / "out", **{
        "--initial_transform": transform, "--gnss": None, "--gnss_crs": None}), capsys)
    assert code == 2 and str(transform) in err and expected in err


_ONE_POLYGON = """<?xml version="1.0" encoding="UTF-8"?>
<CityModel xmlns="http://www.opengis.net/citygml/2.0"
 xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:gml="http://www.opengis.net/gml">
<cityObjectMember><bldg:Building gml:id="b1"><bldg:boundedBy><bldg:WallSurface>
<bldg:lod2MultiSurface><gml:MultiSurface srsName="EPSG:25832"><gml:surfaceMember>
<gml:Polygon gml:id="p1"><gml:exterior><gml:LinearRing>{ring}</gml:LinearRing></gml:exterior>
</gml:Polygon></gml:surfaceMember></gml:MultiSurface></bldg:lod2MultiSurface>
</bldg:WallSurface></bldg:boundedBy></bldg:Building></cityObjectMember></CityModel>
"""


@pytest.mark.parametrize("ring, expected", [
    ('<gml:coordinates cs="">691000,5335000,0 691010,5335000,0 691010,5335000,9</gml:coordinates>',
     "empty or repeated separator"),
    ("<gml:coordinates>691000,5335000,0 691010,5335000 691010,5335000,9,3</gml:coordinates>",
     "tuples of [2, 3, 4] values"),
    ("<gml:pos>691000 5335000 0</gml:pos><gml:pos>691010 5335000</gml:pos>"
     "<gml:pos>691010 5335000 9</gml:pos>", "a gml:pos with 2 values (srsDimension 3)"),
])
def test_citygml_coordinates_that_do_not_line_up(tmp_path, capsys, ring, expected):
    bad = tmp_path / "one.gml"
    bad.write_text(_ONE_POLYGON.format(ring=ring))
    code, err = run(["model-info", bad], capsys)
    assert code == 2 and str(bad) in err and "polygon p1" in err and expected in err


def test_exif_of_a_huge_image_is_read(workspace, tmp_path, capsys):
    """The frame header of a 65000 x 65000 pixel image (a 4 GP aerial camera, or damage) made
    Pillow refuse to open it before its EXIF was read."""
    import pyproj
    from fuzz_inputs import _box_citygml, jpeg_with_size

    from colmap_citymodel.block.gnss import read_gnss_exif
    from colmap_citymodel.citymodel.crs import user_crs

    images = tmp_path / "images"
    images.mkdir()
    photos = sorted(LUND.glob("*.jpg"))[:3]
    for p in photos:
        shutil.copyfile(p, images / p.name)
    (images / photos[0].name).write_bytes(jpeg_with_size(photos[0].read_bytes(), 65000, 65000))
    assert len(read_gnss_exif(images, user_crs("EPSG:3006"))) == 3
    # through refine: the photos' names are not those of the reconstruction's images
    to_sweref = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:3006", always_xy=True)
    boxes = tmp_path / "boxes.gml"
    boxes.write_text(_box_citygml(to_sweref.transform(13.1935, 55.6975), "EPSG:3006"))
    code, err = run(refine_argv(workspace, tmp_path / "out", **{
        "--citymodel": boxes, "--gnss": None, "--gnss_crs": None, "--exif": images}), capsys)
    assert code == 2 and str(images) in err and "match a registered image" in err


@pytest.fixture(scope="module")
def long_workspace(tmp_path_factory):
    """16 stations: enough baseline for refine to get past the georegistration."""
    return build_workspace(tmp_path_factory.mktemp("ws16"), num_stations=16)


def test_gnss_with_gross_outliers(long_workspace, tmp_path, capsys):
    """Two positions 95 km and 5000 km off: the georegistration rejects them, and so does the
    adjustment (with them, it eliminated every tie point). Refine runs to its verdict."""
    lines = (long_workspace / "gnss.txt").read_text().splitlines()
    for k, northing in ((8, "1e8"), (38, "53090")):
        parts = lines[k].split()
        parts[2] = northing
        lines[k] = " ".join(parts)
    gnss = tmp_path / "gnss.txt"
    gnss.write_text("\n".join(lines) + "\n")
    code, err = run(refine_argv(long_workspace, tmp_path / "out", **{"--gnss": gnss}), capsys)
    assert code in (0, 3), err
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["quality"]["verdict"] in ("ok", "weak", "failed")


def test_2d_point_far_outside_the_image(workspace, tmp_path, capsys):
    """A finite but absurd keypoint made the adjustment's cost infinite (and refine exit 0)."""
    model = copy_model(workspace, tmp_path)
    images = model / "images.bin"
    data = bytearray(images.read_bytes())
    first_x = data.index(b"\0", 8 + struct.calcsize("<I7dI")) + 1 + 8
    data[first_x:first_x + 8] = struct.pack("<d", -7e41)
    images.write_bytes(bytes(data))
    code, err = run(refine_argv(workspace, tmp_path / "out", **{"--input_path": model}), capsys)
    assert code == 2 and str(images) in err and "far outside the 1280 px image" in err


def test_a_binary_model_of_35_images_is_binary(tmp_path):
    """A binary file whose record count is 35 starts with the byte of "#": it is read as the
    binary model it is, not refused as a text file."""
    import pycolmap

    from colmap_citymodel.block.colmap_files import check_model

    rec = pycolmap.Reconstruction()
    for camera_id in range(1, 36):
        rec.add_camera(pycolmap.Camera(camera_id=camera_id, model="SIMPLE_PINHOLE", width=640,
                                       height=480, params=[500.0, 320.0, 240.0]))
    rec.write(tmp_path)
    assert (tmp_path / "cameras.bin").read_bytes()[:1] == b"#"
    assert check_model(tmp_path) == "bin"
