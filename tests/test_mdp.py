"""Value iteration, greedy values, the three policies and the object selection rule
(pipeline/mdp.py) on hand-built MDPs with known solutions."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from pipeline.model.config import MDPConfig
from pipeline.model.mdp import (
    IMPROVEMENT,
    belief_value_iteration,
    greedy_policy,
    greedy_values,
    is_selected,
    max_height_policy,
    pose_values,
    repeat_value_iteration,
    value_iteration,
    value_iteration_policy,
)
from schema.vocabulary import NO_OP

GAMMA = 0.95
NAN_ROW = [np.nan] * 3


def solve(next_pose, v_s, gamma=GAMMA, tolerance=1e-12, max_iterations=10_000, retry_failed=True):
    return value_iteration([np.asarray(t, dtype=float) for t in next_pose], np.asarray(v_s, float), gamma, tolerance, max_iterations,
                           retry_failed=retry_failed)


def reference_values(next_pose, v_s, gamma, sweeps=800, retry_failed=True):
    """Textbook value iteration with explicit loops, for comparison; without retries the
    pose's own entry of each row is worth its grasp, V_s(x) (MODEL.md (12.9))."""
    value = np.array(v_s, dtype=float)
    for _ in range(sweeps):
        new = value.copy()
        for x, table in enumerate(next_pose):
            after = value.copy()
            if not retry_failed:
                after[x] = v_s[x]
            for row in np.asarray(table, dtype=float):
                if not np.isnan(row).any():
                    new[x] = max(new[x], gamma * float(row @ after))
        new = np.maximum(new, v_s)
        value = new
    return value


def random_mdp(rng, n_poses, n_actions):
    tables = []
    for _ in range(n_poses):
        rows = rng.dirichlet(np.full(n_poses, 0.3), n_actions)
        rows[rng.random(n_actions) < 0.3] = np.nan
        tables.append(rows)
    if n_poses > 2:
        tables[1] = np.full((n_actions, n_poses), np.nan)  # a pose whose pushes are all infeasible
        tables[2] = np.zeros((0, n_poses))  # a pose with no candidate pushes at all
    return tables, rng.random(n_poses)


def figure_4_6():
    """Thesis figure 4.6: every pose reachable from pose 0 is as poor as pose 0, but
    one of them topples on to a pose with a perfect grasp.

    pose 0 (V_s 0.4): u0 stays, u1 -> pose 1, u2 -> pose 3 or stays
    pose 1 (V_s 0.4): u0 -> pose 2 with 0.9, stays with 0.1
    pose 2 (V_s 1.0): no pushes
    pose 3 (V_s 0.4): u0 stays
    """
    v_s = np.array([0.4, 0.4, 1.0, 0.4])
    next_pose = [
        np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0.5, 0, 0, 0.5]], dtype=float),
        np.array([[0, 0.1, 0.9, 0]], dtype=float),
        np.zeros((0, 4)),
        np.array([[0, 0, 0, 1]], dtype=float),
    ]
    return next_pose, v_s


def long_shot():
    """Pose 0 (V_s 0.2): a long shot, 0.3 onto pose 1 (V_s 1.0), else stays; a safer push, 0.9
    onto pose 2 (V_s 0.5), else stays.  Retried without end the long shot is worth
    V0 = 0.3 gamma / (1 - 0.7 gamma) = 0.851 and value iteration takes it; pushed once, it is
    worth 0.3 + 0.7 * 0.2 = 0.44 against the safer push's 0.9 * 0.5 + 0.1 * 0.2 = 0.47 (MODEL.md (12.9)).
    """
    next_pose = [np.array([[0.7, 0.3, 0.0], [0.1, 0.0, 0.9]]), np.zeros((0, 3)), np.zeros((0, 3))]
    return next_pose, np.array([0.2, 1.0, 0.5])


# ----------------------------------------------------------------------------- value iteration


def test_one_topple_to_a_better_pose():
    v, q = solve([[[0.0, 1.0]], np.zeros((0, 2))], [0.2, 0.9])
    np.testing.assert_allclose(v, [GAMMA * 0.9, 0.9])
    np.testing.assert_allclose(q[0], [0.9])
    assert q[1].shape == (0,)


def test_push_that_rarely_topples_has_the_geometric_series_value():
    # V0 = gamma (0.9 V0 + 0.1 * 1)  =>  V0 = 0.1 gamma / (1 - 0.9 gamma)
    v, q = solve([[[0.9, 0.1]], np.zeros((0, 2))], [0.0, 1.0])
    expected = 0.1 * GAMMA / (1 - 0.9 * GAMMA)
    np.testing.assert_allclose(v, [expected, 1.0], atol=1e-12)
    np.testing.assert_allclose(q[0], [0.9 * expected + 0.1], atol=1e-12)


def test_without_retries_a_failed_push_is_worth_the_grasp_where_it_failed():
    next_pose, v_s = long_shot()
    v, q = solve(next_pose, v_s)
    v0 = 0.3 * GAMMA / (1 - 0.7 * GAMMA)
    np.testing.assert_allclose(v, [v0, 1.0, 0.5], atol=1e-12)
    assert value_iteration_policy(0, v_s, q[0], GAMMA).action == 0
    v, q = solve(next_pose, v_s, retry_failed=False)
    np.testing.assert_allclose(q[0], [0.44, 0.47], atol=1e-12)
    np.testing.assert_allclose(v, [GAMMA * 0.47, 1.0, 0.5], atol=1e-12)
    assert value_iteration_policy(0, v_s, q[0], GAMMA).action == 1


def test_without_retries_a_push_that_never_topples_is_worth_grasping_now():
    # With retries, V0 = gamma (0.9 V0 + 0.1) (the geometric series above); without, one try.
    v, q = solve([[[0.9, 0.1]], np.zeros((0, 2))], [0.0, 1.0], retry_failed=False)
    np.testing.assert_allclose(q[0], [0.1], atol=1e-12)
    np.testing.assert_allclose(v, [0.1 * GAMMA, 1.0], atol=1e-12)
    v, q = solve([[[1.0, 0.0]], np.zeros((0, 2))], [0.3, 1.0], retry_failed=False)
    np.testing.assert_allclose(v, [0.3, 1.0])
    assert value_iteration_policy(0, np.array([0.3, 1.0]), q[0], GAMMA).action == NO_OP


def test_without_retries_the_policy_evaluation_still_lands_on_the_fixed_point_at_once():
    # A loop of pushes that rarely topple: 0 -> 1 half the time, 1 -> 2 (the perfect grasp) one
    # time in five or back to 0.  Each sweep's exact evaluation of its greedy policy (12.5), with
    # a failed push's mass at V_s, makes two sweeps enough where plain sweeps would still be rising.
    next_pose = [np.array([[0.5, 0.5, 0.0]]), np.array([[0.3, 0.5, 0.2]]), np.zeros((0, 3))]
    v_s = np.array([0.0, 0.1, 1.0])
    exact = reference_values(next_pose, v_s, GAMMA, retry_failed=False)
    v, _ = solve(next_pose, v_s, max_iterations=2, retry_failed=False)
    np.testing.assert_allclose(v, exact, atol=1e-12)


def test_value_iteration_counts_on_retries_by_default():
    # The thesis's retries are the default of value_iteration itself, as of MDPConfig.
    next_pose, v_s = long_shot()
    default, _ = value_iteration(next_pose, v_s, GAMMA, 1e-12, 10_000)
    np.testing.assert_allclose(default, solve(next_pose, v_s, retry_failed=True)[0], atol=0)
    assert MDPConfig().retry_failed


def test_without_retries_matches_textbook_value_iteration_and_a_chain_still_pays():
    rng = np.random.default_rng(3)
    for n_poses, n_actions in [(2, 3), (5, 20), (8, 50)]:
        next_pose, v_s = random_mdp(rng, n_poses, n_actions)
        v, q = solve(next_pose, v_s, retry_failed=False)
        np.testing.assert_allclose(v, reference_values(next_pose, v_s, GAMMA, retry_failed=False), atol=1e-10)
        retried, _ = solve(next_pose, v_s)
        assert np.all(v >= v_s) and np.all(v <= retried + 1e-12)  # retries can only add value
        for x, (table, qx) in enumerate(zip(next_pose, q)):
            after = v.copy()
            after[x] = v_s[x]
            np.testing.assert_allclose(qx, table @ after, atol=1e-12)
    # Pushes that topple for sure are not retries: a chain keeps gamma^k.
    v, _ = solve([[[0, 1, 0]], [[0, 0, 1]], np.zeros((0, 3))], [0.0, 0.0, 1.0], retry_failed=False)
    np.testing.assert_allclose(v, [GAMMA**2, GAMMA, 1.0], atol=1e-12)


