"""`model-info` through the CLI runner (cli.main) and as a subprocess (`python -m colmap_citymodel`):
summaries of real files and one clear line with exit code 2 for bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from colmap_citymodel.cli import main as cli_main
from data_paths import CITYGML

REPO = Path(__file__).resolve().parents[1]

UNRESOLVED_XLINK = """<?xml version="1.0" encoding="UTF-8"?>
<CityModel xmlns="http://www.opengis.net/citygml/2.0" xmlns:gml="http://www.opengis.net/gml"
  xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:xlink="http://www.w3.org/1999/xlink">
 <cityObjectMember>
  <bldg:Building gml:id="B1">
   <bldg:boundedBy><bldg:RoofSurface><bldg:lod2MultiSurface><gml:MultiSurface srsName="EPSG:25832">
    <gml:surfaceMember><gml:Polygon gml:id="roof"><gml:exterior><gml:LinearRing>
     <gml:posList srsDimension="3">0 0 10 10 0 10 10 10 10 0 10 10 0 0 10</gml:posList>
    </gml:LinearRing></gml:exterior></gml:Polygon></gml:surfaceMember>
   </gml:MultiSurface></bldg:lod2MultiSurface></bldg:RoofSurface></bldg:boundedBy>
   <bldg:lod2Solid><gml:Solid><gml:exterior><gml:CompositeSurface>
    <gml:surfaceMember xlink:href="#roof"/>
    <gml:surfaceMember xlink:href="#wall_that_is_missing"/>
   </gml:CompositeSurface></gml:exterior></gml:Solid></bldg:lod2Solid>
  </bldg:Building>
 </cityObjectMember>
</CityModel>
"""


def bad_inputs(tmp_path: Path) -> dict[str, tuple[list[str], str]]:
    """name -> (arguments after model-info, fragment the one-line message must contain)."""
    src = (CITYGML / "berlin/3920_5820.gml").read_bytes()
    truncated = tmp_path / "truncated.gml"
    truncated.write_bytes(src[: len(src) // 3])
    foreign = tmp_path / "feed.xml"
    foreign.write_text('<?xml version="1.0"?><rss version="2.0"><channel><title>x</title></channel></rss>')
    xlink = tmp_path / "xlink.gml"
    xlink.write_text(UNRESOLVED_XLINK)
    return {
        "malformed": ([str(truncated)], "malformed XML"),
        "foreign": ([str(foreign)], "not a CityGML file"),
        "missing": ([str(tmp_path / "missing.gml")], "no such file"),
        "no_crs": ([str(CITYGML / "synthetic/no_crs_house_part.gml")], "no CRS in the file; pass --crs EPSG:N"),
        "unresolved_xlink": ([str(xlink)], "wall_that_is_missing"),
        "plateau_geographic": ([str(CITYGML / "plateau/53394517_bldg_6697_op_CityGML2.gml")], "--target_crs"),
    }


def test_model_info_json_berlin_block(capsys):
    assert cli_main(["model-info", str(CITYGML / "berlin/3910_5819.gml"), "--json"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1
    info = json.loads(out[0])
    for key in ("version", "crs", "num_buildings", "num_faces", "num_vertices", "faces_by_class", "bbox", "warnings"):
        assert key in info
    assert info["version"] == "2.0"
    assert info["crs"]["horizontal_epsg"] == 25833
    assert info["num_buildings"] == 35
    assert info["faces_with_holes"] == 1
    assert info["num_faces"] + info["num_dropped_degenerate"] == 1207
    assert sum(info["faces_by_class"].values()) == info["num_faces"]
    (x0, y0, _), (x1, y1, _) = info["bbox"]
    # tile 3910_5819 of the Berlin 1-km grid (EPSG:25833): x in 391xxx, y in 5819xxx
    assert 391_000 <= x0 < x1 <= 392_100 and 5_818_900 <= y0 < y1 <= 5_820_000


def test_model_info_human_summary_and_options(capsys):
    path = CITYGML / "synthetic/no_crs_house_part.gml"
    assert cli_main(["model-info", str(path), "--crs", "EPSG:3946"]) == 0
    out = capsys.readouterr().out
    assert "CityGML 2.0" in out and "EPSG:3946" in out
    assert "buildings   1 (1 building parts)" in out
    assert "faces       7: GroundSurface 1, RoofSurface 2, WallSurface 4" in out
    plateau = CITYGML / "plateau/53394517_bldg_6697_op_CityGML2.gml"
    assert cli_main(["model-info", str(plateau), "--target_crs", "EPSG:6677", "--lod", "1", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["crs"]["horizontal_epsg"] == 6677 and info["lod"] == 1
    assert info["num_faces"] + info["num_dropped_degenerate"] == 134


def test_model_info_directory(capsys):
    assert cli_main(["model-info", str(CITYGML / "tum2twin"), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["num_buildings"] == 7 and len(info["files"]) == 7
    assert info["num_holes"] == 6


def test_bad_input_through_cli_main(tmp_path, capsys):
    for name, (args, fragment) in bad_inputs(tmp_path).items():
        assert cli_main(["model-info", *args, "--json"]) == 2, name
        captured = capsys.readouterr()
        assert captured.out == "", name  # nothing printed as a result
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1, (name, captured.err)
        assert lines[0].startswith("error: ") and fragment in lines[0], (name, lines[0])
        assert "Traceback" not in captured.err


def test_bad_input_as_subprocess(tmp_path):
    cases = bad_inputs(tmp_path)
    for name in ("malformed", "foreign", "missing", "no_crs", "unresolved_xlink"):
        args, fragment = cases[name]
        run = subprocess.run(
            [sys.executable, "-m", "colmap_citymodel", "model-info", *args, "--json"],
            capture_output=True, text=True, cwd=REPO, timeout=120,
        )
        assert run.returncode == 2, (name, run.stderr)
        assert "Traceback" not in run.stderr, name
        errors = [line for line in run.stderr.splitlines() if line.startswith("error: ")]
        assert len(errors) == 1 and fragment in errors[0], (name, run.stderr)
        assert args[0] in errors[0]  # the message names the file
        assert run.stdout == ""


def test_subprocess_success(tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "colmap_citymodel", "model-info",
         str(CITYGML / "nrw/LoD2_32_328_5725_1_NW.gml"), "--json"],
        capture_output=True, text=True, cwd=REPO, timeout=120,
    )
    assert run.returncode == 0, run.stderr
    info = json.loads(run.stdout)
    assert info["num_buildings"] == 2 and info["num_faces"] == 15
    assert info["crs"]["horizontal_epsg"] == 25832 and info["crs"]["vertical_epsg"] == 7837
