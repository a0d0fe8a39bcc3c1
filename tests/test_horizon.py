"""Pushes for a budget (schema.horizon): hand-solved chains and a brute-force recursion."""

import numpy as np
import pytest

from schema.horizon import (
    belief_budget_choices,
    budget_choices,
    choosable_pushes,
    csr_from_rows,
    pose_belief_q,
    values_before,
)
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
    assert choosable_pushes(np.full(3, np.nan), -1.0).all(), "at -1 every push passes, its direction unread"


# ---------------------------------------------------------------- (12.14): a budget that believes its failures


def reference_belief_budget(next_pose, v_s, power, pushes, choosable=None):
    """Backward induction over (x, fresh) and (x, failed here) with explicit loops.
    returns : Q0, Q1 for h = 1..pushes (index h - 1), per pose (A_x,) float, NaN where the row is NaN"""
    n = len(v_s)
    v0, v1 = np.array(v_s, dtype=float), np.array(v_s, dtype=float)
    q0s, q1s = [], []
    for _ in range(pushes):
        n0, n1 = np.array(v_s, dtype=float), np.array(v_s, dtype=float)
        q0h, q1h = [], []
        for x, table in enumerate(next_pose):
            a0, a1 = [], []
            for a, row in enumerate(np.asarray(table, dtype=float)):
                if np.isnan(row).any():
                    a0.append(np.nan), a1.append(np.nan)
                    continue
                p = 1.0 - row[x]
                leave = sum(row[y] * v0[y] for y in range(n) if y != x)
                a0.append(leave + (1 - p) * v1[x])
                a1.append((p ** (power - 1) * leave if p > 0 else 0.0) + (1 - p ** power) * v1[x])
                if choosable is None or choosable[x][a]:
                    n0[x], n1[x] = max(n0[x], a0[-1]), max(n1[x], a1[-1])
            q0h.append(np.array(a0)), q1h.append(np.array(a1))
        v0, v1 = n0, n1
        q0s.append(q0h), q1s.append(q1h)
    return q0s, q1s


def belief_budget(next_pose, v_s, power, pushes, choosable=None):
    """``belief_budget_choices`` and, per budget and pose, ``pose_belief_q`` from the values it solved:
    actions (H, P), V0 (H, P), V1 (H, P), and Q0, Q1 as ``reference_belief_budget``."""
    action_offsets, transition_offsets, targets, probability = csr = csr_from_rows(next_pose)
    mask = None if choosable is None else np.concatenate([np.zeros(0, dtype=bool), *choosable])
    actions, fresh, failed = belief_budget_choices(v_s, *csr, pushes, power, mask)
    q0s, q1s = [], []
    for h in range(1, pushes + 1):
        before = values_before(v_s, fresh, failed, h)
        qs = [pose_belief_q(*before, x, slice(int(action_offsets[x]), int(action_offsets[x + 1])), transition_offsets, targets,
                            probability, power) for x in range(len(v_s))]
        q0s.append([q[0] for q in qs]), q1s.append([q[1] for q in qs])
    return actions, fresh, failed, q0s, q1s