def test_figure_4_6_values():
    next_pose, v_s = figure_4_6()
    v, q = solve(next_pose, v_s)
    # pose 1: V = gamma (0.1 V1 + 0.9)  =>  V1 = 0.9 gamma / (1 - 0.1 gamma)
    v1 = 0.9 * GAMMA / (1 - 0.1 * GAMMA)
    np.testing.assert_allclose(v, [GAMMA * v1, v1, 1.0, 0.4], atol=1e-12)
    np.testing.assert_allclose(q[0], [GAMMA * v1, v1, 0.5 * GAMMA * v1 + 0.5 * 0.4], atol=1e-12)


def test_gamma_discounts_each_topple():
    # A chain 0 -> 1 -> 2 with a perfect grasp only at the end: V_T(0) = gamma^2.
    chain = [[[0, 1, 0]], [[0, 0, 1]], np.zeros((0, 3))]
    for gamma in (0.5, 0.8, 0.95):
        v, _ = solve(chain, [0.0, 0.0, 1.0], gamma=gamma)
        np.testing.assert_allclose(v, [gamma**2, gamma, 1.0], atol=1e-12)
    # Discounting can make grasping now better than a long detour.
    v, _ = solve(chain, [0.6, 0.0, 1.0], gamma=0.7)
    assert v[0] == pytest.approx(0.6)


def test_matches_textbook_value_iteration_on_random_mdps():
    rng = np.random.default_rng(0)
    for n_poses, n_actions in [(2, 3), (5, 20), (8, 50)]:
        next_pose, v_s = random_mdp(rng, n_poses, n_actions)
        v, q = solve(next_pose, v_s)
        np.testing.assert_allclose(v, reference_values(next_pose, v_s, GAMMA), atol=1e-10)
        for table, qx in zip(next_pose, q):
            np.testing.assert_allclose(qx, table @ v, atol=1e-12)  # NaN where the row is NaN


def test_values_are_bounded_by_the_grasp_qualities():
    rng = np.random.default_rng(1)
    for _ in range(20):
        next_pose, v_s = random_mdp(rng, int(rng.integers(1, 9)), int(rng.integers(0, 30)))
        v, _ = solve(next_pose, v_s)
        assert np.all(v >= v_s)
        assert np.all(v <= v_s.max() + 1e-12)


def test_tolerance_bounds_the_bellman_residual():
    rng = np.random.default_rng(2)
    next_pose, v_s = random_mdp(rng, 6, 40)
    exact, _ = solve(next_pose, v_s, tolerance=0.0, max_iterations=200)
    for tolerance in (1e-2, 1e-6, 1e-12):
        v, q = solve(next_pose, v_s, tolerance=tolerance)
        best = np.array([np.nanmax(qx) if np.isfinite(qx).any() else -np.inf for qx in q])
        residual = np.abs(np.maximum(v_s, GAMMA * best) - v)
        assert residual.max() <= tolerance
        assert np.all(v <= exact + 1e-12)
        assert np.abs(v - exact).max() <= tolerance * GAMMA / (1 - GAMMA) + 1e-12


def test_max_iterations_bounds_the_sweeps():
    next_pose, v_s = figure_4_6()
    v, q = solve(next_pose, v_s, max_iterations=0)
    np.testing.assert_array_equal(v, v_s)
    np.testing.assert_allclose(q[0], next_pose[0] @ v_s)


def test_no_sweeps_return_the_grasp_values_as_floats():
    # max_iterations 0 returns V_s as V_T, and as V0 believing failures: floats (the (P,) float the
    # docstrings promise) whatever V_s came as, integers here, as after any number of sweeps.
    next_pose, _ = figure_4_6()
    v_s = np.array([0, 0, 1, 0])
    v, _ = value_iteration(next_pose, v_s, GAMMA, 1e-12, 0)
    v0, v1, _, _ = belief_value_iteration(next_pose, v_s, GAMMA, 2.1, 1e-12, 0)
    for values in (v, v0, v1):
        assert values.dtype == np.float64
    np.testing.assert_array_equal(v, [0.0, 0.0, 1.0, 0.0])
    np.testing.assert_array_equal(v0, [0.0, 0.0, 1.0, 0.0])


def test_nan_rows_are_ignored():
    base = [[[0.5, 0.5, 0.0]], [[0.0, 0.0, 1.0]], np.zeros((0, 3))]
    v_s = [0.1, 0.2, 0.8]
    with_nan = [
        # A NaN row that would be worth a lot if it were read, and a partly NaN row.
        [[0.5, 0.5, 0.0], NAN_ROW, [0.0, np.nan, 1.0]],
        [NAN_ROW, [0.0, 0.0, 1.0]],
        np.full((2, 3), np.nan),
    ]
    v, _ = solve(base, v_s)
    v_nan, q_nan = solve(with_nan, v_s)
    np.testing.assert_allclose(v_nan, v)
    assert np.isnan(q_nan[0][1:]).all() and np.isfinite(q_nan[0][0])
    assert np.isnan(q_nan[1][0]) and np.isfinite(q_nan[1][1])
    assert np.isnan(q_nan[2]).all()


def test_rarely_toppling_pushes_converge_in_a_few_sweeps():
    # Plain value iteration contracts by 0.99 gamma per sweep here (hundreds of sweeps to 1e-12);
    # evaluating each sweep's greedy policy exactly lands on the fixed point within a few.
    one = [[[0.99, 0.01]], np.zeros((0, 2))]
    v, _ = solve(one, [0.0, 1.0], max_iterations=3)
    np.testing.assert_allclose(v, [0.01 * GAMMA / (1 - 0.99 * GAMMA), 1.0], atol=1e-12)
    # A chain 0 -> 1 -> 2 where pose 1 can also fall back to 0: two poses act, coupled.
    chain = [[[0.95, 0.05, 0.0]], [[0.05, 0.9, 0.05]], np.zeros((0, 3))]
    v_s = [0.0, 0.1, 1.0]
    exact, _ = solve(chain, v_s, tolerance=0.0, max_iterations=10_000)
    fast, _ = solve(chain, v_s, max_iterations=4)
    np.testing.assert_allclose(fast, exact, atol=1e-12)
    np.testing.assert_allclose(exact, reference_values(chain, v_s, GAMMA, sweeps=2000), atol=1e-10)


def sure_chain():
    """A chain of sure topples 0 -> 1 -> 2, a perfect grasp only at its end (V_s 0, 0, 1)."""
    return [np.array([[0.0, 1.0, 0.0]]), np.array([[0.0, 0.0, 1.0]]), np.zeros((0, 3))], np.array([0.0, 0.0, 1.0])


def test_a_sweep_that_moves_no_value_by_more_than_the_tolerance_is_the_last():
    # The stopping rule of both solvers at its boundary, with gamma 0.5 (every number exact): the first
    # sweep from V_s raises V(1) to 0.5 and leaves V(0) at 0, as pose 1 was worth nothing when pose 0
    # looked at it.  A change of exactly the tolerance is no more than it: that sweep is returned as it
    # stands, short of the fixed point (0.25, 0.5, 1) by 0.25, within tolerance * gamma / (1 - gamma).
    # A tolerance below 0.5 takes the next sweep, which changes V(0) by 0.25 and lands on the fixed point.
    chain, v_s = sure_chain()
    v, q = value_iteration(chain, v_s, 0.5, 0.5, 100)
    np.testing.assert_array_equal(v, [0.0, 0.5, 1.0])
    np.testing.assert_array_equal(q[0], [0.5])  # Q_T under the V returned
    v, _ = value_iteration(chain, v_s, 0.5, 0.4, 100)
    np.testing.assert_array_equal(v, [0.25, 0.5, 1.0])
    # Believing failures (12.13), where sweeps iterate V0 over the topples between poses, the same.
    v0, _, _, _ = belief_value_iteration(chain, v_s, 0.5, 2.1, 0.5, 100)
    np.testing.assert_array_equal(v0, [0.0, 0.5, 1.0])
    v0, _, _, _ = belief_value_iteration(chain, v_s, 0.5, 2.1, 0.4, 100)
    np.testing.assert_array_equal(v0, [0.25, 0.5, 1.0])


