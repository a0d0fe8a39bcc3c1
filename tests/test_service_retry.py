# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""POST /plan with ``failed_actions``: the policy's push among the candidates no failed push
rules out (schema.retry), served."""

from __future__ import annotations

import dataclasses
import json
import warnings
from types import SimpleNamespace

import numpy as np
import pytest

from pipeline.model import mdp
from schema import horizon, neighbourhood, retry
from schema.api import MAX_FAILED_ACTIONS, PlanRequest
from schema.frames import unit
from schema.vocabulary import NO_OP
from service.planning import untried_push
from service.store import Store
from tests.test_service import (  # noqa: F401 (fixtures)
    JSON,
    MIN_DIRECTION_Z,
    client,
    dataset,
    planar_transform,
    stored_transform,
    tables,
)


def body(tables, object_id: str, pose: int, **extra) -> dict:
    observed = planar_transform(-0.4, 0.1, 0.25) @ stored_transform(tables, object_id, pose)
    return {"object_id": object_id, "pose": observed.tolist(), **extra}


def plan(client, tables, object_id: str, pose: int, **extra) -> dict:
    response = client.post("/plan", content=json.dumps(body(tables, object_id, pose, **extra)), headers=JSON)
    assert response.status_code == 200, response.text
    return response.json()


# --- schema.retry -------------------------------------------------------------------


def test_the_margin_is_the_datasets_policies():
    assert retry.POLICY_IMPROVEMENT == mdp.IMPROVEMENT


def test_a_failed_push_rules_out_its_neighbourhood_and_nothing_else():
    x = np.array([1.0, 0.0, 0.0])
    points = np.array([[0.0, 0.0, 0.05], [0.015, 0.0, 0.05], [0.05, 0.0, 0.05], [0.005, 0.0, 0.05]])
    directions = np.array([x, x, x, [-1.0, 0.0, 0.0]])
    # 0 and 1 are 15 mm apart with one direction; 2 is 50 mm away; 3 is near but pushes the other way.
    assert retry.ruled_out(points, directions, [0]).tolist() == [True, True, False, False]
    assert retry.ruled_out(points, directions, [3]).tolist() == [False, False, False, True]
    assert retry.ruled_out(points, directions, [0, 2, 0]).tolist() == [True, True, True, False]
    assert not retry.ruled_out(points, directions, []).any()
    assert retry.ruled_out(points, directions, [0], radius=0.01).tolist() == [True, False, False, False]


def test_the_best_untried_push_must_beat_grasping_now():
    values = np.array([0.5, np.nan, 0.8, 0.8, 0.3])
    everything = np.ones(5, dtype=bool)
    assert retry.best_untried(values, everything, 0.2, 1e-12) == 2, "the first of equal values"
    assert retry.best_untried(values, np.array([1, 1, 0, 1, 1], bool), 0.2, 1e-12) == 3
    assert retry.best_untried(values, np.array([1, 1, 0, 0, 1], bool), 0.2, 1e-12) == 0
    assert retry.best_untried(values, np.array([1, 1, 0, 0, 1], bool), 0.5, 1e-12) == NO_OP, "a tie with V_s stays"
    assert retry.best_untried(values, everything, 0.75, 1e-12, scale=0.95) == 2
    assert retry.best_untried(values, everything, 0.77, 1e-12, scale=0.95) == NO_OP, "0.95 x 0.8 = 0.76"
    assert retry.best_untried(values, np.zeros(5, bool), 0.0, 1e-12) == NO_OP
    assert retry.best_untried(np.zeros(0), np.zeros(0, bool), 0.0, 1e-12) == NO_OP
    assert retry.best_untried(np.array([0.4]), np.ones(1, bool), 0.3, 1e-12) == 0, "one candidate"
    assert retry.best_untried(np.array([0.4]), np.ones(1, bool), 0.4, 0.0) == NO_OP, "equal to grasping now is no gain"


def test_impossible_failures_and_the_ranking_without_a_map():
    ok = np.array([True, False, True])
    assert retry.impossible_failure([0, 2], ok) is None and retry.impossible_failure([], ok) is None
    assert retry.impossible_failure([0, 3, 1], ok) == (1, 3, False), "the first: index 3 does not exist"
    assert retry.impossible_failure([2, 1], ok) == (1, 1, True), "index 1 is not ok"
    q, p = np.array([0.5, np.nan, 0.7]), np.array([0.9, np.nan, 0.2])
    for power in (None, 1.0):
        np.testing.assert_array_equal(retry.ranking_values(q, p, 0.3, 0.6, power, True), q)
        assert retry.given_failures(0.6, power) is None
    np.testing.assert_array_equal(retry.ranking_values(q, p, 0.3, 0.6, 2.0, True), retry.believed_values(q, p, 0.3, 0.6, 2.0))
    np.testing.assert_array_equal(retry.ranking_values(q, p, 0.3, 0.6, 2.0, False), retry.believed_values(q, p, 0.3, 0.3, 2.0))
    assert retry.given_failures(0.5, 2.0) == 0.25


def test_the_after_failure_map_keeps_certainty_and_order():
    p = np.linspace(0.0, 1.0, 11)
    mapped = np.array([retry.after_failure(v, 1.7) for v in p])
    assert mapped[0] == 0.0 and mapped[-1] == 1.0
    assert np.all(np.diff(mapped) > 0) and np.all(mapped[1:-1] < p[1:-1]), "lower, in the same order"
    assert retry.after_failure(0.6, 1.0) == 0.6 and retry.after_failure(0.5, 2.0) == 0.25


def test_float32_candidates_are_ruled_out_as_their_float64_values_are():
    # The service passes the store's float32 points.  A failed push's neighbours at the radius,
    # within float32's rounding of it (~40 nm here, far above neighbourhood.TOLERANCE), are what
    # the same candidates widened to float64 say they are: the tables, not their storage, decide.
    rng = np.random.default_rng(8)
    offsets = unit(rng.normal(size=(400, 3))) * (neighbourhood.RADIUS + rng.uniform(-3e-8, 3e-8, (400, 1)))
    points = (np.array([0.1, 0.05, 0.03]) + np.vstack([np.zeros(3), offsets])).astype(np.float32)
    directions = np.tile(np.float32([1.0, 0.0, 0.0]), (len(points), 1))
    widened = retry.ruled_out(points.astype(float), directions.astype(float), [0])
    assert 0 < widened[1:].sum() < 400, "both sides of the radius"
    np.testing.assert_array_equal(retry.ruled_out(points, directions, [0]), widened)


def test_choose_untried_by_default_pushes_only_what_beats_grasping_by_its_value_alone():
    points = np.array([[0.0, 0.0, 0.05], [0.1, 0.0, 0.05], [0.2, 0.0, 0.05]])
    directions = np.tile([1.0, 0.0, 0.0], (3, 1))
    values, choosable = np.array([0.9, 0.3, 0.45]), np.ones(3, dtype=bool)
    # Push 0 failed: of the rest, 0.45 does not beat grasping at 0.5; discounted by 2 it would.
    assert retry.choose_untried(values, points, directions, [0], choosable, 0.5, 1e-12) == (NO_OP, 1)
    assert retry.choose_untried(values, points, directions, [0], choosable, 0.5, 1e-12, scale=2.0) == (2, 1)
    assert retry.choose_untried(values, points, directions, [0], choosable, 0.4, 1e-12) == (2, 1)


def test_failed_ratios_clip_rounded_probabilities_into_0_1():
    # 1 - P(x | x, u) rounds a hair outside [0, 1]; further out is clipped the same way.
    p = np.array([-1e-17, -0.2, 1.0 + 2e-16, 1.3, 0.5])
    for power in (2.1, 1.0):
        ratio, believed = retry.failed_ratios(p, power)
        clipped = np.array([0.0, 0.0, 1.0, 1.0, 0.5])
        expected_ratio = np.array([0.0 ** (power - 1.0)] * 2 + [1.0, 1.0, 0.5 ** (power - 1.0)])
        np.testing.assert_allclose(ratio, expected_ratio, rtol=1e-15, atol=0)
        np.testing.assert_allclose(believed, clipped ** power, rtol=1e-15, atol=0)


def test_a_probability_rounded_outside_0_1_is_believed_as_its_clipped_value():
    # The served p_topple_given_failures and value iteration's ranking read the same clipped p as
    # failed_ratios: a hair below 0 is not a complex power, a hair above 1 not more than certain.
    assert retry.after_failure(-1e-17, 2.1) == 0.0
    assert retry.after_failure(1.0 + 2e-16, 2.1) == 1.0
    assert np.isnan(retry.after_failure(float("nan"), 2.1))
    q = np.array([0.4, 0.6])
    rounded = retry.believed_values(q, np.array([-1e-17, 1.0 + 2e-16]), 0.3, 0.5, 2.1)
    np.testing.assert_array_equal(rounded, retry.believed_values(q, np.array([0.0, 1.0]), 0.3, 0.5, 2.1))


def test_believed_values_are_the_grasp_plus_the_believed_chance_of_the_topple_gain():
    # Q_T = p T + (1 - p) F  ->  Q'' = V_s + p^k (T - V_s), docs/MODEL.md (12.12).
    rng = np.random.default_rng(9)
    p, topple = rng.uniform(0.05, 1.0, 50), rng.uniform(0.0, 1.0, 50)
    stay, failure, k = 0.35, 0.6, 2.1
    q = p * topple + (1.0 - p) * failure
    np.testing.assert_allclose(retry.believed_values(q, p, stay, failure, k), stay + p**k * (topple - stay), atol=1e-14)
    # k = 1 with failures counted at the grasp believes the table.
    q = p * topple + (1.0 - p) * stay
    np.testing.assert_allclose(retry.believed_values(q, p, stay, stay, 1.0), q, atol=1e-14)


def test_without_discount_a_push_that_never_topples_again_adds_no_fixed_point():
    # gamma = 1: a push with p = 0 (b = 0) is 0 / 0 in its own fixed point and must count as
    # nothing; the others' fixed points are their Q0 (gamma b Q0 / b), so V1 is the largest
    # choosable Q0 of a push that can still topple, or the grasp.
    rng = np.random.default_rng(10)
    p = np.where(np.arange(100) % 2 == 0, 0.0, rng.uniform(0.1, 0.9, 100))
    q0 = rng.uniform(0.2, 0.6, 100)
    choosable = rng.random(100) < 0.8
    k, stay = 2.1, 0.3
    b = p ** (k - 1.0)
    v1 = max(stay, q0[choosable & (p > 0)].max())
    with np.errstate(all="raise"), warnings.catch_warnings():
        warnings.simplefilter("error")  # numpy warns of a `where` with no `out` to fill: the 0 / 0 entries would be garbage
        q1 = retry.failed_state_values(q0, p, stay, 1.0, k, choosable)
    np.testing.assert_allclose(q1, b * q0 + (1.0 - b) * v1, atol=1e-14)
    np.testing.assert_allclose(q1[p == 0], v1, atol=0)
    # Only pushes that never topple: the grasp.
    with np.errstate(all="raise"):
        np.testing.assert_array_equal(retry.failed_state_values(q0[::2], p[::2], stay, 1.0, k, choosable[::2]), stay)


def test_a_build_that_believes_failures_needs_both_its_gamma_and_its_choosable_pushes():
    q, p, choosable = np.array([0.5, 0.7]), np.array([0.9, 0.2]), np.ones(2, dtype=bool)
    for missing in ({"gamma": 0.95}, {"choosable": choosable}):
        with pytest.raises(ValueError, match=r"^a build that believes failures ranks by Q1, which needs its gamma and choosable pushes$"):
            retry.ranking_values(q, p, 0.3, 0.6, 2.1, True, believes=True, **missing)
    np.testing.assert_array_equal(
        retry.ranking_values(q, p, 0.3, 0.6, 2.1, True, believes=True, gamma=0.95, choosable=choosable),
        retry.failed_state_values(q, p, 0.3, 0.95, 2.1, choosable),
    )


def test_a_poses_q_is_the_budgets_own_bits():
    rng = np.random.default_rng(4)
    n_poses, per_pose = 4, 6
    rows = []
    for _ in range(n_poses):
        matrix = rng.random((per_pose, n_poses)) * (rng.random((per_pose, n_poses)) < 0.6)
        matrix[:, 0] += 1e-3
        matrix = matrix / matrix.sum(axis=1, keepdims=True)
        matrix[rng.random(per_pose) < 0.2] = np.nan  # pushes that are not ok
        rows.append(matrix.astype(np.float32).astype(float))
    v_s = rng.random(n_poses)
    action_offsets, transition_offsets, next_pose, probability = horizon.csr_from_rows(rows)
    actions, values = horizon.budget_choices(v_s, action_offsets, transition_offsets, next_pose, probability, 3)
    choices = 0
    for h in range(3):
        previous = v_s if h == 0 else values[h - 1]
        for x in range(n_poses):
            span = slice(int(action_offsets[x]), int(action_offsets[x + 1]))
            q = horizon.pose_q(previous, span, transition_offsets, next_pose, probability)
            assert np.isnan(q).tolist() == np.isnan(rows[x]).any(axis=1).tolist()
            action = retry.best_untried(q, np.ones(per_pose, bool), v_s[x], horizon.IMPROVEMENT)
            assert action == actions[h, x]
            assert (q[action] if action != NO_OP else v_s[x]) == values[h, x], "the same sums, bit for bit"
            choices += action != NO_OP
    assert choices > 0


def test_float32_values_and_probabilities_are_read_as_their_float64_values():
    # Tables and studies may hand over float32 columns; each is widened exactly first, so a choice and a
    # belief are float64's.  float32(0.8) is 0.800000011920929: it beats grasping at 0.8 by more than the
    # margin, which float32 arithmetic (0.8 + 1e-12 rounds to float32(0.8)) would call a tie.
    narrow = np.float32([0.8, 0.3])
    everything = np.ones(2, dtype=bool)
    assert float(narrow[0]) - 0.8 > retry.POLICY_IMPROVEMENT
    assert retry.best_untried(narrow, everything, 0.8, retry.POLICY_IMPROVEMENT) == 0
    assert retry.best_untried(narrow, everything, 0.76, retry.POLICY_IMPROVEMENT, scale=0.95) == 0, "0.95 x 0.80000001 > 0.76"
    # P(topple) in float32: clipped and raised to k as the same numbers in float64, bit for bit.
    p = np.float32([0.0, 0.1, 0.35, 0.9, 1.0])
    wide = p.astype(np.float64)
    assert retry.clip_probability(p).dtype == np.float64
    for got, expected in zip(retry.failed_ratios(p, 2.1), retry.failed_ratios(wide, 2.1), strict=True):
        assert got.dtype == np.float64
        np.testing.assert_array_equal(got, expected)
    # Without a map the ranking is the table's Q, as float64.
    ranked = retry.ranking_values(narrow, p[:2], 0.3, 0.6, None, True)
    assert ranked.dtype == np.float64
    np.testing.assert_array_equal(ranked, narrow.astype(np.float64))


# --- the service --------------------------------------------------------------------


def test_with_nothing_failed_the_choice_is_the_stored_policys(dataset):
    store = Store.load(dataset)
    compared = 0
    for object_id, obj in store.objects.items():
        for pose in range(obj.n_poses):
            for policy in ("greedy", "value_iteration"):
                request = PlanRequest(object_id=object_id, pose=np.eye(4).tolist(), policy=policy)
                action, final, ruled = untried_push(obj, pose, request, store.gamma)
                assert (action, final, ruled) == (int(obj.policy_action[policy][pose]), None, 0), (object_id, pose, policy)
                compared += action != NO_OP
            for budget in (1, 2, 4):
                request = PlanRequest(object_id=object_id, pose=np.eye(4).tolist(), pushes_left=budget)
                action, final, _ = untried_push(obj, pose, request, store.gamma)
                actions, values = obj.budget(budget)
                assert action == actions[pose]
                assert final == (None if action == NO_OP else values[pose])
    assert compared > 0


def test_value_iteration_pushes_only_when_the_discounted_q_beats_grasping_now(dataset):
    store = Store.load(dataset)
    obj = next(o for o in store.objects.values() if (o.v_s > 0.1).any())
    pose = int(np.argmax(obj.v_s))
    rows = obj.pose_rows(pose)
    allowed = np.flatnonzero(obj.choosable(rows))
    target, stay = int(allowed[0]), float(obj.v_s[pose])
    request = PlanRequest(object_id=obj.object_id, pose=np.eye(4).tolist(), failed_actions=[])
    for q_value, expected in ((stay / store.gamma - 1e-6, NO_OP), (stay / store.gamma + 1e-6, target)):
        q = np.full(len(obj.q), np.nan)
        q[rows.start + target] = q_value  # above V_s either way; gamma Q only beats it in the second
        action, _, _ = untried_push(dataclasses.replace(obj, q=q), pose, request, store.gamma)
        assert action == expected, (q_value, stay)


def test_the_neighbours_of_a_failed_push_are_ruled_out_and_each_policy_ranks_by_its_own_values(dataset):
    """On one pose of the test dataset, rearranged: candidates a, b, c, d choosable, b 1 cm from
    a with a's direction, c and d far away.  Q ranks a > b > c > d, greedy d > c > b > a."""
    store = Store.load(dataset)
    obj = next(iter(store.objects.values()))
    pose = 0
    rows = obj.pose_rows(pose)
    a, b, c, d = (int(i) for i in np.flatnonzero(obj.choosable(rows))[:4])
    points, directions = obj.points.copy(), obj.directions.copy()
    directions[rows.start + b] = directions[rows.start + a]
    points[rows.start + b] = points[rows.start + a] + np.float32([0.01, 0.0, 0.0])
    for far, offset in ((c, 0.2), (d, -0.2)):
        points[rows.start + far] = points[rows.start + a] + np.float32([0.0, offset, 0.0])
    q, greedy = np.full(len(obj.q), np.nan), np.full(len(obj.q), np.nan)
    stay = float(obj.v_s[pose])
    for action, (q_value, greedy_value) in zip((a, b, c, d), ((4, 1), (3, 2), (2, 3), (1, 4))):
        q[rows.start + action], greedy[rows.start + action] = stay + q_value, stay + greedy_value
    sure = np.ones(len(obj.p_topple), dtype=np.float32)  # P = 1: what value iteration believes after a failure is its Q
    moved = dataclasses.replace(obj, points=points, directions=directions, q=q, greedy=greedy, p_topple=sure)

    def choose(policy, failed):
        request = PlanRequest(object_id=obj.object_id, pose=np.eye(4).tolist(), policy=policy, failed_actions=failed)
        return untried_push(moved, pose, request, store.gamma, 2.1)

    assert choose("value_iteration", [])[0] == a and choose("greedy", [])[0] == d
    assert choose("value_iteration", [a])[0] == c, "b is a's neighbour: ruled out with it"
    assert choose("value_iteration", [a])[2] == int(retry.ruled_out(points[rows], directions[rows], [a])[
        np.flatnonzero(moved.choosable(rows))].sum()) >= 2
    assert choose("greedy", [d])[0] == c and choose("greedy", [d, c])[0] == b
    assert choose("value_iteration", [a, c])[0] == d and choose("value_iteration", [a, c, d])[0] == NO_OP


