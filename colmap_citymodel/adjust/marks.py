"""Ground control marks in the hybrid adjustment (group "gcp").

Each control mark (block.marks) is one more point X with two kinds of observations in
COLMAP's bundle adjuster:

- its surveyed position: X - P = 0 with the survey's sigmas (E, N, U; core
  PointPositionPriorCost), P in the plane store's local frame;
- its measurement in each image: the ray through the measured pixel (core MarkRayCost, in
  pixels over `MarkOptions.sigma_pixel`), on the mark's point and the frame's pose.

A mark measured in one image only still pulls that image's ray through its surveyed point (two
observations); one in two or more also fixes its point from the images. The marks of a refine
run are active for every problem built while `marks_in_adjustment` holds them (the GNSS-only
adjustment, every hybrid solve, the re-solves of the precision stage), so that the stages
between need not carry them: `HybridProblem` asks `active_marks()` (a context variable, one
per thread).

Blunders: after the adjustment without the model (step 2), each mark's surveyed position is
compared with where the adjusted cameras' rays put it, d = T - P, against
C = C_survey + C_rays (C_rays the rays' intersection covariance at `sigma_pixel`): the
statistic d^T C^-1 d is chi-square with 3 degrees of freedom for a sound mark. A blunder pulls
the block towards itself and pushes the others' residuals up (the ends of a line of marks
most), so the marks beyond the (1 - `blunder_alpha`) quantile are tested again in a block
adjusted without each of them (the deleted residual, its covariance grown by how well the
other marks hold the block there); the worst beyond the bound is left out, the adjustment
repeated, and the test repeated on the others (data snooping one mark at a time, Baarda
1968), while at least `MIN_TESTED` marks remain. A mark with fewer than two images cannot be
tested that way and is kept. A mark left out is named with its statistic and its offset in
the report.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import dataclass, field

import numpy as np
import pycolmap
from scipy import stats

from ..block.marks import (GroundMarks, measurements_in, similarity, similarity_design,
                           triangulate_mark)

logger = logging.getLogger(__name__)

#: Marks a blunder test needs (one left out, the others must still hold the block's datum
#: with redundancy: a similarity has 7 parameters, three marks give 9 coordinates).
MIN_TESTED = 4
#: Marks beyond the bound in the block adjusted with all of them that are tested again in a
#: block adjusted without each (one more adjustment each): the worst few, where a blunder is.
MAX_SUSPECTS = 6


@dataclass
class ControlMarks:
    """The control marks of a refine run matched to its reconstruction, in the plane store's
    local frame: surveyed positions and sigmas, and per mark its measurements (image id, xy in
    COLMAP pixels). `excluded`: marks left out of every adjustment, with the reason."""

    names: list[str]
    positions: np.ndarray  # (M, 3) local frame
    sigmas: np.ndarray  # (M, 3) m
    measurements: list[list[tuple[int, np.ndarray]]]
    sigma_pixel: float = 1.0
    excluded: dict[str, str] = field(default_factory=dict)
    missing_images: dict[str, list[str]] = field(default_factory=dict)
    tests: dict[str, dict] = field(default_factory=dict)  # the blunder test per mark

    def __len__(self) -> int:
        return len(self.names)

    @property
    def used(self) -> list[int]:
        """Indices of the marks in the adjustment: not excluded, measured in an image."""
        return [k for k, name in enumerate(self.names)
                if name not in self.excluded and self.measurements[k]]

    def holds_datum(self, rec: pycolmap.Reconstruction) -> bool:
        """Three or more marks in the adjustment measured in `rec`'s images, not on one line:
        they fix its datum."""
        used = [k for k in self.used if self.in_block(rec, k)]
        if len(used) < 3:
            return False
        xyz = self.positions[used]
        return bool(np.linalg.matrix_rank(xyz - xyz.mean(0), tol=1e-3) >= 2)

    def in_block(self, rec: pycolmap.Reconstruction, k: int) -> list[tuple[int, np.ndarray]]:
        """Mark `k`'s measurements in images `rec` holds with a pose (a sliding window's
        reconstruction holds some of the block's images)."""
        return [(i, xy) for i, xy in self.measurements[k]
                if rec.exists_image(i) and rec.image(i).has_pose]

    def triangulated(self, rec: pycolmap.Reconstruction, k: int):
        """Mark `k` intersected from its rays in `rec` (block.marks.triangulate_mark) or None."""
        return triangulate_mark(rec, self.in_block(rec, k), self.sigma_pixel)