def test_the_exact_evaluation_pushes_only_where_a_push_beats_grasping():
    # Each sweep evaluates "push where gamma Q_T > V_s, else grasp" (the policy rule); a pose that
    # would do worse pushing, or only as well, must grasp in it, or the evaluation says too little.
    # Pose 0 (V_s 0) rarely topples, onto pose 1 (V_s 0.9), whose one push lands on pose 2 (V_s 0.2):
    # pose 1 grasps, so V_T(0) = 0.01 gamma 0.9 / (1 - 0.99 gamma) after the first sweep's evaluation.
    # Had pose 1 pushed there, the evaluation would be worth less than the Bellman update and three
    # sweeps would leave V_T(0) at a fraction of that.
    next_pose = [np.array([[0.99, 0.01, 0.0]]), np.array([[0.0, 0.0, 1.0]]), np.zeros((0, 3))]
    v, _ = solve(next_pose, [0.0, 0.9, 0.2], max_iterations=3)
    np.testing.assert_allclose(v, [0.01 * GAMMA * 0.9 / (1 - 0.99 * GAMMA), 0.9, 0.2], atol=1e-12)
    # Undiscounted, pose 0 (V_s 0.5) has only a push that leaves it there: pushing ties grasping, and
    # a tie grasps.  (Pushing it would make the evaluation's system singular, and pose 1, which rarely
    # topples onto the perfect pose 2, would creep up by plain sweeps instead of being worth 1 at once.)
    next_pose = [np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 0.99, 0.01]]), np.zeros((0, 3))]
    v, _ = solve(next_pose, [0.5, 0.0, 1.0], gamma=1.0, max_iterations=3)
    np.testing.assert_allclose(v, [0.5, 1.0, 1.0], atol=1e-9)


def test_float32_inputs_are_solved_in_float64():
    # The service stores its tables in float32.  The solvers read tables and V_s as float64, so
    # float32 inputs give, to the bit, what the same numbers widened to float64 give (in float32 a
    # policy evaluation's gamma T and a failed push's 1 - P(x | x, u) would round).  Two sweeps
    # stop before later sweeps could wash such rounding out; 10,000 run to the tolerance.
    tables = [np.array([[0.95, 0.05, 0.0], [0.1, 0.0, 0.9]]), np.array([[0.05, 0.9, 0.05]]), np.zeros((0, 3))]
    narrow = [t.astype(np.float32) for t in tables]
    wide = [t.astype(float) for t in narrow]
    v_s32 = np.array([0.1, 0.3, 1.0], dtype=np.float32)
    v_s64 = v_s32.astype(float)
    for max_iterations in (2, 10_000):
        for retry_failed in (True, False):
            v, q = value_iteration(narrow, v_s32, GAMMA, 1e-12, max_iterations, retry_failed=retry_failed)
            v_wide, q_wide = value_iteration(wide, v_s64, GAMMA, 1e-12, max_iterations, retry_failed=retry_failed)
            np.testing.assert_array_equal(v, v_wide)
            for a, b in zip(q, q_wide):
                np.testing.assert_array_equal(a, b)
        narrow_belief = belief_value_iteration(narrow, v_s32, GAMMA, 2.1, 1e-12, max_iterations)
        wide_belief = belief_value_iteration(wide, v_s64, GAMMA, 2.1, 1e-12, max_iterations)
        for a, b in zip(narrow_belief[:2], wide_belief[:2]):
            np.testing.assert_array_equal(a, b)
        for a, b in zip(narrow_belief[2] + narrow_belief[3], wide_belief[2] + wide_belief[3]):
            np.testing.assert_array_equal(a, b)
    for a, b in zip(greedy_values(narrow, v_s32), greedy_values(wide, v_s64)):
        np.testing.assert_array_equal(a, b)


def test_an_object_without_poses_has_no_values():
    v, q = solve([], np.zeros(0))
    assert v.shape == (0,) and q == []
    assert greedy_values([], np.zeros(0)) == []
    assert pose_values([], np.zeros(0), []) == []


def test_policies_choose_among_the_choosable_pushes_and_every_push_keeps_its_value():
    # Pose 0 (V_s 0.1): push 0 reaches pose 1 (V_s 0.9) surely but may not be chosen (a push from
    # above, say); push 1 reaches it half the time.  Pose 1 is the best pose.
    v_s = np.array([0.1, 0.9])
    tables = [np.array([[0.0, 1.0], [0.5, 0.5]]), np.array([[0.0, 1.0]])]
    thesis = MDPConfig(choice_radius=0.0, believe_failures=False)  # the value below counts on retrying push 1
    free = pose_values(tables, v_s, [-1, -1], thesis)
    assert free[0].policies["value_iteration"].action == 0 and free[0].policies["greedy"].action == 0
    kept = pose_values(tables, v_s, [-1, -1], thesis, [np.array([False, True]), np.array([True])])
    assert kept[0].policies["value_iteration"].action == 1 and kept[0].policies["greedy"].action == 1
    # V_T(0) solves V = gamma (0.5 V + 0.5 * 0.9) with push 1 alone; V_T(1) = V_s(1).
    v0 = GAMMA * 0.45 / (1 - GAMMA * 0.5)
    assert kept[0].value == pytest.approx(v0)
    # The push it may not choose still has its Q_T under that plan, and its greedy value.
    np.testing.assert_allclose(kept[0].q, [0.9, 0.5 * v0 + 0.45], atol=1e-9)
    np.testing.assert_allclose(kept[0].greedy, free[0].greedy)
    # All choosable is the same as no mask, to the bit.
    every = pose_values(tables, v_s, [-1, -1], thesis, [np.ones(2, dtype=bool), np.ones(1, dtype=bool)])
    assert plans(every) == plans(free)


def plans(values) -> list[tuple]:
    """What ``pose_values`` says of each pose (V_T, every Q_T, the policies' choices), for comparing two plans to the bit."""
    return [(v.value, v.q.tolist(), v.policies) for v in values]


@pytest.mark.parametrize("believe_failures", [False, True])
def test_a_mask_of_zeros_and_ones_is_a_mask_not_row_numbers(believe_failures):
    """The solvers read each pose's choosable pushes as bool, as the choices do: a 0/1 integer or list
    mask plans exactly as the bool mask, where indexing by it took its entries as row numbers (found by
    mutation testing: V_T(0) 0.855 instead of 0.814 on the case below); masks that are not one per pose,
    one entry per push, are refused, even when their total length matches."""
    v_s = np.array([0.1, 0.9, 0.2])
    tables = [np.array([[0.0, 1.0, 0.0], [0.5, 0.5, 0.0], [0.0, 0.0, 1.0]]), np.array([[0.0, 0.0, 1.0]]), np.zeros((0, 3))]
    config = MDPConfig(choice_radius=0.0, believe_failures=believe_failures)
    masks = [np.array([False, True, False]), np.array([True]), np.zeros(0, dtype=bool)]
    as_bool = pose_values(tables, v_s, [-1, -1, -1], config, masks)
    for other in ([m.astype(int) for m in masks], [m.tolist() for m in masks]):
        assert plans(pose_values(tables, v_s, [-1, -1, -1], config, other)) == plans(as_bool)
    # Only push 1 may be chosen in pose 0: it reaches pose 1 (V_s 0.9, where pushing would lose it to pose 2)
    # half the time, and a failure leaves pose 0 retrying it, believed at p^k after a failure when so planned.
    p = 0.5 ** (config.after_failure_power if believe_failures else 1.0)
    failed = GAMMA * p * 0.9 / (1 - GAMMA * (1 - p))
    assert as_bool[0].policies["value_iteration"].action == 1
    assert as_bool[0].value == pytest.approx(GAMMA * (0.5 * 0.9 + 0.5 * failed))
    for wrong in ([np.array([False, True]), np.array([True]), np.zeros(0, dtype=bool)],      # a push short
                  [np.array([False, True]), np.array([False, True]), np.zeros(0, dtype=bool)],  # the right total, shifted
                  [np.array([[False, True, False]]), np.array([True]), np.zeros(0, dtype=bool)],  # 2-D
                  masks[:2]):                                                                   # a pose short
        with pytest.raises(ValueError, match="one per pose|one entry per push"):
            pose_values(tables, v_s, [-1, -1, -1], config, wrong)


# ----------------------------------------------------------------------------- believing failures (12.13)


def reference_belief_values(next_pose, v_s, gamma, power, sweeps=3000, choosable=None):
    """Plain value iteration over the 2P states (x, fresh) and (x, failed here), with explicit
    loops and no closed form: a fresh push topples with p, a push in the failed state with p^k,
    landing where the row's topples land; a failure leads to (x, failed), a topple to (x', fresh)."""
    n = len(v_s)
    v0, v1 = np.array(v_s, dtype=float), np.array(v_s, dtype=float)
    for _ in range(sweeps):
        n0, n1 = np.array(v_s, dtype=float), np.array(v_s, dtype=float)
        for x, table in enumerate(next_pose):
            for a, row in enumerate(np.asarray(table, dtype=float)):
                if np.isnan(row).any() or (choosable is not None and not choosable[x][a]):
                    continue
                p = 1.0 - row[x]
                land = sum(row[y] * v0[y] for y in range(n) if y != x) / p if p > 0 else 0.0
                n0[x] = max(n0[x], gamma * (p * land + (1 - p) * v1[x]))
                n1[x] = max(n1[x], gamma * (p ** power * land + (1 - p ** power) * v1[x]))
        v0, v1 = n0, n1
    return v0, v1


