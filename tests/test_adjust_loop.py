"""The refine loop's stopping helpers on hand-made assignments (the loop itself runs in
test_workflow.py)."""

from __future__ import annotations

import numpy as np

from colmap_citymodel.adjust.loop import alternating, assignment_change


def faces(*ids: int) -> bytes:
    return np.array(sorted(ids), np.int64).tobytes()


def test_alternating_needs_two_sets_taking_turns_four_times():
    a, b, c = faces(1, 2, 3), faces(1, 2, 3, 7), faces(1, 2)
    assert alternating([a, b, a, b])
    assert alternating([c, c, b, a, b, a])
    assert not alternating([b, a, b])  # three are not enough
    assert not alternating([a, a, a, a])  # the same set: no alternation
    assert not alternating([a, b, c, b])
    assert not alternating([a, b, a, c])


def test_assignment_change_counts_moved_points_among_the_assigned_ones():
    before = np.array([0, 0, 1, 1, -1, -1, 2, 2, 2, 2])
    assert assignment_change(before, before.copy()) == 0.0
    after = before.copy()
    after[0] = 1  # one point to another face
    after[4] = 2  # an unassigned one gets a face
    assert assignment_change(before, after) == 2 / 9
    # A face lost or gained: no share, the set of planes changed.
    assert assignment_change(before, np.where(before == 0, -1, before)) is None
    assert assignment_change(np.full(4, -1), np.full(4, -1)) == 0.0