def control_marks(marks: GroundMarks, rec: pycolmap.Reconstruction, origin: np.ndarray,
                  sigma_pixel: float) -> ControlMarks:
    """`marks` (model CRS) as control of `rec` in the local frame of `origin`; measurements in
    images `rec` does not hold are dropped (and listed), a mark left without one is excluded."""
    measurements, missing, excluded = [], {}, {}
    for mark in marks.marks:
        found, lost = measurements_in(rec, mark)
        measurements.append(found)
        if lost:
            missing[mark.name] = lost
        if not found:
            excluded[mark.name] = "measured in no registered image of the block"
    if missing:
        logger.warning("marks measured in images the block does not hold: %s",
                       "; ".join(f"{n}: {', '.join(v[:3])}" for n, v in missing.items()))
    positions = np.array([m.position for m in marks.marks]).reshape(-1, 3)
    sigmas = np.array([m.sigma for m in marks.marks]).reshape(-1, 3)
    return ControlMarks(marks.names, positions - np.asarray(origin, float), sigmas,
                        measurements, float(sigma_pixel), excluded, missing)


# -- the marks of the run in progress ---------------------------------------------------------

_ACTIVE: ContextVar[ControlMarks | None] = ContextVar("control_marks", default=None)


@contextmanager
def marks_in_adjustment(marks: ControlMarks | None):
    """Every adjustment problem built inside this block takes `marks` (None: none)."""
    token = _ACTIVE.set(marks)
    try:
        yield marks
    finally:
        _ACTIVE.reset(token)


def active_marks() -> ControlMarks | None:
    """The control marks of the run in progress (`marks_in_adjustment`), or None."""
    return _ACTIVE.get()


# -- residual blocks --------------------------------------------------------------------------

@dataclass
class MarkBlocks:
    """The marks' unknowns in one problem (Ceres holds pointers to `points`: keep this object
    alive): per mark in the problem its index in the ControlMarks and its point. Its residuals
    follow in that order: 3 for the surveyed position, 2 per image."""

    indices: list[int]
    points: list[np.ndarray]

    @property
    def num_unknowns(self) -> int:
        return 3 * len(self.points)


def add_control_marks(problem, core) -> MarkBlocks | None:
    """Group "gcp" of `problem` (adjust.problem.HybridProblem): each active mark's point, its
    surveyed position and its rays into the frames in the problem. Sets problem.counts["gcp"];
    None without marks."""
    problem.counts["gcp"] = 0
    marks = active_marks()
    if marks is None or not marks.used:
        return None
    rec, sigma_image = problem.reconstruction, problem.options.sigma_image
    blocks = MarkBlocks([], [])
    for k in marks.used:
        rays = [(i, xy) for i, xy in marks.in_block(rec, k) if problem.problem.has_parameter_block(
            rec.frame(rec.image(i).frame_id).rig_from_world.params)]
        if not rays:
            continue
        start = marks.triangulated(rec, k)
        point = np.array(start[0] if start is not None else marks.positions[k], np.float64)
        problem.problem.add_parameter_block(point, 3)
        problem.problem.add_residual_block(
            core.PointPositionPriorCost(np.asarray(marks.positions[k], float),
                                        np.asarray(marks.sigmas[k], float) / sigma_image),
            None, [point])
        for image_id, xy in rays:
            problem.problem.add_residual_block(
                _ray_cost(core, rec, image_id, xy, marks.sigma_pixel / sigma_image), None,
                [point, rec.frame(rec.image(image_id).frame_id).rig_from_world.params])
        blocks.indices.append(k)
        blocks.points.append(point)
        problem.counts["gcp"] += 3 + 2 * len(rays)
    return blocks