def test_belief_matches_a_textbook_two_state_value_iteration():
    rng = np.random.default_rng(3)
    for n_poses, n_actions in [(2, 3), (4, 12), (6, 20)]:
        next_pose, v_s = random_mdp(rng, n_poses, n_actions)
        choosable = [rng.random(len(t)) < 0.8 for t in next_pose]
        v0, v1, q0, q1 = belief_value_iteration(next_pose, v_s, GAMMA, 2.1, 1e-13, 10_000, choosable)
        r0, r1 = reference_belief_values(next_pose, v_s, GAMMA, 2.1, choosable=choosable)
        np.testing.assert_allclose(v0, r0, atol=1e-9)
        np.testing.assert_allclose(v1, r1, atol=1e-9)
        assert (v1 <= v0 + 1e-12).all() and (v1 >= v_s).all()  # a failure is never good news
        for x, (table, a0, a1) in enumerate(zip(next_pose, q0, q1)):
            table = np.asarray(table, dtype=float)
            p = 1.0 - table[:, x]
            leave = table @ v0 - table[:, x] * v0[x]
            np.testing.assert_allclose(a0, leave + (1 - p) * v1[x], atol=1e-12)  # NaN where the row is
            np.testing.assert_allclose(a1, p ** 1.1 * leave + (1 - p ** 2.1) * v1[x], atol=1e-12)


def test_belief_of_power_one_is_the_thesis_and_of_a_huge_power_is_no_retries():
    rng = np.random.default_rng(4)
    for n_poses, n_actions in [(3, 5), (7, 30)]:
        next_pose, v_s = random_mdp(rng, n_poses, n_actions)
        thesis_v, thesis_q = solve(next_pose, v_s)
        v0, v1, q0, q1 = belief_value_iteration(next_pose, v_s, GAMMA, 1.0, 1e-13, 10_000)
        np.testing.assert_allclose(v0, thesis_v, atol=1e-10)
        np.testing.assert_allclose(v1, thesis_v, atol=1e-10)  # with k = 1 a failure teaches nothing
        for a, b, c in zip(q0, q1, thesis_q):
            np.testing.assert_allclose(a, c, atol=1e-10)
            np.testing.assert_allclose(b, c, atol=1e-10)
        once_v, once_q = solve(next_pose, v_s, retry_failed=False)
        v0, v1, q0, _ = belief_value_iteration(next_pose, v_s, GAMMA, 1e9, 1e-13, 10_000)
        np.testing.assert_allclose(v0, once_v, atol=1e-10)
        np.testing.assert_allclose(v1, v_s)  # nothing topples once a push has failed: grasp
        for a, c in zip(q0, once_q):
            np.testing.assert_allclose(a, c, atol=1e-10)


def long_shot_and_likely_push():
    """Pose 0 (V_s 0.2): a long shot, 0.1 onto pose 1 (V_s 1.0); a likely push, 0.9 onto pose 2 (V_s 0.5)."""
    return [np.array([[0.9, 0.1, 0.0], [0.1, 0.0, 0.9]]), np.zeros((0, 3)), np.zeros((0, 3))], np.array([0.2, 1.0, 0.5])


def test_belief_tries_the_long_shot_once_then_takes_the_likely_push():
    # Pose 0 (V_s 0.2): a long shot, 0.1 onto pose 1 (V_s 1.0); a likely push, 0.9 onto pose 2
    # (V_s 0.5).  The thesis retries the long shot for ever: 0.1 g / (1 - 0.9 g) = 0.655 against
    # 0.45 g / (1 - 0.1 g) = 0.472.  Believing failures (k = 2.1), once a push has failed the long
    # shot topples with 0.1^2.1 = 0.008 and the likely one with 0.9^2.1 = 0.80, so the failed
    # state takes the likely push, worth V1 = 0.45 * 0.9^1.1 g / (1 - g + 0.9^2.1 g) = 0.469; a
    # fresh long shot is then worth 0.1 + 0.9 * 0.469 = 0.522 against 0.45 + 0.1 * 0.469 = 0.497.
    next_pose, v_s = long_shot_and_likely_push()
    v_t, q_t = solve(next_pose, v_s)
    assert np.argmax(q_t[0]) == 0  # the thesis pushes the long shot, and again after it fails
    v0, v1, q0, q1 = belief_value_iteration(next_pose, v_s, GAMMA, 2.1, 1e-13, 10_000)
    likely = 0.45 * 0.9 ** 1.1 * GAMMA / (1 - GAMMA + 0.9 ** 2.1 * GAMMA)
    assert v1[0] == pytest.approx(likely) and likely == pytest.approx(0.469, abs=5e-4)
    np.testing.assert_allclose(q0[0], [0.1 + 0.9 * likely, 0.45 + 0.1 * likely])
    assert np.argmax(q0[0]) == 0 and np.argmax(q1[0]) == 1  # the long shot first, then the likely push
    assert v0[0] == pytest.approx(GAMMA * (0.1 + 0.9 * likely)) and v0[0] < v_t[0]
    # Poses without pushes keep their grasp in both states.
    np.testing.assert_allclose([v0[1], v0[2], v1[1], v1[2]], [1.0, 0.5, 1.0, 0.5])


def test_pose_values_believe_failures_by_default_and_the_thesis_preset_does_not():
    next_pose, v_s = long_shot_and_likely_push()
    believing = pose_values(next_pose, v_s, [-1, -1, -1], MDPConfig(choice_radius=0.0))
    thesis = pose_values(next_pose, v_s, [-1, -1, -1], MDPConfig(choice_radius=0.0, believe_failures=False))
    assert thesis[0].policies["value_iteration"].action == believing[0].policies["value_iteration"].action == 0
    assert believing[0].value < thesis[0].value  # a failure is worth V1 < V_T
    # k = 1 believes nothing: the thesis's equation, to the bit.
    no_map = pose_values(next_pose, v_s, [-1, -1, -1], MDPConfig(choice_radius=0.0, after_failure_power=1.0))
    assert [(v.value, v.q.tolist()) for v in no_map] == [(v.value, v.q.tolist()) for v in thesis]
    with pytest.raises(ValueError, match="two answers to one question"):
        MDPConfig(retry_failed=False)


def stationary_map_value(next_pose, v_s, acts, gamma, power, grasps_after_failure=()):
    """Exact value of the pose -> push map ``acts`` (NO_OP: grasp) for a client that repeats a failed
    push, under (12.13)'s belief: two states per pushing pose, fresh and failed (the same push then
    topples with p^k and lands where its row's topples land), one linear system; in the poses
    ``grasps_after_failure`` the failed state grasps instead (12.17)."""
    n = len(v_s)
    acting = [x for x in range(n) if acts[x] != NO_OP]
    index = {x: i for i, x in enumerate(acting)}
    m = len(acting)
    system, constant = np.eye(2 * m), np.zeros(2 * m)
    for x in acting:
        row = np.asarray(next_pose[x], dtype=float)[acts[x]]
        p = 1.0 - row[x]
        for scale, state in ((1.0, index[x]), (p ** (power - 1.0), m + index[x])):
            for y in range(n):
                if y != x and row[y] > 0:
                    if y in index:
                        system[state, index[y]] -= gamma * scale * row[y]
                    else:
                        constant[state] += gamma * scale * row[y] * v_s[y]
        system[index[x], m + index[x]] -= gamma * (1.0 - p)  # fresh: a failure leaves it failed here
        if x in grasps_after_failure:
            system[m + index[x]] = 0.0
            system[m + index[x], m + index[x]] = 1.0
            constant[m + index[x]] = v_s[x]  # the failed state is the grasp: worth V_s(x), not discounted
            continue
        system[m + index[x], m + index[x]] -= gamma * (1.0 - p ** power)  # failed: and again
    fresh = np.array(v_s, dtype=float)
    if m:
        fresh[acting] = np.linalg.solve(system, constant)[:m]
    return fresh


def every_map_value(next_pose, v_s, power, options, grasps=False):
    """(map, the poses whose failed state grasps, exact value) of every pose -> push map over ``options``
    (per pose, NO_OP and the pushes it may take), and with ``grasps`` every repeat-or-grasp choice of
    its pushing poses too (``stationary_map_value``)."""
    for acts in itertools.product(*options):
        pushing = [x for x, a in enumerate(acts) if a != NO_OP]
        for grasping in itertools.product((False, True), repeat=len(pushing) if grasps else 0):
            chosen = {x for x, g in zip(pushing, grasping) if g}
            yield acts, chosen, stationary_map_value(next_pose, v_s, acts, GAMMA, power, chosen)


