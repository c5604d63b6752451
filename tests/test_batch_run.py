"""`colmap-citymodel batch` end to end on tiny synthetic workspaces: a broken workspace fails
alone, a rerun skips the finished ones, a Dask LocalCluster gives the outputs of the process
pool, and Ctrl-C leaves no half-written output."""

from __future__ import annotations

import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.batch.run import main as batch_main
from colmap_citymodel.citymodel.crs import user_crs
from colmap_citymodel.citymodel.write_citygml import raw_from_store, write_citygml
from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.simulate.synthetic import StreetSceneOptions, make_street_scene

#: Two streets 1 km apart, each its own tile; the coarse search is off and so are the
#: covariances, to keep each refine to a few seconds.
STREETS = {"street_a": (691000.0, 11), "street_b": (692000.0, 12)}
FAST_OPTIONS = "[workflow]\ncoarse_search_sigmas = 0\n"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    tiles, flights = root / "tiles", root / "flights"
    tiles.mkdir()
    for k, (name, (x0, seed)) in enumerate(STREETS.items()):
        scene = make_street_scene(StreetSceneOptions(seed=seed, num_stations=12,
                                                     point_spacing=2.0),
                                  crs_origin=(x0, 5335000.0, 500.0), crs=user_crs("EPSG:25832"))
        ws = flights / name
        (ws / "sparse" / "0").mkdir(parents=True)
        scene.sfm.write_binary(str(ws / "sparse" / "0"))
        write_citygml(tiles / f"tile_{k}.gml", raw_from_store(scene.store))
        (ws / "gnss.txt").write_text("".join(
            f"{n} {x:.4f} {y:.4f} {z:.4f} 3 3 5\n"
            for n, (x, y, z) in zip(scene.gnss_names, scene.gnss_positions_crs)))
    # a workspace whose model is broken, with good GNSS near tile_0
    broken = flights / "broken"
    (broken / "sparse" / "0").mkdir(parents=True)
    (broken / "sparse" / "0" / "cameras.bin").write_bytes(b"not a COLMAP model")
    (broken / "gnss.txt").write_text((flights / "street_a" / "gnss.txt").read_text())
    options = root / "fast.toml"
    options.write_text(FAST_OPTIONS)
    return root


def run_batch(inputs, out, **kwargs):
    return batch_main(inputs / "flights", inputs / "tiles", out, gnss_crs="EPSG:25832",
                      precision="off", options_file=inputs / "fast.toml", progress=False,
                      **kwargs)


@pytest.fixture(scope="module")
def pool_run(inputs):
    out = inputs / "out_pool"
    return out, {r["workspace"]: r for r in run_batch(inputs, out, workers=2)}


def summary_csv(out):
    with open(out / "summary.csv") as f:
        return {r["workspace"]: r for r in csv.DictReader(f)}


def test_broken_workspace_fails_alone(pool_run):
    out, rows = pool_run
    assert rows["broken"]["status"] == "error"
    assert "incomplete COLMAP model: images.bin and points3D.bin missing" in rows["broken"]["error"]
    assert not (out / "broken").exists()
    assert "incomplete COLMAP model" in (out / "broken.log").read_text()
    for name in STREETS:
        row = rows[name]
        assert row["status"] == "done" and row["verdict"] in ("ok", "weak")
        assert row["images"] == 36 and row["tiles"] == 1 and not row.get("error")
        assert row["near_model"] > row["near_model_gnss_only"]
        assert (out / name / "report.json").is_file() and (out / f"{name}.log").is_file()
    # the summary files say the same
    table = summary_csv(out)
    assert table["broken"]["status"] == "error" and table["street_a"]["verdict"] \
        == rows["street_a"]["verdict"]
    doc = json.loads((out / "summary.json").read_text())
    assert [r["workspace"] for r in doc["workspaces"]] == ["broken", "street_a", "street_b"]
    page = (out / "summary.html").read_text()
    assert 'href="street_a/report.html"' in page and "broken.log" in page


def test_each_workspace_reads_only_its_tile(pool_run):
    out, rows = pool_run
    assert rows["street_a"]["tile_files"] == ["tile_0.gml"]
    assert rows["street_b"]["tile_files"] == ["tile_1.gml"]
    report = json.loads((out / "street_b" / "report.json").read_text())
    assert [Path(p).name for p in report["inputs"]["citymodel"]] == ["tile_1.gml"]


def test_rerun_skips_finished_workspaces(inputs, pool_run, capsys):
    out, rows = pool_run
    stamps = {n: (out / n / "report.json").stat().st_mtime_ns for n in STREETS}
    code = cli_main(["batch", "--workspaces", str(inputs / "flights"), "--citymodel",
                     str(inputs / "tiles"), "--output_path", str(out), "--gnss_crs",
                     "EPSG:25832", "--precision", "off", "--options", str(inputs / "fast.toml"),
                     "--no_progress"])
    printed = capsys.readouterr().out
    assert code == 1  # the broken workspace failed again
    assert "1 to refine" in printed
    assert [ln for ln in printed.splitlines() if ln.startswith("street_a: ")
            and "(done before)" in ln]
    again = summary_csv(out)
    assert again["street_a"]["status"] == again["street_b"]["status"] == "skipped"
    assert again["street_a"]["seconds"] == f"{rows['street_a']['seconds']}"  # the earlier row
    assert {n: (out / n / "report.json").stat().st_mtime_ns for n in STREETS} == stamps


