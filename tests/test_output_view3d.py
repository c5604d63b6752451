"""The interactive 3D view of report.html (output.view3d): what the figure holds, its size on a
large block, and report.html drawn by headless Chromium (WebGL through SwiftShader) with the
page's ready flag, the expected number of traces and no console errors or network requests."""

from __future__ import annotations

import base64
import dataclasses
import json
import os
import re
import select
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.assign.assignment import Assignment
from colmap_citymodel.batch.summary import _html as batch_index
from colmap_citymodel.citymodel.build import store_from_polygons
from colmap_citymodel.options import RefineOptions
from colmap_citymodel.output import view3d
from colmap_citymodel.output.result import RefineResult
from colmap_citymodel.output.write import face_colours, write_refined
from colmap_citymodel.precision.figures import html_page
from colmap_citymodel.precision.quality import QualityReport

ORIGIN = np.array([690000.0, 5336000.0, 500.0])


def block_store():
    """Two 10 m boxes north of an east-west street (walls, roofs, ground), CRS coordinates."""
    polygons, semantics = [], []
    for x0 in (0.0, 14.0):
        a, y0, h = 10.0, 5.0, 10.0
        c = [(x0, y0), (x0 + a, y0), (x0 + a, y0 + a), (x0, y0 + a)]
        for (x1, y1), (x2, y2) in zip(c, c[1:] + c[:1]):
            polygons.append([(x1, y1, 0), (x2, y2, 0), (x2, y2, h), (x1, y1, h)])
            semantics.append("WallSurface")
        polygons.append([(x, y, h) for x, y in c])
        semantics.append("RoofSurface")
        polygons.append([(x, y, 0) for x, y in c[::-1]])
        semantics.append("GroundSurface")
    return store_from_polygons([np.array(p) + ORIGIN for p in polygons], semantics=semantics,
                               origin=ORIGIN)


def block(store, num_points: int, shift=(0.0, 0.0, 0.0), seed: int = 1):
    """A reconstruction (local frame): 12 cameras along the street at y = -5 looking north,
    tie points on the street-side walls and the roofs (10 % off every face)."""
    rng = np.random.default_rng(seed)
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model="PINHOLE", width=800, height=600,
                             params=[600.0, 600.0, 400.0, 300.0], camera_id=1)
    rec.add_camera_with_trivial_rig(camera)
    # camera x right = east, y down, z forward = north
    rotation = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    for k in range(12):
        centre = np.array([2.0 * k, -5.0, 2.0]) + shift
        image = pycolmap.Image(name=f"img{k:03d}.jpg", camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centre))
    normals, offsets = store.normals, store.offsets
    semantic = np.asarray(store.faces.semantic.categories)[store.faces.semantic.codes]
    usable = np.flatnonzero((semantic == "RoofSurface")
                            | ((semantic == "WallSurface") & (normals[:, 1] < -0.5)))
    face = rng.choice(usable, num_points)
    points = np.empty((num_points, 3))
    for f in np.unique(face):
        rows = np.flatnonzero(face == f)
        ring = store.vertices[store.faces[f].exterior]
        lo, hi = ring.min(0), ring.max(0)
        p = lo + rng.random((len(rows), 3)) * (hi - lo)
        points[rows] = p - np.outer(p @ normals[f] + offsets[f], normals[f])  # onto the plane
    off = rng.random(num_points) < 0.1
    face[off] = -1
    points[off] += rng.normal(0.0, 1.0, (int(off.sum()), 3))
    ids = np.array([rec.add_point3D(p + shift, pycolmap.Track()) for p in points])
    return rec, ids, face


def synthetic_result(num_points: int = 2000) -> RefineResult:
    """A RefineResult as refine hands it to the output stage, without running refine."""
    store = block_store()
    refined, ids, face = block(store, num_points)
    gnss_only, _, _ = block(store, num_points, shift=(1.5, -1.0, 1.2))
    distance = np.where(face >= 0, 0.0, np.nan)
    assignment = Assignment(point_ids=ids, face_index=face, distance=distance, threshold=0.5)
    used = np.unique(face[face >= 0])
    return RefineResult(
        reconstruction=refined, store=store, adjusted_store=store, assignment=assignment,
        plane_faces=used, plane_normals=store.normals[used], plane_offsets=store.offsets[used],
        input_to_local=pycolmap.Sim3d(), georegistration_rms=None, step2=None,
        step2_eliminated=0, iterations=[], options=RefineOptions(), gnss_only=gnss_only,
        quality=QualityReport("ok"), refined=refined)