def test_for_a_client_that_repeats_the_long_shot_the_likely_push_is_worth_more():
    # The client that sends only its pose pushes the long shot again after it fails, where it topples
    # with 0.1^2.1: Q_R = 0.1 (1 + 0.9 g 0.1^1.1 / (1 - g + g 0.1^2.1)) = 0.218, against the likely
    # push's 0.45 (1 + 0.1 g 0.9^1.1 / (1 - g + g 0.9^2.1)) = 0.497, its Q0 too (its failed state pushes
    # it again); (12.13)'s Q0 ranks the long shot first (0.522), counting its failure at the likely push
    # a reporting client switches to.
    next_pose, v_s = long_shot_and_likely_push()
    v_r, q_r = repeat_value_iteration(next_pose, v_s, GAMMA, 2.1, 1e-13, 10_000)
    loop = [GAMMA * p ** 1.1 / (1 - GAMMA + GAMMA * p ** 2.1) for p in (0.1, 0.9)]
    expected = [0.1 * (1 + 0.9 * loop[0]), 0.45 * (1 + 0.1 * loop[1])]
    np.testing.assert_allclose(q_r[0], expected, rtol=1e-12)
    assert expected == pytest.approx([0.218, 0.497], abs=5e-4)
    assert v_r[0] == pytest.approx(GAMMA * expected[1]) and v_r[1:].tolist() == [1.0, 0.5]
    believing = pose_values(next_pose, v_s, [-1, -1, -1], MDPConfig(choice_radius=0.0))
    repeating = pose_values(next_pose, v_s, [-1, -1, -1], MDPConfig(choice_radius=0.0, choose_for_repeats=True))
    assert believing[0].policies["value_iteration"].action == 0 and repeating[0].policies["value_iteration"].action == 1
    # Only the choice moves: the stored Q0 and V0, and the chosen push's value is its own Q0.
    for a, b in zip(believing, repeating):
        assert a.value == b.value and np.array_equal(a.q, b.q, equal_nan=True)
    assert repeating[0].policies["value_iteration"].value == believing[0].q[1]
    # And the exact value of each map for that client agrees: the likely push is the better one to store.
    assert stationary_map_value(next_pose, v_s, [1, NO_OP, NO_OP], GAMMA, 2.1)[0] == pytest.approx(v_r[0], abs=1e-12)
    assert stationary_map_value(next_pose, v_s, [0, NO_OP, NO_OP], GAMMA, 2.1)[0] == pytest.approx(GAMMA * expected[0], abs=1e-12)


def test_repeat_value_iteration_is_the_best_pose_to_push_map_for_a_client_that_repeats():
    rng = np.random.default_rng(11)
    coupled = random_mdp(np.random.default_rng(2), 5, 3)  # three poses push, and (12.13)'s V0 is not V_R
    cases = [(*random_mdp(rng, n, a), power) for n, a, power in [(2, 3, 2.1), (3, 3, 2.1), (3, 2, 3.5), (4, 2, 1.4)]]
    for next_pose, v_s, power in cases + [(*coupled, 2.1)]:
        choosable = [rng.random(len(t)) < 0.8 for t in next_pose]
        v_r, q_r = repeat_value_iteration(next_pose, v_s, GAMMA, power, 1e-13, 10_000, choosable)
        options = [[NO_OP] + [u for u in range(len(t)) if choosable[x][u] and not np.isnan(t[u]).any()]
                   for x, t in enumerate(next_pose)]
        best = np.array(v_s, dtype=float)
        for _, _, value in every_map_value(next_pose, v_s, power, options):
            assert (value <= v_r + 1e-9).all(), "no map beats V_R for this client"
            best = np.maximum(best, value)
        np.testing.assert_allclose(v_r, best, atol=1e-9)
        # Its argmax map attains V_R, and Q_R is NaN where the row is.
        acts = [NO_OP if v_s[x] >= GAMMA * np.nanmax(np.where(choosable[x], q, np.nan), initial=-1.0)
                else int(np.nanargmax(np.where(choosable[x], q, np.nan))) for x, q in enumerate(q_r)]
        np.testing.assert_allclose(stationary_map_value(next_pose, v_s, acts, GAMMA, power), v_r, atol=1e-9)
        for table, q in zip(next_pose, q_r):
            assert np.array_equal(np.isnan(q), np.isnan(np.asarray(table, dtype=float)).any(axis=1))
    v_r, _ = repeat_value_iteration(*coupled, GAMMA, 2.1, 1e-13, 10_000)
    v0, *_ = belief_value_iteration(*coupled, GAMMA, 2.1, 1e-13, 10_000)
    assert (v_r > np.asarray(coupled[1]) + 1e-6).sum() >= 2, "poses push onto poses that push"
    assert (v0 > v_r + 1e-6).any(), "the repeating client is worth less than the one that switches"


def test_a_repeating_client_that_then_grasps_is_the_best_map_of_push_and_failed_choice():
    # (12.17): each pushing pose also chooses, once its push failed, to repeat it or grasp there.
    rng = np.random.default_rng(13)
    cases_where_the_grasp_after_a_failure_pays = 0
    for n_poses, n_actions, power in [(2, 3, 2.1), (3, 2, 2.1), (3, 2, 4.0), (2, 2, 6.0)]:
        next_pose, v_s = random_mdp(rng, n_poses, n_actions)
        v_g, q_g = repeat_value_iteration(next_pose, v_s, GAMMA, power, 1e-13, 10_000, then_grasp=True)
        options = [[NO_OP] + [u for u in range(len(t)) if not np.isnan(t[u]).any()] for t in next_pose]
        best, repeating = np.array(v_s, dtype=float), np.array(v_s, dtype=float)
        for _, grasping, value in every_map_value(next_pose, v_s, power, options, grasps=True):
            best = np.maximum(best, value)
            if not grasping:
                repeating = np.maximum(repeating, value)
        np.testing.assert_allclose(v_g, best, atol=1e-9)
        cases_where_the_grasp_after_a_failure_pays += int((best > repeating + 1e-9).any())
        v_r, _ = repeat_value_iteration(next_pose, v_s, GAMMA, power, 1e-13, 10_000)
        assert (v_g >= v_r - 1e-12).all(), "the grasp is one more choice"
    assert cases_where_the_grasp_after_a_failure_pays, "the enumeration meets a map that grasps after a failure"
    # The long shot: 0.1 + 0.9 max(0.2, its repeats' 0.1 g 0.1^1.1 / (1 - g + g 0.1^2.1)) = 0.28.
    next_pose, v_s = long_shot_and_likely_push()
    _, q_g = repeat_value_iteration(next_pose, v_s, GAMMA, 2.1, 1e-13, 10_000, then_grasp=True)
    assert stationary_map_value(next_pose, v_s, [0, NO_OP, NO_OP], GAMMA, 2.1, {0})[0] == pytest.approx(GAMMA * 0.28)
    likely = 0.45 * 0.9 ** 1.1 * GAMMA / (1 - GAMMA + 0.9 ** 2.1 * GAMMA)
    np.testing.assert_allclose(q_g[0], [0.1 + 0.9 * 0.2, 0.45 + 0.1 * likely], rtol=1e-12)
    # Past any belief in repeats (k huge) it is value iteration without retries, (12.9).
    rng = np.random.default_rng(14)
    next_pose, v_s = random_mdp(rng, 5, 8)
    once_v, once_q = solve(next_pose, v_s, retry_failed=False)
    v_g, q_g = repeat_value_iteration(next_pose, v_s, GAMMA, 1e9, 1e-13, 10_000, then_grasp=True)
    np.testing.assert_allclose(v_g, once_v, atol=1e-10)
    for a, b in zip(q_g, once_q):
        np.testing.assert_allclose(a, b, atol=1e-10)
    with pytest.raises(ValueError, match="set both"):
        MDPConfig(repeats_then_grasp=True)
    # With V_s(0) 0.45 the three tell apart: (12.13)'s Q0 and (12.17) push the long shot, (12.16) the likely push.
    rows, v_s = long_shot_and_likely_push()
    v_s = np.array([0.45, 1.0, 0.5])
    actions = [pose_values(rows, v_s, [-1, -1, -1], MDPConfig(choice_radius=0.0, **options))[0].policies["value_iteration"].action
               for options in ({}, {"choose_for_repeats": True}, {"choose_for_repeats": True, "repeats_then_grasp": True})]
    assert actions == [0, 1, 0]