def long_shot_pose(dataset) -> SimpleNamespace:
    """The test dataset's worst pose rearranged: three far-apart candidates, ``failed`` (never topples),
    a ``sure`` push (P 0.9) onto a fair pose and a ``long_shot`` (P 0.3) onto a better one that the
    table values for its retries.

    returns : store (as loaded), moved (the object with the pose rearranged), pose, rows, failed, sure,
      long_shot, q (Q_T counting retries, as the thesis), q_once (a failure counted at V_s, a build
      without retries), p_topple, stay (V_s), v_t (the pose's V_T, the long shot's fixed point), gamma
    """
    store = Store.load(dataset)
    obj = next(iter(store.objects.values()))
    pose = int(np.argmin(obj.v_s))
    rows = obj.pose_rows(pose)
    failed, sure, long_shot = (int(i) for i in np.flatnonzero(obj.choosable(rows))[:3])
    points = obj.points.copy()
    for action, offset in ((failed, 0.0), (sure, 0.2), (long_shot, -0.2)):
        points[rows.start + action] = np.float32([offset, 0.3, 0.05])
    stay, gamma = float(obj.v_s[pose]), store.gamma
    p = {sure: 0.9, long_shot: 0.3}
    landing = {sure: stay + 0.4, long_shot: stay + 0.75}
    v_t = gamma * (0.3 * landing[long_shot]) / (1 - gamma * 0.7)  # the long shot's fixed point
    q, p_topple, v_t_all = np.full(len(obj.q), np.nan), np.full(len(obj.q), np.nan, dtype=np.float32), obj.v_t.copy()
    q[rows.start + failed], p_topple[rows.start + failed] = stay, 0.0
    q_once = q.copy()
    for action in (sure, long_shot):
        q[rows.start + action] = p[action] * landing[action] + (1 - p[action]) * v_t
        q_once[rows.start + action] = p[action] * landing[action] + (1 - p[action]) * stay
        p_topple[rows.start + action] = p[action]
    v_t_all[pose] = v_t
    moved = dataclasses.replace(obj, points=points, q=q, p_topple=p_topple, v_t=v_t_all)
    return SimpleNamespace(store=store, moved=moved, pose=pose, rows=rows, failed=failed, sure=sure, long_shot=long_shot,
                           q=q, q_once=q_once, p_topple=p_topple, stay=stay, v_t=v_t, gamma=gamma)


