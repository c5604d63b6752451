"""The batch summary: one row per workspace, written as summary.csv, summary.json and
summary.html in the output directory (each replaced atomically, after every finished
workspace), and printed as a table.

The figures of a refined workspace come from its report.json: the quality verdict, s0 of the
final solve and of the GNSS-only adjustment (step 2), the share of tie points within 0.5 m of
the model with GNSS only and after refine, and how far refine moved the cameras from the
GNSS-only result.
"""

from __future__ import annotations

import csv
import html
import io
import json
import math
import os
import tempfile
from pathlib import Path

#: (key, header) of the summary's columns, in order.
COLUMNS = [
    ("workspace", "workspace"),
    ("status", "status"),
    ("images", "images"),
    ("gnss", "GNSS"),
    ("tiles", "tiles"),
    ("verdict", "verdict"),
    ("result", "result"),
    ("s0_gnss_only", "s0 GNSS-only"),
    ("s0", "s0"),
    ("near_model_gnss_only", "near model GNSS-only"),
    ("near_model", "near model"),
    ("shift_m", "shift from GNSS-only (m)"),
    ("seconds", "seconds"),
    ("error", "error"),
]
#: The anchor of report.html's 3D view (output.view3d.ANCHOR).
VIEW3D_ANCHOR = "view-3d"
#: Statuses: refined in this run, refined in an earlier one (resume), failed, not run
#: (interrupted before it started).
STATUSES = ("done", "skipped", "error", "not run")


def _number(value):
    return None if value is None or (isinstance(value, float) and not math.isfinite(value)) \
        else value


def row_from_report(report: dict) -> dict:
    """The figures of a summary row from a refine's report.json."""
    quality = report.get("quality") or {}
    metrics = quality.get("metrics") or {}
    step2 = report.get("step2") or {}
    return {
        "images": report.get("num_images"),
        "verdict": quality.get("verdict"),
        "reasons": quality.get("reasons", []),
        "result": report.get("result"),
        "s0_gnss_only": _number(step2.get("sigma0")),
        "s0": _number(report.get("sigma0")),
        "near_model_gnss_only": _number(metrics.get("near_share_gnss_only")),
        "near_model": _number(metrics.get("near_share")),
        "shift_m": _number(metrics.get("shift_m")),
        "refine_seconds": _number((report.get("seconds") or {}).get("total")),
    }


def read_report_row(path: str | Path) -> dict:
    return row_from_report(json.loads(Path(path).read_text()))


# -- formatting -----------------------------------------------------------------------------------

def cell(row: dict, key: str) -> str:
    """A row's value as text (shares in percent)."""
    value = row.get(key)
    if value is None or value == "":
        return ""
    if key.startswith("near_model"):
        return f"{100 * value:.0f} %"
    if key in ("s0", "s0_gnss_only"):
        return f"{value:.3f}"
    if key == "shift_m":
        return f"{value:.2f}"
    if key == "seconds":
        return f"{value:.1f}"
    return " ".join(str(value).split())  # one line (some errors span several)


def status_line(row: dict) -> str:
    """One console line for a finished workspace."""
    name = row["workspace"]
    if row.get("status") == "error":
        return f"{name}: error: {cell(row, 'error')}"
    parts = [f"{row.get('images')} images"]
    if row.get("s0") is not None:
        parts.append(f"s0 {row['s0']:.3f}")
    if row.get("near_model") is not None:
        before = row.get("near_model_gnss_only")
        parts.append("near the model " + (f"{cell(row, 'near_model_gnss_only')} -> "
                                          if before is not None else "")
                     + cell(row, "near_model"))
    if row.get("seconds") is not None:
        parts.append(f"{row['seconds']:.1f} s")
    verdict = row.get("verdict") or "?"
    if row.get("result") == "gnss_only":
        verdict += ", GNSS-only result written"
    tag = " (done before)" if row.get("status") == "skipped" else ""
    return f"{name}: {verdict}{tag} ({', '.join(parts)})"