def values(spec: dict) -> np.ndarray:
    """The numbers of a plotly typed-array spec."""
    dtype = np.dtype(spec["dtype"]).newbyteorder("<")
    return np.frombuffer(base64.b64decode(spec["bdata"]), dtype)


def colour_at(marker: dict, value: float) -> str:
    """The colour that `marker`'s colourscale gives `value` (at a stop pair of one colour)."""
    t = (value - marker["cmin"]) / (marker["cmax"] - marker["cmin"])
    scale = marker["colorscale"]
    for (t0, c0), (t1, c1) in zip(scale, scale[1:]):
        if t0 <= t <= t1:
            assert c0 == c1, f"{value} falls between two colours"
            return c0
    raise AssertionError(f"{value} is outside the colourscale")


def palette(result):
    return face_colours(result.store.num_faces)


@pytest.fixture(scope="module")
def result():
    return synthetic_result()


def test_the_figure_holds_the_model_both_blocks_and_their_toggle(result):
    figure, facts = view3d.build_figure(result, palette(result))
    store = result.store
    assert facts["num_faces"] == store.num_faces  # all faces are near this block
    names = [t["name"] for t in figure["data"]]
    # walls without and with tie points, roofs with, ground without; then the outlines
    assert names[:facts["num_model_traces"]] == [
        "walls (6)", "walls with tie points (2)", "roofs with tie points (2)", "ground (2)",
        "face outlines"]
    assert facts["blocks"] == {"gnss_only": [5, 6, 7], "refined": [8, 9, 10]}
    assert facts["num_traces"] == len(figure["data"]) == 11
    # the refined block shows first; the buttons switch the blocks' traces, the model stays
    visible = [t.get("visible", True) for t in figure["data"]]
    assert visible == [True] * 5 + [False] * 3 + [True] * 3
    menus = figure["layout"]["updatemenus"]
    labels = [b["label"] for b in menus[0]["buttons"]]
    assert labels == ["GNSS-only block", "refined block", "both blocks"]
    assert menus[0]["buttons"][0]["args"][0]["visible"] == [True] * 8 + [False] * 3
    assert menus[0]["buttons"][2]["args"][0]["visible"] == [True] * 11
    assert menus[0]["active"] == 1
    # colour by face: the palette of assignments.ply; by residual: n . x + d of the face
    a = result.assignment
    refined_points = figure["data"][9]
    assigned = a.face_index >= 0
    marker = refined_points["marker"]
    np.testing.assert_array_equal(values(marker["color"]), a.face_index[assigned])
    colours = face_colours(store.num_faces)
    for f in np.unique(a.face_index[assigned]):
        assert colour_at(marker, f) == "#%02x%02x%02x" % tuple(colours[f])
    xyz = np.c_[values(refined_points["x"]), values(refined_points["y"]),
                values(refined_points["z"])]
    np.testing.assert_allclose(xyz, [result.refined.point3D(int(i)).xyz
                                     for i in a.point_ids[assigned]], atol=1e-4)
    residual_button = menus[1]["buttons"][1]
    assert list(residual_button["args"][1]) == [6, 9]
    # restyle reads a list as one value per trace: the colourscale is given for each of both
    assert residual_button["args"][0]["marker.colorscale"] == [view3d.RESIDUAL_COLOURS] * 2
    face_button = menus[1]["buttons"][0]["args"][0]
    assert face_button["marker.colorscale"] == [marker["colorscale"]] * 2
    np.testing.assert_array_equal(values(face_button["marker.color"][1]), values(marker["color"]))
    gnss_residuals = values(residual_button["args"][0]["marker.color"][0])
    refined_residuals = values(residual_button["args"][0]["marker.color"][1])
    assert np.abs(refined_residuals).max() < 1e-3  # the refined points lie on their faces
    assert np.sqrt(np.mean(gnss_residuals ** 2)) > 0.5  # the GNSS-only ones 1-2 m off
    # fixed axis ranges in true proportions, around both blocks' cameras and the model
    scene = figure["layout"]["scene"]
    ranges = np.array([scene[f"{axis}axis"]["range"] for axis in "xyz"])
    size = ranges[:, 1] - ranges[:, 0]
    np.testing.assert_allclose([scene["aspectratio"][axis] for axis in "xyz"], size / size.max())
    for rec in (result.refined, result.gnss_only):
        centres = np.array([im.projection_center() for im in rec.images.values()])
        assert np.all((centres > ranges[:, 0]) & (centres < ranges[:, 1]))
    assert np.all(ranges[:, 0] <= store.vertices.min(0)) and np.all(
        ranges[:, 1] >= store.vertices.max(0))
    # the cameras: 12 frusta (4 rays + a rectangle each) and the track
    cameras = figure["data"][10]
    assert cameras["name"] == "refined: cameras (12)"
    assert np.count_nonzero(np.isnan(values(cameras["x"]))) == 12 * 5 + 1