def test_after_a_failure_value_iteration_prefers_a_likely_push_to_a_long_shot(dataset):
    """Two far-apart candidates: a sure push onto a fair pose and a long shot onto a better one
    that the table values for its retries.  After an unrelated failure, value iteration with
    the map takes the sure push; without it (k = 1, or a build from before it) the long shot."""
    s = long_shot_pose(dataset)
    moved, pose, rows, gamma, stay = s.moved, s.pose, s.rows, s.gamma, s.stay
    failed, sure, long_shot = s.failed, s.sure, s.long_shot
    assert s.q[rows.start + long_shot] > s.q[rows.start + sure], "the table prefers the long shot"
    request = PlanRequest(object_id=moved.object_id, pose=np.eye(4).tolist(), failed_actions=[failed])
    assert untried_push(moved, pose, request, gamma, 2.1)[0] == sure
    assert untried_push(moved, pose, request, gamma, 1.0)[0] == long_shot
    assert untried_push(moved, pose, request, gamma, None)[0] == long_shot
    # A build without retries counts a failure at V_s in Q_T: the same landings, so the same belief.
    once = dataclasses.replace(moved, q=s.q_once)
    assert untried_push(once, pose, request, gamma, 2.1, retry_failed=False)[0] == sure
    # The long shot alone is still worth a try; read as if Q counted retries (V_T), it would not be.
    both = PlanRequest(object_id=moved.object_id, pose=np.eye(4).tolist(), failed_actions=[failed, sure])
    assert untried_push(once, pose, both, gamma, 2.1, retry_failed=False)[0] == long_shot
    p_topple = s.p_topple[rows].astype(float)
    believed_once = retry.believed_values(s.q_once[rows], p_topple, stay, stay, 2.1)
    expected = retry.believed_values(s.q[rows], p_topple, stay, s.v_t, 2.1)
    np.testing.assert_allclose(believed_once[[sure, long_shot]], expected[[sure, long_shot]], rtol=1e-6)  # float32 P
    assert expected[sure] == pytest.approx(stay + 0.9 ** 2.1 * 0.4) and expected[long_shot] == pytest.approx(stay + 0.3 ** 2.1 * 0.75)


