"""Pushes for a budget (schema.horizon): hand-solved chains and a brute-force recursion."""

import numpy as np
import pytest

from schema.horizon import budget_choices, choosable_pushes, csr_from_rows
from schema.vocabulary import NO_OP


def choose(v_s, next_pose, budget):
    # float32, as the service stores them
    action_offsets, transition_offsets, targets, probability = csr_from_rows(next_pose)
    return budget_choices(v_s, action_offsets, transition_offsets, targets, probability.astype(np.float32), budget)


def test_csr_from_rows_keeps_the_nonzero_entries_row_by_row():
    rows = [np.array([[0.25, 0.0, 0.75], [np.nan, np.nan, np.nan]]), np.zeros((0, 3)), np.array([[0.0, 1.0, 0.0]])]
    action_offsets, transition_offsets, targets, probability = csr_from_rows(rows)
    np.testing.assert_array_equal(action_offsets, [0, 2, 2, 3])
    np.testing.assert_array_equal(transition_offsets, [0, 2, 2, 3])  # the NaN row: no transitions (not ok)
    np.testing.assert_array_equal(targets, [0, 2, 1])
    np.testing.assert_array_equal(probability, [0.25, 0.75, 1.0])


def test_one_sure_push_beats_a_long_shot_on_a_small_budget_only():
    # Pose 0 (V_s 0): a long shot to pose 2 (V_s 1) with probability 0.3, else it stays; or a
    # sure push to pose 1 (V_s 0.35), from which nothing helps.
    v_s = np.array([0.0, 0.35, 1.0])
    next_pose = [np.array([[0.7, 0.0, 0.3], [0.0, 1.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]), np.array([[0.0, 0.0, 1.0]])]
    actions, values = choose(v_s, next_pose, 10)
    assert actions[0, 0] == 1 and values[0, 0] == pytest.approx(0.35)  # one push left: the sure 0.35 > 0.3
    # Two left: the long shot, then the sure push if it failed: 0.3 + 0.7 x 0.35.
    assert actions[1, 0] == 0 and values[1, 0] == pytest.approx(0.3 + 0.7 * 0.35)
    # h left: 1 - 0.7^(h-1) x (1 - 0.35) ... the long shot every time but the last.
    for h in range(2, 11):
        assert actions[h - 1, 0] == 0
        assert values[h - 1, 0] == pytest.approx(1 - 0.7 ** (h - 1) * (1 - 0.35), abs=1e-6)
    assert (actions[:, 1] == NO_OP).all() and (actions[:, 2] == NO_OP).all()
    assert np.allclose(values[:, 1:], [0.35, 1.0])


def test_a_push_that_only_shuffles_between_equal_poses_is_not_chosen():
    # float32 probabilities that sum to 1 only within rounding must not make a useless push look better.
    v_s = np.array([0.5, 0.5])
    next_pose = [np.array([[0.3, 0.7], [0.1, 0.9]]), np.array([[0.6, 0.4]])]
    actions, values = choose(v_s, next_pose, 3)
    assert (actions == NO_OP).all() and np.allclose(values, 0.5)


def brute_force(v_s, next_pose, budget):
    """The recursion on dense matrices, pose by pose."""
    value = v_s.copy()
    out = []
    for _ in range(budget):
        best = v_s.copy()
        for x, m in enumerate(next_pose):
            q = np.where(np.isnan(m).any(axis=1), -np.inf, np.nan_to_num(m) @ value)
            if len(q) and q.max() > v_s[x] + 1e-9:
                best[x] = q.max()
        out.append(best)
        value = best
    return np.array(out)


@pytest.mark.parametrize("seed", range(5))
def test_values_agree_with_the_recursion_and_one_push_left_is_greedy(seed):
    rng = np.random.default_rng(seed)
    n = 5
    v_s = rng.random(n)
    next_pose = []
    for _ in range(n):
        m = rng.dirichlet(np.full(n, 0.3), size=int(rng.integers(0, 8)))
        m[rng.random(len(m)) < 0.3] = np.nan
        next_pose.append(m)
    actions, values = choose(v_s, next_pose, 6)
    assert np.allclose(values, brute_force(v_s, [m.astype(np.float32).astype(float) for m in next_pose], 6), atol=1e-6)
    assert (np.diff(values, axis=0) >= -1e-12).all(), "a bigger budget is never worth less"
    for x, m in enumerate(next_pose):
        greedy = np.where(np.isnan(m).any(axis=1), -np.inf, np.nan_to_num(m) @ v_s)
        if actions[0, x] == NO_OP:
            assert not len(greedy) or greedy.max() <= v_s[x] + 1e-6
        else:
            assert greedy[actions[0, x]] == pytest.approx(greedy.max(), abs=1e-6)


def test_a_budget_chooses_among_the_choosable_pushes_only():
    # Pose 0: push 0 reaches pose 1 surely, push 1 half the time; push 0 may not be chosen.
    rows = [np.array([[0.0, 1.0], [0.5, 0.5]]), np.array([[0.0, 1.0]])]
    v_s = np.array([0.1, 0.9])
    actions, values = budget_choices(v_s, *csr_from_rows(rows), 2)
    assert actions[0, 0] == 0
    actions, values = budget_choices(v_s, *csr_from_rows(rows), 2, np.array([False, True, True]))
    assert actions[0, 0] == actions[1, 0] == 1
    np.testing.assert_allclose(values[:, 0], [0.5, 0.5 * 0.5 + 0.45])
    nothing, _ = budget_choices(v_s, *csr_from_rows(rows), 1, np.zeros(3, dtype=bool))
    assert nothing[0, 0] == NO_OP


def test_choosable_pushes_compare_as_the_served_float32_directions():
    z = np.array([-1.0, -0.31, -0.3, np.float32(-0.3), -0.29, 1.0])
    np.testing.assert_array_equal(choosable_pushes(z, -0.3), [False, False, True, True, True, True])
    # A float64 just below -0.3 rounds to float32 -0.3, as the service reads it: choosable there, so here.
    assert choosable_pushes(np.array([-0.3 - 1e-9]), -0.3)[0]
    assert choosable_pushes(np.array([-1.0]), -1.0)[0]
