"""Check point plots (Unger Fig. 22, |Delta| vs sigma) and the evaluate report directory."""

from __future__ import annotations

import base64
import json
import re
import struct

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.cli import main as cli_main
from colmap_citymodel.errors import InputError
from colmap_citymodel.precision.plots import _round_length, evaluation_markdown, evaluation_plots, plot_checkpoint_errors, plot_delta_vs_sigma, write_evaluation_report

PNG = b"\x89PNG\r\n\x1a\n"
OFFSET = np.array([691_000.0, 5_336_000.0, 500.0])


def _png_size(data: bytes) -> tuple[int, int]:
    assert data[:8] == PNG and data[12:16] == b"IHDR"
    return struct.unpack(">II", data[16:24])


def _strip(n=12, seed=0):
    rng = np.random.default_rng(seed)
    known = np.column_stack([np.linspace(0, 100, n), rng.uniform(-5, 5, n), rng.uniform(0, 9, n)])
    return known + OFFSET, rng.normal(0, 0.05, (n, 3))


def test_round_scale_lengths():
    assert [_round_length(v) for v in (0.37, 0.12, 0.09, 2.4, 7.0, 1.0)] == \
        [0.2, 0.1, 0.05, 2.0, 5.0, 1.0]


def test_error_arrows_and_delta_sigma_are_pngs():
    known, errors = _strip()
    png = plot_checkpoint_errors(known[:, :2], errors, ids=[f"CP{i}" for i in range(12)])
    width, height = _png_size(png)
    assert len(png) > 10_000 and width > 1.5 * height  # a strip along a street: a wide figure
    square = known.copy()
    square[:, 1] = OFFSET[1] + np.linspace(0, 100, 12)[::-1]
    w2, h2 = _png_size(plot_checkpoint_errors(square[:, :2], errors))
    assert h2 > height  # an extent as tall as wide gets a taller figure
    sigma = np.abs(errors) * np.random.default_rng(1).uniform(0.3, 3.0, errors.shape)
    png = plot_delta_vs_sigma(errors, sigma)
    assert _png_size(png)[0] > 500 and len(png) > 10_000
    with pytest.raises(ValueError, match="one error per known position"):
        plot_checkpoint_errors(known[:3, :2], errors)
    with pytest.raises(ValueError, match="finite, positive sigma"):
        plot_delta_vs_sigma(errors, np.full_like(errors, np.nan))


def _evaluation(known, errors, sigma=None, truth=False) -> dict:
    ids = [f"CP{i}" for i in range(len(known))]
    points = {pid: {"error": e.tolist(), "views": 3, "rms_px": 0.5,
                    **({} if sigma is None else {"sigma": s.tolist()})}
              for pid, e, s in zip(ids, errors, sigma if sigma is not None else errors)}
    rms = np.sqrt(np.mean(errors ** 2, axis=0))
    block = {"num_checkpoints": len(ids), "rms_x": rms[0], "rms_y": rms[1], "rms_z": rms[2],
             "rms_3d": float(np.linalg.norm(rms)), "rms_3d_after_helmert": 0.01,
             "helmert": None, "frame": "crs", "missing": [], "points": points}
    return {"evaluated": block, "truth": dict(block) if truth else None}, dict(zip(ids, known))


def test_evaluation_plots_follow_what_the_evaluation_has():
    known, errors = _strip()
    evaluation, coordinates = _evaluation(known, errors)
    plots = evaluation_plots(evaluation, coordinates)
    assert list(plots) == ["check point errors, evaluated model (Unger Fig. 22)"]
    assert evaluation_plots(evaluation, None) == {}  # no known coordinates: no arrows
    with_sigma, _ = _evaluation(known, errors, np.full_like(errors, 0.04), truth=True)
    plots = evaluation_plots(with_sigma, coordinates)
    assert len(plots) == 4 and sum("Delta| vs sigma" in k for k in plots) == 2
    assert all(_png_size(png)[0] > 500 for png in plots.values())
    text = evaluation_markdown(with_sigma)
    assert "## Truth poses" in text and "| CP0 | " in text and "sigma X" in text