def failed_value(actions: dict, object_id: str, pose: dict, index: int, choosable: np.ndarray, gamma: float,
                 power: float) -> float:
    """V1 of a pose of a build that believes failures (MODEL.md (12.13)), by hand from the analysts'
    tables: the best of V_s and each choosable push's own fixed point gamma b Q0 / (1 - gamma + gamma b)."""
    best = pose["v_s"]
    for a in np.flatnonzero(choosable):
        row = actions[(object_id, index, int(a))]
        if row["q"] is not None:
            b = row["p_topple"] ** (power - 1)
            best = max(best, gamma * b * row["q"] / (1 - gamma + gamma * b))
    return best


def choice_value(action: dict, pose: dict, column: str, power: float, v1: float | None = None) -> float:
    """What a policy ranks an untried push by, from the analysts' tables: greedy its expected V_s,
    value iteration what it believes now, by hand: Q1 = b Q0 + (1 - b) V1 (MODEL.md (12.13)) for a
    build that believes failures (``v1`` given), else (12.12)."""
    if column == "greedy":
        return action["greedy"]
    p, stay = action["p_topple"], pose["v_s"]
    if v1 is not None:
        return p ** (power - 1) * action["q"] + (1 - p ** (power - 1)) * v1
    return stay + p ** (power - 1) * (action["q"] - (1 - p) * pose["v_t"]) - p ** power * stay


