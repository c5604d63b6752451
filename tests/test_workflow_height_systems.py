"""GNSS heights in other height systems against a German LoD2 model (EPSG:25832 + DHHN2016), on
the demo workspace (`colmap_citymodel/simulate/demo.toml`, simulated by COLMAP) through refine's CLI entry.

The demo's GNSS (model heights, 3/3/5 m noise) is rewritten as EPSG:4979 latitude, longitude and
ellipsoidal height h = H + N_EGM96 + DELTA_GEOID, DELTA_GEOID standing in for the difference
between the national quasigeoid (GCG2016, a grid this machine does not have) and EGM96; and once
more with 120 m added (heights above take-off). Refine must convert the first with the EGM96
fallback and, with `--gnss_height_offset auto`, find both offsets within 0.2 m and end with check
points within 5 % of the run with correct heights.

    python tests/test_workflow_height_systems.py [WORKDIR]   prints the figures
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import numpy as np
import pycolmap
import pyproj
import pytest

from colmap_citymodel.citymodel import crs as crs_module

DEMO = Path(__file__).resolve().parents[1] / "colmap_citymodel" / "simulate" / "demo.toml"
#: The stand-in for "national quasigeoid minus EGM96" at the demo site (m).
DELTA_GEOID = 0.8
#: Heights above take-off instead of ellipsoidal heights (m).
ABOVE_TAKE_OFF = 120.0


def build_workspace(workdir: Path, cache: Path | None = None) -> Path:
    from colmap_citymodel.simulate import sequence

    workspace = workdir / "workspace"
    if not (workspace / "database.db").exists():
        sequence.main(DEMO, workspace, cache_path=cache, progress=False)
    # The demo model names EPSG:25832 alone; a German LoD2 tile names its height system too.
    model = workspace / "given_model.gml"
    dhhn = workspace / "model_dhhn2016.gml"
    dhhn.write_text(model.read_text().replace('srsName="EPSG:25832"',
                                              'srsName="EPSG:25832+7837"'))
    rows = [line.split() for line in (workspace / "gnss_all.txt").read_text().splitlines()
            if line.strip() and not line.startswith("#")]
    names = [r[0] for r in rows]
    xyz = np.array([[float(v) for v in r[1:4]] for r in rows])
    sigmas = [" ".join(r[4:7]) for r in rows]
    to_geographic = pyproj.Transformer.from_crs("EPSG:25832", "EPSG:4326", always_xy=True)
    lon, lat = to_geographic.transform(xyz[:, 0], xyz[:, 1])
    undulation = crs_module.geoid_undulation(lon, lat, crs_module.fallback_geoid())

    def write(name: str, lines) -> None:
        (workspace / name).write_text("\n".join(lines) + "\n")

    write("gnss_dhhn2016.txt", (f"{n} {x:.4f} {y:.4f} {z:.4f} {s}"
                                for n, (x, y, z), s in zip(names, xyz, sigmas)))
    for name, extra in (("gnss_ellipsoidal.txt", 0.0), ("gnss_take_off.txt", ABOVE_TAKE_OFF)):
        h = xyz[:, 2] + undulation + DELTA_GEOID + extra
        write(name, (f"{n} {b:.9f} {a:.9f} {z:.4f} {s}"
                     for n, a, b, z, s in zip(names, lon, lat, h, sigmas)))
    return workspace


def gnss_mean_height_error(workspace: Path) -> float:
    """The simulated GNSS's own mean height error (GNSS minus true camera centre), m."""
    truth = pycolmap.Reconstruction(str(workspace / "truth"))
    origin = np.loadtxt(workspace / "truth" / "origin.txt", comments="#")
    centres = {im.name: im.projection_center() + origin for im in truth.images.values()}
    errors = []
    for line in (workspace / "gnss_all.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            parts = line.split()
            if parts[0] in centres:
                errors.append(float(parts[3]) - centres[parts[0]][2])
    return float(np.mean(errors))


def run(workspace: Path, out: Path, gnss: str, gnss_crs: str, offset=None):
    """refine through its CLI entry; returns (check point RMS 3D, the result)."""
    from colmap_citymodel.workflow import main

    result = main(workspace / "sparse" / "0", workspace / "model_dhhn2016.gml", out,
                  gnss=workspace / gnss, gnss_crs=gnss_crs, gnss_height_offset=offset,
                  progress=False, precision="off",
                  checkpoints=workspace / "checkpoints.txt",
                  checkpoint_observations=workspace / "checkpoint_observations.txt")
    errors = result.checkpoints.errors
    return float(np.sqrt(np.mean(np.sum(errors ** 2, axis=1)))), result


RUNS = {  # name: (GNSS file, its CRS, --gnss_height_offset)
    "dhhn2016": ("gnss_dhhn2016.txt", "EPSG:25832+7837", None),
    "ellipsoidal_fallback": ("gnss_ellipsoidal.txt", "EPSG:4979", None),
    "ellipsoidal_auto": ("gnss_ellipsoidal.txt", "EPSG:4979", "auto"),
    "take_off_auto": ("gnss_take_off.txt", "EPSG:4979", "auto"),
}


@pytest.fixture(scope="module")
def runs(tmp_path_factory, sequence_cache):
    if crs_module.fallback_geoid() is None:
        pytest.skip("EGM96 grid (Debian proj-data) not installed")
    workdir = tmp_path_factory.mktemp("height_systems")
    workspace = build_workspace(workdir, sequence_cache)
    results = {name: run(workspace, workdir / name, *spec) for name, spec in RUNS.items()}
    return workspace, results


@pytest.mark.slow
def test_ellipsoidal_heights_work_through_the_egm96_fallback(runs, caplog):
    _, results = runs
    reference, _ = results["dhhn2016"]
    rms, result = results["ellipsoidal_fallback"]
    assert result.quality.verdict != "failed"
    assert rms <= 1.05 * reference, (rms, reference)


@pytest.mark.slow
@pytest.mark.parametrize("name, applied", [("ellipsoidal_auto", DELTA_GEOID),
                                           ("take_off_auto", DELTA_GEOID + ABOVE_TAKE_OFF)])
def test_auto_finds_the_height_offset_and_keeps_the_accuracy(runs, name, applied):
    workspace, results = runs
    reference, _ = results["dhhn2016"]
    rms, result = results[name]
    assert rms <= 1.05 * reference, (rms, reference)
    # Model minus GNSS: the applied offset and the GNSS's own mean height error.
    expected = -(applied + gnss_mean_height_error(workspace))
    offset = result.gnss_offset
    assert offset["value_m"] == pytest.approx(expected, abs=0.2)
    assert offset["geoid"]["name"] == "EGM96" and offset["sigma_m"] < 1.0
    assert offset["prior_dropped"] == (applied > 10)


if __name__ == "__main__":  # pragma: no cover
    logging.basicConfig(level=logging.WARNING)
    import tempfile

    workdir = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp())
    workspace = build_workspace(workdir)
    error = gnss_mean_height_error(workspace)
    print(f"GNSS's own mean height error {error:+.3f} m")
    for name, spec in RUNS.items():
        out = workdir / name
        if out.exists():
            import shutil

            shutil.rmtree(out)
        rms, result = run(workspace, out, *spec)
        offset = result.gnss_offset
        text = ""
        if offset:
            applied = DELTA_GEOID + (ABOVE_TAKE_OFF if "take_off" in name else 0.0)
            text = (f", offset {offset['value_m']:+.3f} +- {offset['sigma_m']:.3f} m, expected "
                    f"{-(applied + error):+.3f} m")
        print(f"{name}: check points RMS 3D {rms:.3f} m, {result.quality.verdict}{text}")
