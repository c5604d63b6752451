"""Video frames in order: a sanity check of the registered poses (`refine --sequence`).

Frames cut from a video are named in capture order. Between consecutive frames the camera
moves a little and turns a little, so after registration each frame's centre lies near the
midpoint of its neighbours' (at the ends: near the line through the next two) and its viewing
direction near theirs. A frame far off that path, or turned away from its neighbours, was
posed wrongly (a mismatched frame, a frame the model put on the wrong facade) and is reported;
the verdict stays that of the block.

Scales come from the sequence itself: a frame "jumps" when it lies more than JUMP_STEPS
median steps (and at least MIN_JUMP_M) off its neighbours' path, or its view turns more than
JUMP_STEPS median turns (and at least MIN_TURN_DEG) from theirs; of neighbouring frames the
one furthest off is named. Each camera (of a rig) is its own sequence.
"""

from __future__ import annotations

import logging

import numpy as np
import pycolmap

from ..adjust.sliding_window import natural_key

logger = logging.getLogger(__name__)

#: A frame this many median steps (turns) off its neighbours' path (view) jumps: a smoothly
#: moving camera stays within about one step of the midpoint of its neighbours.
JUMP_STEPS = 3.0
#: Metres off the path below which no frame counts as jumping (a camera standing still).
MIN_JUMP_M = 1.0
#: Degrees of turn from the neighbours' view below which no frame counts as jumping.
MIN_TURN_DEG = 10.0
#: Fewest frames of one camera that make a sequence to check.
MIN_FRAMES = 3


def frame_order(rec: pycolmap.Reconstruction) -> dict[int, list[int]]:
    """The registered images of each camera in the natural order of their names."""
    out: dict[int, list[int]] = {}
    for image_id in rec.reg_image_ids():
        out.setdefault(rec.image(image_id).camera_id, []).append(int(image_id))
    return {c: sorted(ids, key=lambda i: natural_key(rec.image(i).name))
            for c, ids in out.items()}


def _poses(rec: pycolmap.Reconstruction, ids: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) camera centres and (N, 3) unit viewing directions (world frame)."""
    centres = np.array([rec.image(i).projection_center() for i in ids])
    views = np.array([np.asarray(rec.image(i).cam_from_world().rotation.matrix())[2]
                      for i in ids])
    return centres, views / np.linalg.norm(views, axis=1, keepdims=True)


def _expected(values: np.ndarray) -> np.ndarray:
    """(N, 3) each frame's value from its neighbours: their mean, at the ends the linear
    extrapolation from the next two."""
    out = np.empty_like(values)
    out[1:-1] = 0.5 * (values[:-2] + values[2:])
    out[0] = 2.0 * values[1] - values[2]
    out[-1] = 2.0 * values[-2] - values[-3]
    return out


def _local_maxima(values: np.ndarray) -> np.ndarray:
    """bool: no lower than either neighbour (the frame a jump is of, not its neighbours)."""
    padded = np.pad(values, 1, constant_values=-np.inf)
    return (values >= padded[:-2]) & (values >= padded[2:])


def check_camera(rec: pycolmap.Reconstruction, ids: list[int]) -> dict:
    """The check of one camera's frames `ids` (in order): median step and turn, the jumps."""
    centres, views = _poses(rec, ids)
    steps = np.linalg.norm(np.diff(centres, axis=0), axis=1)
    turns = np.degrees(np.arccos(np.clip(np.sum(views[1:] * views[:-1], axis=1), -1, 1)))
    step, turn = float(np.median(steps)), float(np.median(turns))
    off = np.linalg.norm(centres - _expected(centres), axis=1)
    expected_view = _expected(views)
    expected_view /= np.maximum(np.linalg.norm(expected_view, axis=1, keepdims=True), 1e-12)
    away = np.degrees(np.arccos(np.clip(np.sum(views * expected_view, axis=1), -1, 1)))
    jump_m, jump_deg = max(JUMP_STEPS * step, MIN_JUMP_M), max(JUMP_STEPS * turn, MIN_TURN_DEG)
    flagged = (((off > jump_m) & _local_maxima(off))
               | ((away > jump_deg) & _local_maxima(away)))
    jumps = [{"image": rec.image(ids[k]).name, "off_path_m": float(off[k]),
              "turn_deg": float(away[k]), "position": int(k)} for k in np.flatnonzero(flagged)]
    return {"frames": len(ids), "median_step_m": step, "median_turn_deg": turn,
            "jump_m": jump_m, "jump_deg": jump_deg, "jumps": jumps}


def sequence_check(rec: pycolmap.Reconstruction) -> dict:
    """report.json's `sequence`: per camera with at least MIN_FRAMES registered frames, the
    median step and turn between consecutive frames and the frames that jump."""
    cameras = {}
    for camera_id, ids in frame_order(rec).items():
        if len(ids) < MIN_FRAMES:
            continue
        cameras[str(camera_id)] = check = check_camera(rec, ids)
        for jump in check["jumps"]:
            logger.warning(
                "sequence: frame %s lies %.2f m off the path of its neighbours and turns %.1f "
                "deg from their view (camera %s: median step %.2f m, turn %.1f deg): its pose "
                "does not follow the video", jump["image"], jump["off_path_m"],
                jump["turn_deg"], camera_id, check["median_step_m"], check["median_turn_deg"])
    jumps = [j["image"] for c in cameras.values() for j in c["jumps"]]
    logger.info("sequence: %d frames of %d camera(s) in name order, %d jump(s)%s",
                sum(c["frames"] for c in cameras.values()), len(cameras), len(jumps),
                (": " + ", ".join(jumps[:10]) + (" ..." if len(jumps) > 10 else ""))
                if jumps else "")
    return {"cameras": cameras, "jumps": jumps}