def test_a_failed_push_is_not_served_again_nor_its_neighbours(client, tables, dataset):
    store = Store.load(dataset)
    replaced = 0
    for (object_id, pose), row in tables["poses"].items():
        obj = store.objects[object_id]
        for policy, column in (("value_iteration", "q"), ("greedy", "greedy")):
            first = row[f"{policy}_action"]
            if first == NO_OP:
                continue
            answer = plan(client, tables, object_id, pose, policy=policy, failed_actions=[first])
            rows = obj.pose_rows(pose)
            excluded = retry.ruled_out(obj.points[rows], obj.directions[rows], [first])
            assert excluded[first] and answer["ruled_out"] == int((excluded & obj.choosable(rows)).sum()) >= 1
            assert (answer["p_topple_given_failures"] is None) == (answer["action"] is None)
            assert "1 failed push" in answer["reason"]
            actions = tables["actions"]
            mdp = tables["manifest"]["parameters"]["mdp"]
            power = mdp["after_failure_power"]
            v1 = failed_value(actions, object_id, row, pose, obj.choosable(rows), store.gamma, power) if mdp["believe_failures"] else None
            allowed = {a: choice_value(actions[(object_id, pose, a)], row, column, power, v1)
                       for a in np.flatnonzero(~excluded & obj.choosable(rows)) if actions[(object_id, pose, a)][column] is not None}
            if answer["action"] is None:
                best = max(allowed.values(), default=-np.inf)
                scale = store.gamma if policy == "value_iteration" else 1.0
                assert scale * best <= row["v_s"] + 1e-9, (object_id, pose, policy)
                assert answer["decision"] in ("grasp", "no_grasp") and answer["p_topple_neighbourhood"] is None
            else:
                replaced += 1
                assert not excluded[answer["action"]]
                assert allowed[answer["action"]] == pytest.approx(max(allowed.values()), abs=1e-8)
                again = {"object_id": object_id, "pose": pose, "action": answer["action"]}
                assert answer["p_topple"] == pytest.approx(client.post("/batch/transitions", json={"items": [again]})
                                                           .json()["results"][0]["result"]["p_topple"])
                assert answer["p_topple_neighbourhood"] == round(obj.neighbourhood_p(pose, answer["action"]), 6)
                assert answer["p_topple_given_failures"] == pytest.approx(answer["p_topple"] ** power, abs=1e-12)
                assert f"{answer['p_topple_given_failures']:.3g} now that pushes here have failed" in answer["reason"]
    assert replaced > 0, "some pose should have another push worth trying"