def test_report_directory(tmp_path):
    known, errors = _strip()
    evaluation, coordinates = _evaluation(known, errors, np.full_like(errors, 0.04))
    plots = evaluation_plots(evaluation, coordinates)
    out = write_evaluation_report(tmp_path / "report", evaluation, plots)
    assert json.loads((out / "evaluation.json").read_text())["evaluated"]["num_checkpoints"] == 12
    files = sorted((out / "plots").glob("*.png"))
    assert len(files) == len(plots) == 2
    page = (out / "report.html").read_text()
    embedded = re.findall(r"src='data:image/png;base64,([^']+)'", page)
    assert sorted(base64.b64decode(e) for e in embedded) == sorted(f.read_bytes() for f in files)
    assert "RMS 3D" in page and "CP11" in page
    with pytest.raises(InputError, match="output path exists"):
        write_evaluation_report(out, evaluation, plots)


def _workspace(tmp_path, error=0.05):
    """A synthetic model in CRS coordinates shifted by 0.3 m, check points with known errors."""
    options = pycolmap.SyntheticDatasetOptions()
    options.num_rigs, options.num_frames_per_rig, options.num_points3D = 1, 6, 30
    pycolmap.set_random_seed(2)
    rec = pycolmap.synthesize_dataset(options)
    rng = np.random.default_rng(3)
    lines_cp, lines_obs, ids = [], [], []
    for point_id, point in list(rec.points3D.items())[:10]:
        known = point.xyz + OFFSET + rng.normal(0, error, 3)
        ids.append(f"CP{point_id}")
        lines_cp.append(f"CP{point_id} {known[0]:.6f} {known[1]:.6f} {known[2]:.6f}")
        for element in point.track.elements:
            image = rec.image(element.image_id)
            xy = image.points2D[element.point2D_idx].xy
            lines_obs.append(f"{image.name} CP{point_id} {xy[0]:.9f} {xy[1]:.9f}")
    (tmp_path / "checkpoints.txt").write_text("\n".join(lines_cp) + "\n")
    (tmp_path / "obs.txt").write_text("\n".join(lines_obs) + "\n")
    model = tmp_path / "sparse"
    model.mkdir()
    rec.transform(pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), OFFSET + [0.3, 0.0, 0.0]))
    rec.write(str(model))
    return model, ids


def test_evaluate_cli_writes_the_report(tmp_path, capsys):
    model, ids = _workspace(tmp_path)
    args = ["evaluate", "--input_path", str(model), "--checkpoints",
            str(tmp_path / "checkpoints.txt"), "--observations", str(tmp_path / "obs.txt")]
    assert cli_main(args + ["--output_path", str(tmp_path / "plain")]) == 0
    out = tmp_path / "plain"
    evaluation = json.loads((out / "evaluation.json").read_text())
    assert evaluation["evaluated"]["num_checkpoints"] == 10
    assert abs(evaluation["evaluated"]["rms_x"] - 0.3) < 0.1  # the 0.3 m shift
    names = [p.name for p in sorted((out / "plots").glob("*.png"))]
    assert names == ["0_check_point_errors_evaluated_model.png"]  # no sigma: no Delta plot
    assert (out / "report.html").read_text().count("data:image/png;base64,") == 1

    # With the adjustment's covariance next to the model: the Delta vs sigma plot too.
    sigma = 0.02
    (model / "checkpoint_precision.json").write_text(json.dumps({
        "ids": ids, "points": [[0, 0, 0]] * len(ids),
        "covariance": (np.eye(3 * len(ids)) * sigma ** 2).tolist(), "note": "test sigma"}))
    assert cli_main(args + ["--output_path", str(tmp_path / "with_sigma")]) == 0
    out = tmp_path / "with_sigma"
    names = [p.name for p in sorted((out / "plots").glob("*.png"))]
    assert names == ["0_check_point_errors_evaluated_model.png",
                     "1_Delta_vs_sigma_evaluated_model.png"]
    page = (out / "report.html").read_text()
    assert page.count("data:image/png;base64,") == 2 and "Delta/sigma" in page
    capsys.readouterr()
    # A taken output directory is one clear error before anything is evaluated.
    assert cli_main(args + ["--output_path", str(out)]) == 2
    captured = capsys.readouterr()
    assert "output path exists" in captured.err and "RMS X" not in captured.out
