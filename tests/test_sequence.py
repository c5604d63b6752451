"""`refine --sequence`: video frames in name order; a frame whose registered pose jumps from
its neighbours' (off their path, or turned away from their view) is reported, the others not."""

import numpy as np
import pycolmap
import pytest

from colmap_citymodel.cli import build_parser
from colmap_citymodel.precision.sequence import sequence_check


def turn_about_z(deg: float) -> np.ndarray:
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def drive(centres, headings, names=None) -> pycolmap.Reconstruction:
    """A camera looking horizontally along `headings` (deg, from E) at `centres`."""
    rec = pycolmap.Reconstruction()
    camera = pycolmap.Camera(model="SIMPLE_PINHOLE", width=640, height=480,
                             params=[500.0, 320.0, 240.0], camera_id=1)
    rec.add_camera_with_trivial_rig(camera)
    # camera axes x right, y down, z forward; heading 0: looking along +E
    base = np.array([[0, -1.0, 0], [0, 0, -1.0], [1.0, 0, 0]])  # rows: cam axes in world
    names = names or [f"frame_{k}.jpg" for k in range(len(centres))]
    for k, (centre, heading) in enumerate(zip(centres, headings)):
        rotation = base @ turn_about_z(heading).T  # cam_from_world
        image = pycolmap.Image(name=names[k], camera_id=1, image_id=k + 1)
        rec.add_image_with_trivial_frame(
            image, pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), -rotation @ centre))
    return rec


def curve(n: int = 30):
    """A drive along a gentle curve, 1.5 m and 1 deg per frame."""
    headings = np.arange(n) * 1.0
    steps = 1.5 * np.column_stack([np.cos(np.radians(headings)),
                                   np.sin(np.radians(headings)), np.zeros(n)])
    return np.cumsum(steps, axis=0), headings


def test_a_smooth_drive_has_no_jump():
    centres, headings = curve()
    check = sequence_check(drive(centres, headings))
    camera = check["cameras"]["1"]
    assert camera["frames"] == 30 and check["jumps"] == []
    assert camera["median_step_m"] == pytest.approx(1.5, abs=0.01)
    assert camera["median_turn_deg"] == pytest.approx(1.0, abs=0.05)


def test_a_frame_off_the_path_and_one_turned_away_are_reported():
    centres, headings = curve()
    centres[9] += [0.0, 6.0, 0.0]  # put on the other side of the street
    headings[20] += 40.0  # looking at another facade
    # Names in natural order (frame_2 before frame_10), given shuffled to the model.
    order = np.random.default_rng(0).permutation(30)
    rec = drive(centres[order], headings[order], [f"frame_{k}.jpg" for k in order])
    check = sequence_check(rec)
    assert check["jumps"] == ["frame_9.jpg", "frame_20.jpg"]
    jumps = check["cameras"]["1"]["jumps"]
    assert jumps[0]["off_path_m"] == pytest.approx(6.0, abs=0.2)
    assert jumps[1]["turn_deg"] == pytest.approx(40.0, abs=1.0)
    assert jumps[1]["off_path_m"] < 0.1


def test_refine_takes_the_sequence_flag():
    parser = build_parser()
    args = parser.parse_args(["refine", "--input_path", "in", "--citymodel", "m.gml",
                              "--output_path", "out", "--sequence"])
    assert args.sequence is True
    args = parser.parse_args(["refine", "--input_path", "in", "--citymodel", "m.gml",
                              "--output_path", "out"])
    assert args.sequence is False