def test_a_budget_after_a_failure_values_its_push_as_the_budget_does(client, tables):
    checked = 0
    for object_id, pose in list(tables["poses"])[:15]:
        first = plan(client, tables, object_id, pose, pushes_left=2)
        if first["action"] is None:
            continue
        answer = plan(client, tables, object_id, pose, pushes_left=2, failed_actions=[first["action"]])
        assert answer["pushes_left"] == 2 and answer["ruled_out"] >= 1
        if answer["action"] is not None:
            checked += 1
            assert answer["action"] != first["action"]
            assert answer["expected_v_s_final"] <= first["expected_v_s_final"] + 1e-12, "the best was ruled out"
    assert checked > 0


def test_a_build_from_before_the_map_serves_no_probability_given_failures(dataset, tables):
    from service.planning import plan as plan_for
    from service.settings import Settings

    store = Store.load(dataset)
    served = 0
    for (object_id, pose), row in tables["poses"].items():
        if row["greedy_action"] == NO_OP:
            continue
        request = PlanRequest.model_validate(body(tables, object_id, pose, policy="greedy", failed_actions=[row["greedy_action"]]))
        with_map = plan_for(store, request, Settings())
        store.after_failure_power = None
        without = plan_for(store, request, Settings())
        store.after_failure_power = 1.0  # the thesis preset's: no map
        unmapped = plan_for(store, request, Settings())
        store.after_failure_power = 3.0
        cubed = plan_for(store, request, Settings())
        store.after_failure_power = tables["manifest"]["parameters"]["mdp"]["after_failure_power"]
        if with_map["action"] is not None:
            served += 1
            assert with_map["p_topple_given_failures"] is not None and without["p_topple_given_failures"] is None
            assert unmapped["p_topple_given_failures"] is None
            assert cubed["p_topple_given_failures"] == pytest.approx(cubed["p_topple"] ** 3, abs=1e-15)
            assert {**without, "p_topple_given_failures": None, "reason": None} == {**with_map, "p_topple_given_failures": None, "reason": None}
    assert served > 0