def test_repeat_value_iteration_of_power_one_is_the_thesis_value_iteration():
    # Without a belief a repeated push is a fresh draw: the thesis's own stationary optimum.
    rng = np.random.default_rng(12)
    for n_poses, n_actions in [(3, 5), (7, 30)]:
        next_pose, v_s = random_mdp(rng, n_poses, n_actions)
        thesis_v, thesis_q = solve(next_pose, v_s)
        v_r, q_r = repeat_value_iteration(next_pose, v_s, GAMMA, 1.0, 1e-13, 10_000)
        np.testing.assert_allclose(v_r, thesis_v, atol=1e-10)
        pushing = thesis_v > np.asarray(v_s) + 1e-9
        assert pushing.any()
        for x in np.flatnonzero(pushing):  # where the thesis pushes, it pushes what the repeating client should
            assert np.nanargmax(q_r[x]) == np.nanargmax(thesis_q[x])
    with pytest.raises(ValueError, match="power >= 1"):
        repeat_value_iteration(next_pose, v_s, GAMMA, 0.5, 1e-13, 10)
    with pytest.raises(ValueError, match="one that grasps"):
        MDPConfig(choose_for_repeats=True, retry_failed=False, believe_failures=False)
    for thesis in ({"believe_failures": False}, {"after_failure_power": 1.0}):  # no belief to rank repeats by
        with pytest.raises(ValueError, match="needs mdp.believe_failures = true"):
            MDPConfig(choose_for_repeats=True, **thesis)


def test_the_choice_by_neighbourhood_ranks_the_repeating_clients_values():
    # The default chooses by neighbourhood (12.15): with the option it averages Q_R, not Q0.  Two pushes a
    # metre apart are each their own only neighbour.
    rows, v_s = long_shot_and_likely_push()
    pushes = [(np.array([[0.0, 0, 0], [1.0, 0, 0]]), np.array([[1.0, 0, 0], [0, 1.0, 0]])), (np.zeros((0, 3)), np.zeros((0, 3))),
              (np.zeros((0, 3)), np.zeros((0, 3)))]
    plain = pose_values(rows, v_s, [-1, -1, -1], MDPConfig(choice_neighbours=1), pushes=pushes)
    repeating = pose_values(rows, v_s, [-1, -1, -1], MDPConfig(choice_neighbours=1, choose_for_repeats=True), pushes=pushes)
    assert plain[0].policies["value_iteration"].action == 0 and repeating[0].policies["value_iteration"].action == 1
    assert repeating[0].policies["value_iteration"].value == plain[0].q[1]


def test_belief_plans_over_the_choosable_pushes_only():
    # The likely push may not be chosen (a push from above, say): the failed state can only take
    # the long shot again, V1 = max(0.2, 0.1^1.1 * 0.1 g / (1 - g + 0.1^2.1 g)) = 0.2, and the
    # fresh long shot is worth 0.1 + 0.9 * 0.2; the likely push keeps its Q0 under that plan.
    next_pose, v_s = long_shot_and_likely_push()
    choosable = [np.array([True, False]), np.zeros(0, dtype=bool), np.zeros(0, dtype=bool)]
    v0, v1, q0, q1 = belief_value_iteration(next_pose, v_s, GAMMA, 2.1, 1e-13, 10_000, choosable)
    assert v1[0] == pytest.approx(0.2) and v0[0] == pytest.approx(GAMMA * (0.1 + 0.9 * 0.2))
    np.testing.assert_allclose(q0[0], [0.1 + 0.9 * 0.2, 0.45 + 0.1 * 0.2])
    np.testing.assert_allclose(q1[0], [0.1 ** 1.1 * 0.1 + (1 - 0.1 ** 2.1) * 0.2, 0.9 ** 1.1 * 0.45 + (1 - 0.9 ** 2.1) * 0.2])
    free = belief_value_iteration(next_pose, v_s, GAMMA, 2.1, 1e-13, 10_000)
    assert free[1][0] > 0.4, "with every push choosable the failed state takes the likely push"
    # pose_values plans the same way, and chooses only among the choosable pushes.
    values = pose_values(next_pose, v_s, [-1, -1, -1], MDPConfig(choice_radius=0.0, tolerance=1e-13), choosable)
    assert values[0].value == pytest.approx(v0[0]) and values[0].policies["value_iteration"].action == 0
    np.testing.assert_allclose(values[0].q, q0[0])


def test_the_service_reads_q1_off_the_stored_q0():
    # schema.retry.failed_state_values, from a pose's own Q0, P and V_s alone, is the solver's Q1.
    from schema import retry

    rng = np.random.default_rng(5)
    for n_poses, n_actions in [(3, 6), (6, 25)]:
        next_pose, v_s = random_mdp(rng, n_poses, n_actions)
        choosable = [rng.random(len(t)) < 0.7 for t in next_pose]
        _, _, q0, q1 = belief_value_iteration(next_pose, v_s, GAMMA, 2.1, 1e-13, 10_000, choosable)
        for x, table in enumerate(next_pose):
            p = 1.0 - np.asarray(table, dtype=float)[:, x]
            served = retry.ranking_values(q0[x], p, v_s[x], np.nan, 2.1, True, believes=True, gamma=GAMMA, choosable=choosable[x])
            np.testing.assert_allclose(served, q1[x], atol=1e-12)
    with pytest.raises(ValueError, match="gamma and choosable"):
        retry.ranking_values(q0[0], p, v_s[0], np.nan, 2.1, True, believes=True)


def test_belief_without_discount_keeps_a_push_that_never_topples_finite():
    # gamma = 1 (the config allows it): a push that never topples is 0 / 0 in the failed state's
    # closed form; it is worth nothing there, and the values stay finite.
    next_pose = [np.array([[1.0, 0.0], [0.5, 0.5]]), np.zeros((0, 2))]
    v_s = np.array([0.2, 1.0])
    v0, v1, q0, q1 = belief_value_iteration(next_pose, v_s, 1.0, 2.1, 1e-12, 10_000)
    assert np.isfinite(v0).all() and np.isfinite(v1).all() and all(np.isfinite(q).all() for q in q0 + q1)
    assert v1[0] == pytest.approx(1.0) and v0[0] == pytest.approx(1.0)  # undiscounted, the sure-in-time push pays
    from schema import retry

    served = retry.failed_state_values(q0[0], np.array([0.0, 0.5]), 0.2, 1.0, 2.1, np.ones(2, dtype=bool))
    np.testing.assert_allclose(served, q1[0])


def test_belief_refuses_a_power_below_one():
    # The message names the solver that refused (the rows' reader is shared).
    with pytest.raises(ValueError, match=r"^belief_value_iteration needs power >= 1, got 0\.5$"):
        belief_value_iteration([np.zeros((0, 1))], np.array([0.5]), GAMMA, 0.5, 1e-9, 100)


# ----------------------------------------------------------------------------- greedy values and policies


def test_greedy_values_are_expected_next_grasp_quality():
    table = np.array([[0.25, 0.75], [1.0, 0.0], NAN_ROW[:2]])
    (g,) = greedy_values([table], np.array([0.2, 0.6]))
    np.testing.assert_allclose(g[:2], [0.25 * 0.2 + 0.75 * 0.6, 0.2])
    assert np.isnan(g[2])


def test_figure_4_6_greedy_no_ops_while_value_iteration_acts():
    next_pose, v_s = figure_4_6()
    _, q = solve(next_pose, v_s)
    greedy = greedy_values(next_pose, v_s)
    g = greedy_policy(0, v_s, greedy[0])
    assert (g.action, g.value) == (NO_OP, pytest.approx(0.4))
    choice = value_iteration_policy(0, v_s, q[0], GAMMA)
    assert choice.action == 1  # topple to pose 1, from which pose 2 is one more push away
    assert choice.value == pytest.approx(q[0][1])
    # From pose 1 both act; in pose 2 both grasp.
    assert greedy_policy(1, v_s, greedy[1]).action == 0
    assert value_iteration_policy(1, v_s, q[1], GAMMA).action == 0
    assert greedy_policy(2, v_s, greedy[2]).action == NO_OP
    assert value_iteration_policy(2, v_s, q[2], GAMMA).action == NO_OP


def test_greedy_acts_only_on_a_strict_expected_improvement():
    v_s = np.array([0.5, 0.3, 0.9])
    worse_or_equal = np.array([[1.0, 0, 0], [0.5, 0.5, 0.0], [0.6, 0.4, 0.0]])  # E = 0.5, 0.4, 0.42
    g = greedy_policy(0, v_s, worse_or_equal @ v_s)
    assert g.action == NO_OP and g.value == 0.5
    better = np.vstack([worse_or_equal, [0.0, 0.5, 0.5]])  # E = 0.6
    g = greedy_policy(0, v_s, better @ v_s)
    assert g.action == 3 and g.value == pytest.approx(0.6)
    assert greedy_policy(0, v_s, np.full(2, np.nan)).action == NO_OP
    assert greedy_policy(0, v_s, np.zeros(0)).action == NO_OP


def test_value_iteration_policy_no_ops_when_grasping_now_is_at_least_as_good():
    v_s = np.array([0.9, 0.0, 1.0])
    q = np.array([0.92, 0.94, np.nan])  # gamma * 0.94 = 0.893 < 0.9
    assert value_iteration_policy(0, v_s, q, GAMMA).action == NO_OP
    assert value_iteration_policy(0, v_s, q, GAMMA).value == 0.9
    assert value_iteration_policy(0, v_s, q, 0.99).action == 1  # 0.99 * 0.94 = 0.9306 > 0.9