def test_force_refines_again_in_place(inputs, pool_run, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(pool_run[0] / "street_b", out / "street_b")
    stamp = (out / "street_b" / "report.json").stat().st_mtime_ns
    listing = tmp_path / "list.txt"
    listing.write_text(f"{inputs / 'flights' / 'street_b'}\n")
    (row,) = batch_main(listing, inputs / "tiles", out, force=True, gnss_crs="EPSG:25832",
                        precision="off", options_file=inputs / "fast.toml", progress=False,
                        workers=1)
    assert row["status"] == "done" and row["verdict"] == pool_run[1]["street_b"]["verdict"]
    assert (out / "street_b" / "report.json").stat().st_mtime_ns != stamp
    assert [p.name for p in out.iterdir() if p.name.startswith(".street_b")] == []


def test_dask_local_cluster_gives_the_outputs_of_the_pool(inputs, pool_run):
    out_pool, rows_pool = pool_run
    out = inputs / "out_dask"
    rows = {r["workspace"]: r for r in run_batch(inputs, out, workers=2, scheduler="local")}
    assert rows["broken"]["status"] == "error" and rows["broken"]["error"] \
        == rows_pool["broken"]["error"]
    for name in STREETS:
        for key in ("status", "images", "verdict", "s0", "s0_gnss_only", "near_model",
                    "shift_m", "tile_files"):
            assert rows[name][key] == rows_pool[name][key], (name, key)
        a = pycolmap.Reconstruction(str(out_pool / name))
        b = pycolmap.Reconstruction(str(out / name))
        centres = [(a.image(i).projection_center(), b.image(i).projection_center())
                   for i in a.images]
        assert np.max([np.abs(p - q).max() for p, q in centres]) < 1e-6


def half_written(out: Path) -> bool:
    """Whether a refine's temporary output directory holds files."""
    for p in out.glob(".street_*"):
        try:
            if any(p.iterdir()):
                return True
        except OSError:  # renamed or removed meanwhile
            pass
    return False


def test_ctrl_c_leaves_no_half_written_output(inputs, tmp_path):
    """SIGINT to the process group (what Ctrl-C in a terminal sends) while a refine is writing
    its output: no workspace directory without its report, no temporary directory left, a
    summary that parses."""
    out = tmp_path / "out"
    command = [sys.executable, "-m", "colmap_citymodel", "batch", "--workspaces",
               str(inputs / "flights" / "street_a"), str(inputs / "flights" / "street_b"),
               "--citymodel", str(inputs / "tiles"), "--output_path", str(out),
               "--gnss_crs", "EPSG:25832", "--precision", "off", "--options",
               str(inputs / "fast.toml"), "--workers", "2", "--no_progress"]
    # its own process group, with Ctrl-C handled even where this test runs with it ignored
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                               text=True, start_new_session=True,
                               preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 240
    try:
        while time.monotonic() < deadline and process.poll() is None:
            if half_written(out):  # a refine is writing its output: interrupt now
                break
            time.sleep(0.02)
        assert process.poll() is None, "the batch ended before any output was written"
        os.killpg(process.pid, signal.SIGINT)
        _, stderr = process.communicate(timeout=120)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
    assert process.returncode == 130, stderr
    assert "interrupted" in stderr
    for name in STREETS:
        assert not (out / name).exists() or (out / name / "report.json").is_file()
    assert [p.name for p in out.glob(".street*")] == []
    rows = {r["workspace"]: r for r in json.loads((out / "summary.json").read_text())["workspaces"]}
    assert sorted(rows) == sorted(STREETS)
    for name, row in rows.items():
        assert (row["status"] == "done") == (out / name).exists()


def test_output_completed_as_ctrl_c_came_counts_as_done(inputs, tmp_path, monkeypatch):
    """A refine that renamed its finished output into place just before the interrupt, whose
    result never reached the batch: the summary says done, not "not run"."""
    import colmap_citymodel.batch.engine as engine

    def interrupted_after_writing(fn, tasks, workers, threads=None):
        first = Path(tasks[0].output)
        first.mkdir(parents=True)
        (first / "report.json").write_text(json.dumps(
            {"num_images": 7, "quality": {"verdict": "weak", "reasons": []}}))
        raise KeyboardInterrupt
        yield  # a generator, as the engines are

    monkeypatch.setattr(engine, "run_local", interrupted_after_writing)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        run_batch(inputs, out, workers=1)
    rows = {r["workspace"]: r for r in json.loads((out / "summary.json").read_text())["workspaces"]}
    done = [name for name, row in rows.items() if row["status"] == "done"]
    assert len(done) == 1 and rows[done[0]]["images"] == 7 and rows[done[0]]["verdict"] == "weak"
    assert all(row["status"] == "not run" for name, row in rows.items() if name not in done)