def test_belief_budget_matches_backward_induction_and_is_the_budget_at_power_one():
    from tests.test_mdp import random_mdp

    rng = np.random.default_rng(6)
    for n_poses, n_actions in [(2, 4), (5, 15)]:
        next_pose, v_s = random_mdp(rng, n_poses, n_actions)
        choosable = [rng.random(len(t)) < 0.8 for t in next_pose]
        actions, fresh, failed, q0s, q1s = belief_budget(next_pose, v_s, 2.1, 3, choosable)
        r0s, r1s = reference_belief_budget(next_pose, v_s, 2.1, 3, choosable)
        for h in range(3):
            for x in range(n_poses):
                np.testing.assert_allclose(q0s[h][x], r0s[h][x], atol=1e-12)
                np.testing.assert_allclose(q1s[h][x], r1s[h][x], atol=1e-12)
                for q, chosen, value in ((q0s[h][x], actions[h, x], fresh[h, x]), (q1s[h][x], None, failed[h, x])):
                    allowed = np.where(choosable[x], q, np.nan)
                    finite = np.isfinite(allowed).any() and np.nanmax(allowed) > v_s[x] + 1e-9
                    assert value == pytest.approx(np.nanmax(allowed) if finite else v_s[x], abs=1e-12)
                    if chosen is not None:
                        assert chosen == (int(np.nanargmax(allowed)) if finite else NO_OP), (h, x)
        # k = 1 believes nothing: the budget's own choices and values, failed or not.
        actions, fresh, failed, _, _ = belief_budget(next_pose, v_s, 1.0, 3, choosable)
        mask = np.concatenate([np.zeros(0, dtype=bool), *choosable])
        plain_actions, plain_values = budget_choices(v_s, *csr_from_rows(next_pose), 3, mask)
        np.testing.assert_array_equal(actions, plain_actions)
        np.testing.assert_allclose(fresh, plain_values, atol=1e-12)
        np.testing.assert_allclose(failed, plain_values, atol=1e-12)


def test_belief_budget_with_one_push_left_takes_the_likely_push_after_a_failure():
    # One push left: fresh, the long shot is worth 0.1 + 0.9 * 0.2 = 0.28 and the likely push
    # 0.45 + 0.1 * 0.2 = 0.47; after a failure 0.1^1.1 * 0.1 + (1 - 0.1^2.1) * 0.2 = 0.206 against
    # 0.9^1.1 * 0.45 + (1 - 0.9^2.1) * 0.2 = 0.441.  Two left: the long shot first is worth
    # 0.1 + 0.9 * 0.441 = 0.497, the likely push 0.45 + 0.1 * 0.441 = 0.494.
    from tests.test_mdp import long_shot_and_likely_push

    next_pose, v_s = long_shot_and_likely_push()
    actions, fresh, failed, q0s, q1s = belief_budget(next_pose, v_s, 2.1, 2)
    likely = 0.9 ** 1.1 * 0.45 + (1 - 0.9 ** 2.1) * 0.2
    np.testing.assert_allclose(q0s[0][0], [0.28, 0.47])
    np.testing.assert_allclose(q1s[0][0], [0.1 ** 1.1 * 0.1 + (1 - 0.1 ** 2.1) * 0.2, likely])
    np.testing.assert_allclose(q0s[1][0], [0.1 + 0.9 * likely, 0.45 + 0.1 * likely])
    assert list(actions[:, 0]) == [1, 0]  # the likely push with one left; the long shot first with two
    assert failed[0, 0] == pytest.approx(likely) and fresh[1, 0] == pytest.approx(0.1 + 0.9 * likely)
    # The thesis's budget (k = 1) takes the long shot with two left too, but values it at the fresh retry.
    plain, values = budget_choices(v_s, *csr_from_rows(next_pose), 2)
    assert plain[1, 0] == 0 and values[1, 0] == pytest.approx(0.1 + 0.9 * 0.47)
    with pytest.raises(ValueError, match="power >= 1"):
        belief_budget_choices(v_s, *csr_from_rows(next_pose), 2, 0.9)
    _, transition_offsets, targets, probability = csr_from_rows(next_pose)
    with pytest.raises(ValueError, match="power >= 1"):
        pose_belief_q(v_s, v_s, 0, slice(0, 2), transition_offsets, targets, probability, 0.9)
    for bad in (0, 3):
        with pytest.raises(ValueError, match="pushes_left must be 1..2"):
            values_before(v_s, fresh, failed, bad)