def test_the_view_is_in_the_local_frame_and_says_the_origin(result):
    section, facts = view3d.view_section(result, palette(result))
    figure, _ = view3d.build_figure(result, palette(result))
    for trace in figure["data"]:
        x = values(trace["x"])
        assert np.nanmax(np.abs(x)) < 100.0  # metres from the origin, not CRS coordinates
    assert "E 690000.000, N 5336000.000, H 500.000" in section
    assert f"id='{view3d.ANCHOR}'" in section
    assert "window.viewReady = true" in section
    assert "<script src=" not in section and "* plotly.js v" in section  # plotly.js inline
    assert "2,000 of 2,000 tie points drawn" in section


def test_a_large_block_is_subsampled_and_stays_small():
    result = synthetic_result(100_000)
    t0 = time.perf_counter()
    section, facts = view3d.view_section(result, palette(result), max_points=30_000)
    seconds = time.perf_counter() - t0
    figure, _ = view3d.build_figure(result, palette(result), max_points=30_000)
    drawn = sum(len(values(t["x"])) for t in figure["data"][facts["num_model_traces"]:]
                if t["mode"] == "markers")
    assert facts["num_drawn"] == 30_000
    assert drawn == 2 * 30_000  # the same subset in both blocks
    assert "30,000 of 100,000 tie points drawn (a random subset)" in section
    assert len(section.encode()) < 20e6
    assert seconds < 20.0
    # the subset is the same in every run
    again, _ = view3d.build_figure(result, palette(result), max_points=30_000)
    assert again["data"][9]["x"] == figure["data"][9]["x"]


def test_without_gnss_only_the_refined_block_and_after_a_failed_gate_gnss_only_first():
    result = synthetic_result(300)
    failed = dataclasses.replace(result, quality=QualityReport("failed", ["no help"]),
                                 reconstruction=result.gnss_only)  # as refine hands it back
    figure, facts = view3d.build_figure(failed, palette(failed))
    assert facts["shown"] == "gnss_only"
    assert [t.get("visible", True) for t in figure["data"]] == [True] * 8 + [False] * 3
    assert figure["layout"]["updatemenus"][0]["active"] == 0
    section, _ = view3d.view_section(failed, palette(failed))
    assert "The GNSS-only block is what was written" in section
    alone = dataclasses.replace(result, gnss_only=None)
    figure, facts = view3d.build_figure(alone, palette(alone))
    assert facts["blocks"] == {"refined": [5, 6, 7]} and len(figure["data"]) == 8
    assert [b["label"] for b in figure["layout"]["updatemenus"][0]["buttons"]] == \
        ["refined block"]
    assert "there is no GNSS-only one" in view3d.view_section(alone, palette(alone))[0]