def table(rows: list[dict]) -> str:
    """The summary as a Markdown table."""
    keys = [k for k, _ in COLUMNS if k not in ("gnss", "result")]
    headers = dict(COLUMNS)
    lines = ["| " + " | ".join(headers[k] for k in keys) + " |",
             "|" + "---|" * len(keys)]
    for row in rows:
        lines.append("| " + " | ".join(cell(row, k).replace("|", "/") for k in keys) + " |")
    return "\n".join(lines)


def counts(rows: list[dict]) -> str:
    """'3 done, 1 skipped, 1 error; verdicts: 2 ok, 2 weak'."""
    by_status = [f"{sum(r.get('status') == s for r in rows)} {s}" for s in STATUSES
                 if any(r.get("status") == s for r in rows)]
    verdicts = {}
    for r in rows:
        if r.get("verdict"):
            verdicts[r["verdict"]] = verdicts.get(r["verdict"], 0) + 1
    text = ", ".join(by_status)
    if verdicts:
        text += "; verdicts: " + ", ".join(f"{n} {v}" for v, n in sorted(verdicts.items()))
    return text


def _html(rows: list[dict]) -> str:
    colour = {"ok": "#d8f0d8", "weak": "#fff2c8", "failed": "#f8d8d8"}
    head = "".join(f"<th>{html.escape(h)}</th>" for _, h in COLUMNS)
    body = []
    for row in rows:
        cells = []
        for key, _ in COLUMNS:
            text = html.escape(cell(row, key))
            if key == "workspace" and row.get("status") in ("done", "skipped"):
                report = f'{html.escape(row["workspace"])}/report.html'
                text = (f'<a href="{report}">{text}</a> '
                        f'<a href="{report}#{VIEW3D_ANCHOR}" title="the block on the city model '
                        'in 3D">3D</a>')
            elif key == "status" and row.get("status") in ("done", "error"):
                text = f'<a href="{html.escape(row["workspace"])}.log">{text}</a>'
            style = ""
            if key == "verdict" and row.get("verdict") in colour:
                style = f' style="background:{colour[row["verdict"]]}"'
            if key == "verdict" and row.get("reasons"):
                style += f' title="{html.escape("; ".join(row["reasons"]))}"'
            if key == "status" and row.get("status") == "error":
                style = ' style="background:#f8d8d8"'
            cells.append(f"<td{style}>{text}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>colmap-citymodel "
            "batch</title><style>body{font-family:sans-serif}table{border-collapse:collapse}"
            "td,th{border:1px solid #bbb;padding:2px 6px;text-align:left}</style></head>"
            f"<body><h1>colmap-citymodel batch</h1><p>{html.escape(counts(rows))}</p>"
            "<p>near model: tie points within 0.5 m of the city model; shift: mean camera "
            "shift of the refined block from the GNSS-only adjustment. Hover a verdict for "
            "its reasons; 3D: the block on the city model in report.html's 3D view.</p>"
            f"<table><tr>{head}</tr>\n" + "\n".join(body)
            + "</table></body></html>\n")


def _csv(rows: list[dict]) -> str:
    out = io.StringIO()
    writer = csv.writer(out)
    writer.writerow([k for k, _ in COLUMNS])
    for row in rows:
        writer.writerow(["" if row.get(k) is None else row.get(k) for k, _ in COLUMNS])
    return out.getvalue()


def write_text_atomic(path: Path, text: str) -> None:
    """Write `path` through a temporary file in its directory: readers see the old or the new
    file, never half of one."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", dir=path.parent)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # mkstemp's 0600 would hide the summary from others
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_summary(output: Path, rows: list[dict]) -> None:
    """summary.csv, summary.json and summary.html in `output`."""
    write_text_atomic(output / "summary.json", json.dumps({"workspaces": rows}, indent=1))
    write_text_atomic(output / "summary.csv", _csv(rows))
    write_text_atomic(output / "summary.html", _html(rows))


def read_summary(output: Path) -> dict[str, dict]:
    """Rows of an earlier summary.json by workspace ({} when there is none)."""
    try:
        doc = json.loads((output / "summary.json").read_text())
        return {r["workspace"]: r for r in doc.get("workspaces", []) if "workspace" in r}
    except (OSError, ValueError, TypeError, KeyError):
        return {}
