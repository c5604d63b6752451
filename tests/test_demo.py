"""End to end, as README's first command runs it: simulate a flight, map it with COLMAP's
incremental mapper, GNSS-only baseline vs refine, check points against the known truth."""

import json

import pycolmap
import pytest

from colmap_citymodel import demo
from colmap_citymodel.errors import InputError


@pytest.mark.slow
@pytest.mark.ci
def test_demo_end_to_end(tmp_path):
    out = tmp_path / "demo"
    rms = demo.main(out, progress=False)
    # GNSS with a bias of metres leaves the block metres off; the model brings it to decimetres.
    assert rms["gnss_only"] > 1.0
    assert rms["refined"] < 0.3
    assert rms["refined"] < rms["gnss_only"] / 5
    refined = out / "refined"
    georeference = json.loads((refined / "georeference.json").read_text())
    assert georeference["crs"]["horizontal_epsg"] == 25832
    model = pycolmap.Reconstruction(str(refined))
    assert model.num_reg_images() >= 55  # of 60 simulated images
    for name in ("report.md", "report.json", "assignments.ply", "model_mesh.ply"):
        assert (refined / name).stat().st_size > 0
    # The input workspace is left as simulate wrote it: refine wrote only to refined/.
    assert not (out / "workspace" / "sparse" / "0" / "georeference.json").exists()
    summary = json.loads((out / "summary.json").read_text())
    assert summary["refined"]["rms_3d"] == pytest.approx(rms["refined"])
    # Check marks from the simulator's gcp_list file: the ASPRS figures and the block test,
    # which the refined block passes with its sigmas and GNSS alone fails.
    assert summary["refined"]["asprs"]["num_checkpoints"] == summary["refined"]["num_checkpoints"]
    assert summary["refined"]["test"]["passed"] and not summary["gnss_only"]["test"]["passed"]
    report = json.loads((refined / "report.json").read_text())
    assert report["checkpoints"]["rmse_3d_m"] == pytest.approx(rms["refined"], abs=1e-6)


def test_demo_refuses_a_foreign_directory(tmp_path):
    (tmp_path / "mine.txt").write_text("user data")
    with pytest.raises(InputError, match="not a previous demo output"):
        demo.main(tmp_path, progress=False)
    assert (tmp_path / "mine.txt").read_text() == "user data"