def test_no_failed_push_is_the_plain_answer(client, tables):
    object_id, pose = next(iter(tables["poses"]))
    plain = plan(client, tables, object_id, pose)
    assert plain["ruled_out"] == 0 and plain["p_topple_given_failures"] is None
    assert plan(client, tables, object_id, pose, failed_actions=[]) == plain


@pytest.mark.parametrize("extra, where", [
    ({"failed_actions": [10_000]}, "failed_actions.0"),
    ({"failed_actions": [-1]}, "failed_actions"),
    ({"failed_actions": None}, "failed_actions"),
    ({"failed_actions": [0.5]}, "failed_actions"),
    ({"failed_actions": [True]}, "failed_actions"),
    ({"failed_actions": ["1"]}, "failed_actions"),
    ({"failed_actions": [1.0]}, "failed_actions"),
    ({"failed_actions": list(range(MAX_FAILED_ACTIONS + 1))}, "failed_actions"),
    ({"failed_actions": [0], "policy": "max_height"}, "failed_actions"),
])
def test_bad_failed_actions_are_422(client, tables, extra, where):
    object_id, pose = next(iter(tables["poses"]))
    response = client.post("/plan", content=json.dumps(body(tables, object_id, pose, **extra)), headers=JSON)
    assert response.status_code == 422, response.text
    assert where in response.json()["detail"]