def _ray_cost(core, rec: pycolmap.Reconstruction, image_id: int, xy: np.ndarray, sigma: float):
    """core.MarkRayCost of one measurement: the pixel undistorted with the camera's current
    intrinsics, the sensor's constant pose in its rig."""
    image = rec.image(image_id)
    camera = image.camera
    ray = np.asarray(camera.cam_ray_from_img(np.asarray(xy, float).reshape(1, 2)),
                     float).reshape(-1)
    rotation, translation = np.array([0.0, 0.0, 0.0, 1.0]), np.zeros(3)
    if not image.is_ref_in_frame():
        rig = rec.rig(rec.frame(image.frame_id).rig_id)
        cam_from_rig = rig.sensor_from_rig(camera.sensor_id)
        rotation = np.asarray(cam_from_rig.rotation.quat, float)
        translation = np.asarray(cam_from_rig.translation, float)
    return core.MarkRayCost(ray[:2] / ray[2], float(camera.mean_focal_length()), float(sigma),
                            rotation, translation)


# -- blunders ---------------------------------------------------------------------------------

def mark_test(marks: ControlMarks, rec: pycolmap.Reconstruction, k: int,
              prediction: np.ndarray | None = None) -> dict | None:
    """Mark `k`'s surveyed position against where `rec`'s rays put it: d = T - P (m, E N U) and
    T = d^T (C_survey + C_rays + `prediction`)^-1 d (chi-square, 3 degrees of freedom); None
    with fewer than two images. `prediction` (3x3): how well the rest holds the block there."""
    found = marks.triangulated(rec, k)
    if found is None:
        return None
    point, covariance, rms = found
    d = point - marks.positions[k]
    total = np.diag(marks.sigmas[k] ** 2) + covariance
    if prediction is not None:
        total = total + prediction
    value = float(d @ np.linalg.solve(total, d))
    return {"offset_m": d.tolist(), "statistic": value, "image_rms_px": rms}


def prediction_covariance(marks: ControlMarks, rec: pycolmap.Reconstruction, k: int,
                          others: list[int]) -> np.ndarray:
    """(3, 3) how well marks `others` hold a rigid block at mark `k`: a similarity fitted to
    their surveyed positions (each with its survey and ray variance), propagated to mark k
    (block.marks.similarity_design)."""
    positions, weights = [], []
    for j in others:
        found = marks.triangulated(rec, j)
        if found is None:
            continue
        positions.append(marks.positions[j])
        weights.append(np.linalg.inv(np.diag(marks.sigmas[j] ** 2) + found[1]))
    if len(positions) < 3:
        return np.zeros((3, 3))
    centre = np.mean(positions, axis=0)
    design = similarity_design(np.array(positions), centre)
    weight = np.zeros((len(design), len(design)))
    for i, w in enumerate(weights):
        weight[3 * i:3 * i + 3, 3 * i:3 * i + 3] = w
    at_k = similarity_design(marks.positions[k], centre)
    return at_k @ np.linalg.pinv(design.T @ weight @ design) @ at_k.T


def snoop_marks(marks: ControlMarks, rec: pycolmap.Reconstruction, solve, solve_without,
                alpha: float) -> list[str]:
    """Data snooping of the control marks in the adjusted block `rec`. Each mark is tested
    against the block (`mark_test`); those beyond chi-square(3) at 1 - `alpha` (at most
    MAX_SUSPECTS, the worst first) are tested again in a block adjusted without them
    (`solve_without()`, called while the mark is excluded, returns that block), where a
    blunder no longer pulls the block towards itself; the worst of those beyond the bound is
    excluded and `solve()` adjusts the block again (returning it, `rec` from then on).
    Repeated until none is, or fewer than
    MIN_TESTED marks with two images remain. Returns the names excluded; `marks.tests` keeps
    each mark's last test."""
    bound = float(stats.chi2.ppf(1.0 - alpha, 3))
    excluded = []
    while True:
        tests = {k: mark_test(marks, rec, k) for k in marks.used}
        tests = {k: t for k, t in tests.items() if t is not None}
        for k, t in tests.items():
            marks.tests[marks.names[k]] = {**t, "bound": bound, "alpha": alpha}
        if len(tests) < MIN_TESTED:
            if tests:
                logger.info("control marks: %d with two or more images, fewer than %d: no "
                            "blunder test", len(tests), MIN_TESTED)
            return excluded
        suspects = sorted((k for k, t in tests.items() if t["statistic"] > bound),
                          key=lambda k: -tests[k]["statistic"])[:MAX_SUSPECTS]
        deleted = {k: _deleted_test(marks, k, solve_without, list(tests)) for k in suspects}
        deleted = {k: t for k, t in deleted.items() if t is not None and t["statistic"] > bound}
        if not deleted:
            return excluded
        worst = max(deleted, key=lambda k: deleted[k]["statistic"])
        name, t = marks.names[worst], deleted[worst]
        marks.tests[name] = {**t, "bound": bound, "alpha": alpha, "without_it": True}
        marks.excluded[name] = (
            f"blunder: its surveyed position is {np.linalg.norm(t['offset_m']):.3f} m from "
            f"where the block adjusted without it puts it (E N U "
            f"{np.round(t['offset_m'], 3).tolist()} m; test {t['statistic']:.1f} > "
            f"{bound:.1f}, chi-square(3) at {alpha:g}); left out of the adjustment")
        logger.warning("control mark %s: %s", name, marks.excluded[name])
        excluded.append(name)
        rec = solve()