def test_pose_belief_q_is_the_solve_s_own_numbers_in_float32():
    # The service stores float32 probabilities: the per-pose Q1 it ranks by after a failure must be
    # the very numbers the solve maximised, so the V1 it reports is the Q1 of the push it chooses.
    from tests.test_mdp import random_mdp

    next_pose, v_s = random_mdp(np.random.default_rng(11), 5, 20)
    action_offsets, transition_offsets, targets, probability = csr_from_rows(next_pose)
    probability = probability.astype(np.float32)
    actions, fresh, failed = belief_budget_choices(v_s, action_offsets, transition_offsets, targets, probability, 3, 2.1)
    for x in range(5):
        rows = slice(int(action_offsets[x]), int(action_offsets[x + 1]))
        q0, q1 = pose_belief_q(fresh[1], failed[1], x, rows, transition_offsets, targets, probability, 2.1)
        if actions[2, x] != NO_OP:
            assert q0[actions[2, x]] == fresh[2, x]  # bit for bit
        if np.isfinite(q1).any() and np.nanmax(q1) > v_s[x] + 1e-9:
            assert np.nanmax(q1) == failed[2, x]


def test_the_belief_budget_renormalises_rows_and_keeps_rows_with_one_outcome():
    # Stored probabilities are float32 rows that sum to 1 only within rounding: the solve
    # renormalises each row and computes in float64, so twice the row, or its float32 copy
    # widened, is the same problem to the bit.  A sure push (one outcome) is a push like any other.
    next_pose = [np.array([[0.0, 1.0, 0.0], [0.6, 0.0, 0.4], [1.0, 0.0, 0.0]]), np.zeros((0, 3)),
                 np.array([[0.0, 0.2, 0.8], [np.nan] * 3])]
    v_s = np.array([0.1, 0.9, 0.3])
    action_offsets, transition_offsets, targets, probability = csr_from_rows(next_pose)
    solved = belief_budget_choices(v_s, action_offsets, transition_offsets, targets, probability, 3, 2.1)
    doubled = belief_budget_choices(v_s, action_offsets, transition_offsets, targets, 2.0 * probability, 3, 2.1)
    for a, b in zip(solved, doubled):
        np.testing.assert_array_equal(a, b)
    single = probability.astype(np.float32)
    widened = belief_budget_choices(v_s, action_offsets, transition_offsets, targets, single.astype(np.float64), 3, 2.1)
    for a, b in zip(belief_budget_choices(v_s, action_offsets, transition_offsets, targets, single, 3, 2.1), widened):
        np.testing.assert_array_equal(a, b)
    q0, q1 = pose_belief_q(v_s, v_s, 0, slice(0, 3), transition_offsets, targets, probability, 2.1)
    assert q0[0] == pytest.approx(0.9) and q1[0] == pytest.approx(0.9), "the sure topple onto pose 1"
    assert q0[2] == pytest.approx(0.1) and q1[2] == pytest.approx(0.1), "the push that never topples is worth staying"
    assert solved[0][0, 0] == 0 and solved[0][0, 2] == 0 and solved[1][0, 2] == pytest.approx(0.2 * 0.9 + 0.8 * 0.3)


def test_a_push_must_beat_grasping_now_by_more_than_the_margin():
    from schema.horizon import IMPROVEMENT, _best_per_pose

    offsets = np.array([0, 2])
    assert _best_per_pose(np.array([IMPROVEMENT, -np.inf]), np.array([0.0]), offsets)[0][0] == NO_OP
    actions, values = _best_per_pose(np.array([IMPROVEMENT, 2 * IMPROVEMENT]), np.array([0.0]), offsets)
    assert actions[0] == 1 and values[0] == 2 * IMPROVEMENT