def test_max_height_policy_rules():
    v_s = np.array([0.2, 0.9, 0.9])
    greedy = np.array([0.3, 0.5, np.nan])
    choice = max_height_policy(0, v_s, 1, greedy)
    assert (choice.action, choice.value) == (1, 0.5)
    # Max-Height does not look at outcomes: it pushes even when the push is worse than waiting.
    assert max_height_policy(0, v_s, 0, np.array([0.1, 0.0, 0.0])).action == 0
    assert max_height_policy(1, v_s, 1, greedy).action == NO_OP  # already in a best pose
    assert max_height_policy(2, v_s, 0, greedy).action == NO_OP  # ties count as best
    assert max_height_policy(0, v_s, -1, greedy).action == NO_OP  # no such action in this pose
    stay = max_height_policy(0, v_s, 2, greedy)  # the action is not ok
    assert (stay.action, stay.value) == (NO_OP, 0.2)


def test_pose_values_takes_retries_from_the_config():
    next_pose, v_s = long_shot()
    once = pose_values(next_pose, v_s, [-1, -1, -1], MDPConfig(choice_radius=0.0, retry_failed=False, believe_failures=False))
    thesis = pose_values(next_pose, v_s, [-1, -1, -1], MDPConfig(choice_radius=0.0, believe_failures=False))
    assert once[0].policies["value_iteration"].action == 1
    assert thesis[0].policies["value_iteration"].action == 0
    assert once[0].policies["greedy"] == thesis[0].policies["greedy"]  # greedy has no retries to count


def test_without_retries_undiscounted_loops_and_pushes_it_may_not_choose():
    # gamma = 1: a loop between two poses that never reaches a better one gains nothing, and a
    # loop with a way out (1 -> 2 one time in ten) is worth the way out, retried or not.
    loop = [np.array([[0.5, 0.5]]), np.array([[0.5, 0.5]])]
    v, q = solve(loop, [0.3, 0.3], gamma=1.0, retry_failed=False)
    np.testing.assert_allclose(v, [0.3, 0.3])
    np.testing.assert_allclose(q[0], [0.3])
    way_out = [np.array([[0.0, 1.0, 0.0]]), np.array([[0.9, 0.0, 0.1]]), np.zeros((0, 3))]
    v, _ = solve(way_out, [0.3, 0.3, 1.0], gamma=1.0, retry_failed=False)
    np.testing.assert_allclose(v, [1.0, 1.0, 1.0], atol=1e-9)
    # A push the policies may not choose keeps its (12.9) value under the plan of the others.
    next_pose = [np.array([[0.0, 1.0, 0.0], [0.5, 0.0, 0.5]]), np.zeros((0, 3)), np.zeros((0, 3))]
    v_s = np.array([0.1, 0.9, 0.6])
    v, q = value_iteration(next_pose, v_s, GAMMA, 1e-12, 10_000, [np.array([False, True]), np.zeros(0, bool), np.zeros(0, bool)],
                           retry_failed=False)
    np.testing.assert_allclose(q[0], [0.9, 0.5 * 0.1 + 0.5 * 0.6], atol=1e-12)
    np.testing.assert_allclose(v[0], GAMMA * 0.35, atol=1e-12)


@pytest.mark.parametrize("retry_failed, believes", [(True, False), (False, False), (True, True)])
def test_pose_values_ties_it_together(retry_failed, believes):
    next_pose, v_s = figure_4_6()
    config = MDPConfig(choice_radius=0.0, gamma=GAMMA, tolerance=1e-12, retry_failed=retry_failed, believe_failures=believes)
    values = pose_values(next_pose, v_s, [1, 0, -1, 0], config)
    if believes:  # the stored Q and value are Q0 and V0 (MODEL.md (12.13))
        v, _, q, _ = belief_value_iteration(next_pose, v_s, GAMMA, config.after_failure_power, 1e-12, 10_000)
    else:
        v, q = solve(next_pose, v_s, retry_failed=retry_failed)
    assert len(values) == 4
    for x, pv in enumerate(values):
        assert set(pv.policies) == {"max_height", "greedy", "value_iteration"}
        assert pv.value == pytest.approx(v[x])
        np.testing.assert_allclose(pv.q, q[x])
        np.testing.assert_allclose(pv.greedy, next_pose[x] @ v_s)
    assert values[0].policies["greedy"].action == NO_OP
    assert values[0].policies["value_iteration"].action == 1
    assert values[0].policies["max_height"].action == 1
    assert values[2].policies["max_height"].action == NO_OP
    assert values[3].policies["max_height"].action == 0  # 0.4 < 1.0: pushes though it cannot help


def test_max_height_action_outside_the_pose_table_is_a_no_op():
    # An action index past the pose's actions (a stale or mismatched table) is no push, not an IndexError.
    v_s = np.array([0.2, 0.9])
    greedy = np.array([0.3, 0.5])
    for action in (2, 3):
        assert max_height_policy(0, v_s, action, greedy) == max_height_policy(0, v_s, -1, greedy)
        assert max_height_policy(0, v_s, action, greedy).action == NO_OP
    assert max_height_policy(0, v_s, 1, greedy).action == 1  # the last real action still counts


@pytest.mark.parametrize("excess", [0.0, 1e-15, IMPROVEMENT])
def test_policies_need_more_than_rounding_to_leave_a_pose(excess):
    # Rows summing to 1 only up to rounding can make "push and stay here" look better by a
    # hair; an improvement of at most IMPROVEMENT is no improvement.
    v_s = np.array([0.5, 0.1])
    at_threshold = np.array([v_s[0] + excess])
    assert greedy_policy(0, v_s, at_threshold) == greedy_policy(0, v_s, np.zeros(0))
    assert value_iteration_policy(0, v_s, at_threshold, 1.0).action == NO_OP
    assert value_iteration_policy(0, v_s, at_threshold / GAMMA, GAMMA).action == NO_OP
    clearly_better = at_threshold + 1e-9
    assert greedy_policy(0, v_s, clearly_better).action == 0
    assert value_iteration_policy(0, v_s, clearly_better, 1.0).action == 0


def test_pose_values_greedy_acts_where_a_push_raises_the_grasp_quality():
    next_pose, v_s = figure_4_6()
    values = pose_values(next_pose, v_s, [1, 0, -1, 0], MDPConfig(choice_radius=0.0, gamma=GAMMA, tolerance=1e-12))
    # Pose 1: its push reaches the perfect pose 2 with 0.9, so Greedy pushes it.
    greedy = values[1].policies["greedy"]
    assert greedy.action == 0 and greedy.value == pytest.approx(0.1 * 0.4 + 0.9 * 1.0)
    assert values[1].policies["value_iteration"].action == 0


# ----------------------------------------------------------------------------- object selection


@pytest.mark.parametrize(
    "v_s, com, kept",
    [
        ([0.9, 0.1], [0.05, 0.02], True),  # good pose stands taller than a bad one
        ([0.9, 0.1], [0.02, 0.05], False),  # the bad pose is the taller one
        ([0.9, 0.1, 0.1], [0.03, 0.05, 0.01], True),  # any qualifying pair will do
        ([0.5, 0.1], [0.05, 0.02], False),  # 0.5 is not > 0.5
        ([0.9, 0.25], [0.05, 0.02], False),  # 0.25 is not < 0.25
        ([0.9, 0.8], [0.05, 0.02], False),  # no bad pose
        ([0.9, 0.1], [0.05, 0.05], False),  # equal heights are not lower
        ([0.9], [0.05], False),
    ],
)
def test_selection_rule(v_s, com, kept):
    assert is_selected(np.array(v_s), np.array(com)) is kept


# ----------------------------------------------------------------------------- the choice by neighbourhood


def _spike_and_plateau():
    """One pose (V_s 0.1) and a better one (V_s 0.9): push 0 alone at its contact topples surely,
    pushes 1-5 share a contact 2 mm apart and topple 0.8 of the time; pose 1 never leaves."""
    v_s = np.array([0.1, 0.9])
    rows = np.array([[0.0, 1.0]] + [[0.2, 0.8]] * 5)
    points = np.array([[0.0, 0.1, 0.0]] + [[0.0, 0.002 * i, 0.0] for i in range(5)])
    directions = np.tile([1.0, 0.0, 0.0], (6, 1))
    return v_s, [rows, np.array([[0.0, 1.0]])], [(points, directions), (np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]))]