def test_the_last_action_is_the_boundary_and_a_push_that_is_not_ok_never_failed(client, tables):
    checked = 0
    for object_id, pose in tables["poses"]:  # every pose: their rows start at other offsets
        actions = {a: r for (o, p, a), r in tables["actions"].items() if (o, p) == (object_id, pose)}
        count = len(actions)
        not_ok = [a for a, r in actions.items() if r["status"] != "ok"]
        ok = [a for a, r in actions.items() if r["status"] == "ok"]
        if not (not_ok and ok):
            continue

        def post(failed, object_id=object_id, pose=pose):
            return client.post("/plan", content=json.dumps(body(tables, object_id, pose, failed_actions=failed)), headers=JSON)

        beyond = post([count])
        assert beyond.status_code == 422 and f"has no action {count}: its actions are 0..{count - 1}" in beyond.json()["detail"]
        assert post([max(ok)]).status_code == 200
        refused = post([ok[0], not_ok[-1]])
        assert refused.status_code == 422 and "failed_actions.1" in refused.json()["detail"]
        assert f"is {actions[not_ok[-1]]['status']}, not ok" in refused.json()["detail"]
        checked += 1
    assert checked > 5, "the test dataset should have poses with ok pushes and others"


def test_a_batch_item_with_an_unknown_failed_action_fails_alone(client, tables):
    (object_id, pose), (other, other_pose) = list(tables["poses"])[:2]
    ok = min(a for (o, p, a), r in tables["actions"].items()
             if (o, p) == (other, other_pose) and r["status"] == "ok" and r["direction_z"] >= MIN_DIRECTION_Z)
    items = [body(tables, object_id, pose, failed_actions=[10_000]), body(tables, other, other_pose, failed_actions=[ok])]
    results = client.post("/batch/plan", json={"items": items}).json()["results"]
    assert results[0]["error"]["status"] == 422 and "no action 10000" in results[0]["error"]["detail"]
    assert results[1]["result"]["ruled_out"] >= 1


def test_a_build_that_does_not_believe_failures_still_ranks_by_the_belief_after_one(tables, dataset):
    """A build with ``mdp.believe_failures`` false (the thesis preset, or one from before it) ranks
    the untried pushes by (12.12), by hand from the analysts' tables, as before (12.13) existed."""
    store = Store.load(dataset)
    actions, checked = tables["actions"], 0
    for (object_id, pose), row in tables["poses"].items():
        first = row["value_iteration_action"]
        if first == NO_OP:
            continue
        obj = store.objects[object_id]
        rows = obj.pose_rows(pose)
        request = PlanRequest(object_id=object_id, pose=np.eye(4).tolist(), failed_actions=[first])
        action = untried_push(obj, pose, request, store.gamma, 2.1, believes=False)[0]
        allowed = ~retry.ruled_out(obj.points[rows], obj.directions[rows], [first]) & obj.choosable(rows)
        by_hand = {a: choice_value(actions[(object_id, pose, a)], row, "q", 2.1) for a in np.flatnonzero(allowed)
                   if actions[(object_id, pose, a)]["q"] is not None}
        if action != NO_OP:
            checked += 1
            assert by_hand[action] == pytest.approx(max(by_hand.values()), abs=1e-8), (object_id, pose)
            believing = untried_push(obj, pose, request, store.gamma, 2.1, believes=True)[0]
            v1 = failed_value(actions, object_id, row, pose, obj.choosable(rows), store.gamma, 2.1)
            q1 = {a: choice_value(actions[(object_id, pose, a)], row, "q", 2.1, v1) for a in by_hand}
            assert q1[believing] == pytest.approx(max(q1.values()), abs=1e-8)
    assert checked > 0
