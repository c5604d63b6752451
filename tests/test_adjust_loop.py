"""The refine loop's stopping helpers on hand-made assignments (the loop itself runs in
test_workflow.py)."""

from __future__ import annotations

import numpy as np
import pytest

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


def test_the_faces_loop_window_keeps_a_face_standing_off_by_its_generalisation():
    """Four faces of a box fit their planes to centimetres, the fifth (a wall) stands 0.45 m
    off its plane, 2.25 of a LOD2 face's 0.2 m. The threshold follows the faces' mean
    distance down to its lower bound: 2 sigma_dTP (0.4 m) with every point alike, which cuts
    the wall's points off; with the faces' errors as unknowns a point stands off its given
    plane by its face's offset too, the bound is 2 x sqrt(0.2^2 + 0.2^2) m and the wall keeps
    them."""
    from conftest import box_store

    from colmap_citymodel.adjust.loop import window_sigma
    from colmap_citymodel.assign.schedule import assign, next_threshold
    from colmap_citymodel.options import AdjustmentOptions, AssignmentOptions

    rng = np.random.default_rng(5)
    store = box_store()
    u, v = rng.uniform(1, 9, (2, 4, 60))
    near = rng.normal(0, 0.02, (4, 60))
    points = np.concatenate([
        np.column_stack([u[0], -0.45 + rng.normal(0, 0.05, 60), v[0]]),  # y = 0 wall, off
        np.column_stack([10 + near[0], u[1], v[1]]),  # x = 10 wall
        np.column_stack([u[2], 10 + near[1], v[2]]),  # y = 10 wall
        np.column_stack([near[2], u[3], v[3]]),  # x = 0 wall
        np.column_stack([u[0], v[0], 10 + near[3]]),  # roof
    ])
    ids = np.arange(len(points))
    options = AssignmentOptions(method="direct")
    first = assign(points, ids, store, 2.0, options)
    assert np.count_nonzero(first.face_index[:60] == 0) == 60

    def wall_points_kept(adjustment: AdjustmentOptions) -> int:
        threshold = next_threshold(first, points, store, options, window_sigma(adjustment, 0.2))
        return int(np.count_nonzero(assign(points, ids, store, threshold, options)
                                    .face_index[:60] == 0))

    assert wall_points_kept(AdjustmentOptions(face_weighting="per_point")) < 30
    assert wall_points_kept(AdjustmentOptions(face_weighting="offsets")) >= 57


def moves(*steps):
    """Iteration records whose block moved by `steps` ((E, N, U) each)."""
    from colmap_citymodel.adjust.record import IterationRecord

    return [IterationRecord(i, 0.5, 0, 0, {}, 0, None, None, 0.0, block_move=tuple(s))
            for i, s in enumerate(steps)]


def test_a_creep_slowing_at_a_steady_rate_leaves_its_geometric_rest():
    """Steps 0.2 * 0.8^k along E leave 0.8 / 0.2 = 4 times the last; a creep that does not
    slow (N) leaves no bound; a swing (U, the sign changing) leaves its last step."""
    from colmap_citymodel.adjust.record import remaining_move

    steps = [(0.2 * 0.8 ** k, 0.1, 0.05 * (-1) ** k) for k in range(6)]
    rest = remaining_move(moves(*steps))
    assert rest[0] == pytest.approx(4.0 * 0.2 * 0.8 ** 5)
    assert np.isinf(rest[1])
    assert rest[2] == pytest.approx(0.05)
    # Two steps of one sign tell no rate: the last step is what is left.
    assert remaining_move(moves((0.3, 0, 0), (0.2, 0, 0)))[0] == pytest.approx(0.2)
    assert remaining_move(moves()) is None