def test_faces_far_from_the_block_are_left_out():
    result = synthetic_result(500)
    store = result.store
    lo, hi = np.array([-5.0, -10.0, -5.0]), np.array([11.0, 20.0, 20.0])
    near = view3d.faces_near(store, lo, hi, max_faces=1000)
    centroids = store.centroids[near]
    assert len(near) == 6 and np.all(centroids[:, 0] < 12.0)  # the first box only
    assert len(view3d.faces_near(store, lo, hi, max_faces=3)) == 3


def test_the_batch_index_links_each_report_and_its_3d_view():
    page = batch_index([{"workspace": "street_a", "status": "done", "verdict": "ok"},
                        {"workspace": "street_b", "status": "error", "error": "bad"}])
    assert 'href="street_a/report.html"' in page
    assert f'href="street_a/report.html#{view3d.ANCHOR}"' in page
    assert "street_b/report.html" not in page


# -- report.html in headless Chromium -------------------------------------------------------------

def _chromium_binary() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return shutil.which(name)
    return None


@pytest.fixture(scope="session")
def chromium() -> str:
    """Debian's chromium; installed with apt-get when missing and we are root."""
    binary = _chromium_binary()
    if binary is None and hasattr(os, "geteuid") and os.geteuid() == 0 \
            and shutil.which("apt-get"):
        env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
        subprocess.run(["apt-get", "update"], capture_output=True, env=env, timeout=900)
        subprocess.run(["apt-get", "install", "-y", "chromium"], capture_output=True, env=env,
                       timeout=1800)
        binary = _chromium_binary()
    if binary is None:
        pytest.skip("headless Chromium is missing and cannot be installed here (needs root "
                    "and apt-get: apt-get install -y chromium)")
    return binary


#: Puts the pipe ends on fds 3 and 4, where --remote-debugging-pipe expects them, and starts
#: the browser.
DUP_AND_EXEC = ("import os, sys; os.dup2(int(sys.argv[1]), 3); os.dup2(int(sys.argv[2]), 4); "
                "os.execvp(sys.argv[3], sys.argv[3:])")