def test_budget_q_is_the_solve_s_own_numbers_with_or_without_belief():
    # After a failure the service ranks a pose's pushes by budget_q: (12.8)'s Q_h (pose_q), which a
    # failure does not change, in a build that does not believe failures; Q0_h fresh and Q1_h failed
    # in one that does.  The push it serves must be valued as the solve valued it, to the bit, from
    # float32 probabilities that sum to 1 only within rounding; a push that is not ok has no value
    # (NaN), and a sure push (one outcome) has one.
    from schema.horizon import IMPROVEMENT, budget_q
    from tests.test_mdp import random_mdp

    next_pose, v_s = random_mdp(np.random.default_rng(12), 5, 12)
    next_pose[0][0] = [0.0, 0.0, 0.0, 1.0, 0.0]  # a sure push onto pose 3
    action_offsets, transition_offsets, targets, probability = csr_from_rows(next_pose)
    probability = (1.5 * probability).astype(np.float32)
    csr = (transition_offsets, targets, probability)
    plain, values = budget_choices(v_s, action_offsets, *csr, 3)
    actions, fresh, failed = belief_budget_choices(v_s, action_offsets, *csr, 3, 2.1)
    for h in range(1, 4):
        for x in range(5):
            rows = slice(int(action_offsets[x]), int(action_offsets[x + 1]))
            ok = np.diff(transition_offsets[rows.start : rows.stop + 1]) > 0
            q = budget_q(v_s, values, values, h, x, rows, *csr, None, False)
            assert q.dtype == np.float64 and np.array_equal(np.isnan(q), ~ok), (h, x)
            np.testing.assert_array_equal(budget_q(v_s, values, values, h, x, rows, *csr, None, True), q)
            q0 = budget_q(v_s, fresh, failed, h, x, rows, *csr, 2.1, False)
            q1 = budget_q(v_s, fresh, failed, h, x, rows, *csr, 2.1, True)
            for solved, chosen, value in ((q, plain, values), (q0, actions, fresh)):
                if chosen[h - 1, x] != NO_OP:
                    assert solved[chosen[h - 1, x]] == value[h - 1, x], (h, x)  # bit for bit
                else:
                    assert not ok.any() or np.nanmax(solved) <= v_s[x] + IMPROVEMENT
            best = np.nanmax(q1) if ok.any() else -np.inf
            assert failed[h - 1, x] == (best if best > v_s[x] + IMPROVEMENT else v_s[x]), (h, x)
    first = budget_q(v_s, values, values, 1, 0, slice(0, 12), *csr, None, False)
    assert first[0] == v_s[3], "the sure push is worth its pose's V_s with one push left"


def test_a_push_within_the_margin_of_a_float32_v_s_is_not_chosen():
    # V_s read as float32 must be compared in float64: a push that reaches a pose one float32 step
    # better a hundredth of the time gains 6e-10, less than the margin, so grasping now stays best.
    v_s = np.array([0.5, np.nextafter(np.float32(0.5), np.float32(1.0))], dtype=np.float32)
    rows = [np.array([[0.99, 0.01]]), np.zeros((0, 2))]
    actions, values = budget_choices(v_s, *csr_from_rows(rows), 2)
    assert (actions == NO_OP).all() and values[1, 0] == 0.5
    believing, fresh, _ = belief_budget_choices(v_s, *csr_from_rows(rows), 2, 2.1)
    assert (believing == NO_OP).all() and fresh[1, 0] == 0.5


def test_a_float64_direction_that_rounds_onto_the_limit_is_choosable():
    # The dataset job holds float64 directions and the service float32 ones: one just below the
    # float32 limit in float64 is the limit in float32, so both must call it choosable.
    limit = np.float32(-0.3)
    below = float(limit) - 1e-10
    assert below < float(limit) and np.float32(below) == limit
    assert choosable_pushes(np.array([below]), -0.3)[0]


def test_csr_from_rows_of_no_poses_and_of_a_partly_nan_row():
    action_offsets, transition_offsets, targets, probability = csr_from_rows([])
    assert action_offsets.tolist() == [0] and transition_offsets.tolist() == [0] and len(targets) == len(probability) == 0
    _, transition_offsets, targets, _ = csr_from_rows([np.array([[np.nan, 0.5, 0.5], [0.5, 0.5, 0.0]])])
    assert transition_offsets.tolist() == [0, 0, 2] and targets.tolist() == [0, 1], "any NaN: a push that is not ok"