def _deleted_test(marks: ControlMarks, k: int, solve_without, tested: list[int]) -> dict | None:
    """`mark_test` of mark `k` in the block adjusted without it (with the other tested marks'
    hold on the block there)."""
    name = marks.names[k]
    marks.excluded[name] = "under test"
    try:
        block = solve_without()
    finally:
        del marks.excluded[name]
    others = [j for j in tested if j != k]
    return mark_test(marks, block, k, prediction_covariance(marks, block, k, others))


def similarity_from_marks(marks: GroundMarks, rec: pycolmap.Reconstruction,
                          sigma_pixel: float = 1.0) -> pycolmap.Sim3d | None:
    """The similarity from `rec`'s frame to the model CRS that the marks measured in two or
    more of its images give (at least three, not on a line): where refine starts without GNSS.
    None where they do not fix it."""
    source, target = [], []
    for mark in marks.marks:
        found = triangulate_mark(rec, measurements_in(rec, mark)[0], sigma_pixel)
        if found is not None:
            source.append(found[0])
            target.append(mark.position)
    if len(source) < 3:
        return None
    target = np.array(target)
    centre = target.mean(axis=0)
    sim = similarity(np.array(source), target - centre)
    if sim is None:
        return None
    return pycolmap.Sim3d(1.0, pycolmap.Rotation3d(), centre) * sim


def datum_observations(marks: ControlMarks | None, rec: pycolmap.Reconstruction
                       ) -> tuple[np.ndarray, np.ndarray] | None:
    """The marks in the adjustment as observations of the block's datum (adjust.observability):
    their surveyed positions (local frame) and per axis sqrt(survey sigma^2 + the rays'
    intersection variance); marks with fewer than two images are left out. None: no marks."""
    if marks is None:
        return None
    positions, sigmas = [], []
    for k in marks.used:
        found = marks.triangulated(rec, k)
        if found is None:
            continue
        positions.append(marks.positions[k])
        sigmas.append(np.sqrt(marks.sigmas[k] ** 2 + np.diag(found[1])))
    if not positions:
        return None
    return np.array(positions), np.array(sigmas)


def marks_record(marks: ControlMarks | None) -> dict | None:
    """report.json `control_marks`: per mark its images, sigmas, test (the last: against the
    returned block, where `workflow.marks_after_refine` ran it) and whether (and why not) it
    was in the adjustment."""
    if marks is None:
        return None
    out = {}
    for k, name in enumerate(marks.names):
        out[name] = {"used": name not in marks.excluded and bool(marks.measurements[k]),
                     "reason": marks.excluded.get(name),
                     "num_images": len(marks.measurements[k]),
                     "missing_images": marks.missing_images.get(name, []),
                     "sigma_enu_m": marks.sigmas[k].tolist(),
                     "surveyed_local_m": marks.positions[k].tolist(),
                     "test": marks.tests.get(name)}
    return {"marks": out, "num_used": len(marks.used), "sigma_pixel": marks.sigma_pixel,
            "blunders": {n: r for n, r in marks.excluded.items() if r.startswith("blunder")}}