class Browser:
    """Headless Chromium driven over the DevTools protocol on a pipe (fds 3 and 4)."""

    def __init__(self, binary: str, profile: Path):
        to_browser_r, self._to_browser = os.pipe()
        self._from_browser, from_browser_w = os.pipe()
        args = [binary, "--headless", "--no-sandbox", "--disable-gpu",
                "--enable-unsafe-swiftshader", "--remote-debugging-pipe", "--no-first-run",
                "--window-size=1400,900", f"--user-data-dir={profile}", "about:blank"]
        self.process = subprocess.Popen(
            [sys.executable, "-c", DUP_AND_EXEC, str(to_browser_r), str(from_browser_w), *args],
            pass_fds=(to_browser_r, from_browser_w), stdout=subprocess.DEVNULL,
            stderr=open(profile.parent / "chromium.log", "wb"))
        os.close(to_browser_r)
        os.close(from_browser_w)
        self._buffer = b""
        self._id = 0
        self.events: list[dict] = []

    def _read(self, timeout: float) -> dict | None:
        end = time.monotonic() + timeout
        while b"\0" not in self._buffer:
            left = end - time.monotonic()
            if left <= 0 or not select.select([self._from_browser], [], [], left)[0]:
                return None
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                raise RuntimeError("chromium closed the DevTools pipe")
            self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def call(self, method: str, params: dict | None = None, session: str | None = None,
             timeout: float = 20.0) -> dict:
        self._id += 1
        message = {"id": self._id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            reply = self._read(end - time.monotonic())
            if reply is None:
                break
            if reply.get("id") == self._id:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                return reply.get("result", {})
            self.events.append(reply)
        raise TimeoutError(f"{method}: no answer from chromium in {timeout} s")

    def close(self) -> None:
        try:
            self.call("Browser.close", timeout=5.0)
        except (RuntimeError, TimeoutError, OSError):
            pass
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        os.close(self._to_browser)
        os.close(self._from_browser)


STATE = ("JSON.stringify({ready: window.viewReady === true, traces: document.body ? "
         "document.body.dataset.traces : null, drawn: document.body ? "
         "document.body.dataset.drawn : null, readyMs: document.body ? "
         "document.body.dataset.readyMs : null})")


def open_page(binary: str, page: Path, profile: Path, timeout: float = 60.0) -> dict:
    """Load `page` and wait for its ready flag: {ready, traces, drawn, readyMs, errors,
    requests} (console errors and exceptions; requests for anything but file:/data:)."""
    browser = Browser(binary, profile)
    try:
        target = browser.call("Target.createTarget", {"url": "about:blank"})["targetId"]
        session = browser.call("Target.attachToTarget",
                               {"targetId": target, "flatten": True})["sessionId"]
        for domain in ("Runtime", "Log", "Network", "Page"):
            browser.call(f"{domain}.enable", session=session)
        browser.call("Page.navigate", {"url": page.resolve().as_uri()}, session=session)
        end = time.monotonic() + timeout
        state = {"ready": False}
        while time.monotonic() < end:
            reply = browser.call("Runtime.evaluate", {"expression": STATE,
                                                      "returnByValue": True}, session=session)
            state = json.loads(reply["result"].get("value") or "{}")
            if state.get("ready"):
                break
            time.sleep(0.2)
        time.sleep(0.3)  # errors of the first frames after the promise
        browser.call("Runtime.evaluate", {"expression": "1"}, session=session)
    finally:
        browser.close()
    errors, requests = [], []
    for event in browser.events:
        method, params = event.get("method"), event.get("params", {})
        if method == "Runtime.exceptionThrown":
            errors.append(params["exceptionDetails"].get("exception", {}).get(
                "description", params["exceptionDetails"].get("text")))
        elif method == "Runtime.consoleAPICalled" and params.get("type") in ("error", "assert"):
            errors.append(" ".join(str(a.get("value", a.get("description")))
                                   for a in params.get("args", [])))
        elif method == "Log.entryAdded" and params["entry"].get("level") == "error":
            errors.append(params["entry"].get("text"))
        elif method == "Network.requestWillBeSent":
            url = params["request"]["url"]
            if not url.startswith(("file:", "data:", "about:")):
                requests.append(url)
    return {**state, "errors": errors, "requests": requests}


@pytest.fixture(scope="module")
def report(tmp_path_factory, result):
    """report.html as write_refined writes it, around the synthetic block's view."""
    directory = tmp_path_factory.mktemp("report")
    page = html_page("colmap-citymodel refine report", {}, "summary")
    from colmap_citymodel.output.write import with_view3d

    path = directory / "report.html"
    path.write_text(with_view3d(page, result))
    return path


def test_headless_chromium_draws_every_trace_without_errors(chromium, report, tmp_path, result):
    state = open_page(chromium, report, tmp_path / "profile")
    _, facts = view3d.build_figure(result, palette(result))
    assert state["ready"], f"the view never set its ready flag: {state}"
    assert int(state["traces"]) == facts["num_traces"] == 11
    # the WebGL scene holds one object per visible trace: model and the refined block
    assert int(state["drawn"]) == facts["num_drawn_visible"] == 8
    assert state["errors"] == []
    assert state["requests"] == []  # offline: plotly.js is in the page
    assert float(state["readyMs"]) < 30_000


def test_write_refined_puts_the_view_into_report_html(chromium, tmp_path, street_refined):
    """The whole output stage on a refined street (what `refine`, `batch` and `demo` write)."""
    refined = street_refined
    out = write_refined(refined, tmp_path / "refined")
    page = (out / "report.html").read_text()
    assert page.index(f"id='{view3d.ANCHOR}'") < page.index("<h2>Summary</h2>")
    assert len(re.findall(r"Plotly\.newPlot", page)) >= 1
    size = (out / "report.html").stat().st_size
    assert size < 20e6
    state = open_page(chromium, out / "report.html", tmp_path / "profile")
    _, facts = view3d.build_figure(refined, palette(refined))
    assert state["ready"] and state["errors"] == [] and state["requests"] == []
    assert int(state["traces"]) == facts["num_traces"]
    assert int(state["drawn"]) == facts["num_drawn_visible"]