def test_the_choice_by_neighbourhood_takes_the_plateau_over_a_lone_spike():
    v_s, tables, pushes = _spike_and_plateau()
    argmax = MDPConfig(believe_failures=False, choice_radius=0.0)
    assert pose_values(tables, v_s, [-1, -1], argmax)[0].policies["value_iteration"].action == 0
    chosen = pose_values(tables, v_s, [-1, -1], MDPConfig(believe_failures=False), pushes=pushes)
    choice = chosen[0].policies["value_iteration"]
    assert choice.action == 1, "the first of the plateau's equal means; the spike has no neighbour"
    assert choice.value == pytest.approx(chosen[0].q[1])
    # Q and V_T are value iteration's whatever the choice: the same as the argmax's.
    np.testing.assert_allclose(chosen[0].q, pose_values(tables, v_s, [-1, -1], argmax)[0].q)
    # A neighbourhood that counts the spike lets it win again (at least 1 neighbour, itself).
    lone = MDPConfig(believe_failures=False, choice_neighbours=1)
    assert pose_values(tables, v_s, [-1, -1], lone, pushes=pushes)[0].policies["value_iteration"].action == 0
    # Only the choosable pushes are chosen, their means over every ok push.
    mask = [np.array([True, False, False, True, True, True]), np.ones(1, dtype=bool)]
    assert pose_values(tables, v_s, [-1, -1], MDPConfig(believe_failures=False), mask, pushes)[0].policies[
        "value_iteration"].action == 3


def test_the_choice_by_neighbourhood_grasps_unless_gamma_times_the_mean_beats_v_s():
    from pipeline.model.mdp import neighbourhood_choice

    _, _, pushes = _spike_and_plateau()
    points, directions = pushes[0]
    q = np.array([0.95, 0.6, 0.7, 0.8, 0.7, 0.6])  # the plateau's mean is 0.68 at pushes 1-5 (all within 20 mm)
    config = MDPConfig()
    every = np.ones(6, dtype=bool)
    for stay, expected in [(config.gamma * 0.68 - 1e-6, 1), (config.gamma * 0.68 + 1e-6, NO_OP)]:
        choice = neighbourhood_choice(0, np.array([stay, 0.9]), q, points, directions, every, config)
        assert choice.action == expected
        assert choice.value == pytest.approx(q[1] if expected == 1 else stay), "the push's own Q_T, or the grasp"


def test_the_choice_by_neighbourhood_needs_the_pushes():
    v_s, tables, _ = _spike_and_plateau()
    # The message names the setting that asks for them.
    with pytest.raises(ValueError, match=r"^mdp\.choice_radius > 0 .*give each pose's pushes$"):
        pose_values(tables, v_s, [-1, -1], MDPConfig())


def test_a_pose_too_sparse_for_any_neighbourhood_takes_the_argmax():
    # Three pushes 5 cm apart: none has another within 20 mm, so none has the 5 neighbours (12.15) asks
    # for. The mean cannot temper them, and grasping at V_s 0.1 would throw away a push worth far more:
    # the pose takes the thesis's argmax, as with choice_radius 0.
    v_s = np.array([0.1, 0.9])
    tables = [np.array([[0.5, 0.5], [0.0, 1.0], [0.7, 0.3]]), np.array([[0.0, 1.0]])]
    points = np.array([[0.0, 0.05 * i, 0.0] for i in range(3)])
    pushes = [(points, np.tile([1.0, 0.0, 0.0], (3, 1))), (np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]))]
    argmax = pose_values(tables, v_s, [-1, -1], MDPConfig(believe_failures=False, choice_radius=0.0))
    chosen = pose_values(tables, v_s, [-1, -1], MDPConfig(believe_failures=False), pushes=pushes)
    assert argmax[0].policies["value_iteration"].action == 1
    assert chosen[0].policies["value_iteration"] == argmax[0].policies["value_iteration"]
    # Among the choosable pushes only: with push 1 not choosable, the argmax of the others, push 0 (it
    # topples more often than push 2 onto the same pose, so with retries it reaches it sooner).
    mask = [np.array([True, False, True]), np.ones(1, dtype=bool)]
    masked = pose_values(tables, v_s, [-1, -1], MDPConfig(believe_failures=False), mask, pushes)[0].policies["value_iteration"]
    assert masked.action == 0
    assert masked == pose_values(tables, v_s, [-1, -1], MDPConfig(believe_failures=False, choice_radius=0.0), mask)[0].policies[
        "value_iteration"]


def test_the_argmax_is_taken_only_where_no_push_has_a_neighbourhood():
    from pipeline.model.mdp import neighbourhood_choice

    # Pushes 0-4 share a contact (a neighbourhood of five, each Q_T 0.2); push 5, 5 cm away, is alone
    # with Q_T 0.9. The neighbourhood's mean is taken, and 0.95 x 0.2 does not beat V_s 0.3: grasp,
    # not the lone push. Without pushes 0-4 choosable, none has a neighbourhood and push 5 is pushed.
    points = np.array([[0.0, 0.001 * i, 0.0] for i in range(5)] + [[0.0, 0.05, 0.0]])
    directions = np.tile([1.0, 0.0, 0.0], (6, 1))
    q = np.array([0.2] * 5 + [0.9])
    v_s = np.array([0.3, 0.9])
    config = MDPConfig()
    assert neighbourhood_choice(0, v_s, q, points, directions, np.ones(6, dtype=bool), config).action == NO_OP
    lone = np.array([False] * 5 + [True])
    choice = neighbourhood_choice(0, v_s, q, points, directions, lone, config)
    assert choice.action == 5 and choice.value == pytest.approx(0.9)
    # The argmax still grasps unless gamma times its Q_T beats V_s.
    assert neighbourhood_choice(0, np.array([0.86, 0.9]), q, points, directions, lone, config).action == NO_OP


def _fan(angles):
    """Pushes at one contact, directions in the table's plane at ``angles`` (rad) about z."""
    return np.zeros((len(angles), 3)), np.array([[np.cos(a), np.sin(a), 0.0] for a in angles])


def test_the_choice_by_neighbourhood_reads_its_angle_from_the_config():
    # Four pushes at one contact: push 0 (Q_T 0.9) and push 1 (0.1) 0.3 rad apart, pushes 2 and 3
    # (0.6 each) pointing the other way.  Within 0.5 rad (the default) pushes 0 and 1 are neighbours,
    # their mean 0.5 loses to the 0.6 of pushes 2-3; within 0.1 rad push 0 is alone and its 0.9 wins.
    # An angle wider than the default joins pushes the default keeps apart: 0.7 rad apart, push 1 is
    # push 0's neighbour within 1 rad and not within 0.5.
    from pipeline.model.mdp import neighbourhood_choice

    v_s = np.array([0.1, 0.9])
    q = np.array([0.9, 0.1, 0.6, 0.6])
    every = np.ones(4, dtype=bool)
    for apart, angle, expected in [(0.3, 0.1, 0), (0.3, 0.5, 2), (0.7, 0.5, 0), (0.7, 1.0, 2)]:
        config = MDPConfig(choice_neighbours=1, choice_angle=angle)
        assert neighbourhood_choice(0, v_s, q, *_fan([0.0, apart, np.pi, np.pi]), every, config).action == expected


@pytest.mark.parametrize("config", [
    MDPConfig(choice_radius=0.0),  # the default's planning: believes failures, k = 2.1, V1 of (12.13)
    MDPConfig(choice_radius=0.0, believe_failures=False),  # the thesis: a failed push is retried, V_T
    MDPConfig(choice_radius=0.0, believe_failures=False, retry_failed=False),  # grasped where it failed, V_s (12.9)
])
def test_every_q_is_the_stored_values_of_where_its_push_leads(config):
    """The tables store V_T and the failed pose's value, so an analyst recomputes any Q_T from a row:
    q = sum_{x' != x} P(x' | x, u) V_T(x') + P(x | x, u) failed_value(x), whichever way failures are valued."""
    tables, v_s = random_mdp(np.random.default_rng(7), 5, 6)
    tables = [np.asarray(t, dtype=float) for t in tables]
    values = pose_values(tables, v_s, [-1] * 5, config)
    v_t = np.array([v.value for v in values])
    failed = np.array([v.failed_value for v in values])
    if not config.retry_failed:
        np.testing.assert_array_equal(failed, v_s)
    elif not config.believe_failures:
        np.testing.assert_array_equal(failed, v_t)
    else:  # V1: a failure is evidence against the pose's pushes, worth no more than V_T and no less than V_s
        assert np.all(failed <= v_t + 1e-12) and np.all(failed >= v_s - 1e-12) and np.any(failed < v_t - 1e-6)
    for x, (table, value) in enumerate(zip(tables, values)):
        ok = ~np.isnan(table).any(axis=1)
        leave = np.where(np.arange(5) == x, 0.0, table[ok])
        np.testing.assert_allclose(value.q[ok], leave @ v_t + table[ok, x] * failed[x], atol=1e-12)
        assert np.isnan(value.q[~ok]).all()
