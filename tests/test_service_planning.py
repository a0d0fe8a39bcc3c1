# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""service.planning's pieces that /plan's answers are made of, checked one at a time: the
one-sentence reason a robot operator reads (budget, failures, force), and the frame check."""

from __future__ import annotations

import dataclasses
import math
from types import SimpleNamespace

import numpy as np
import pytest

from schema.api import PlanRequest
from schema.vocabulary import NO_OP
from service.errors import NoStablePose, OffTable, UnknownFrame
from service.planning import _decision, observed_pose, plan, world_grasp
from service.settings import Settings
from service.store import Store
from tests.test_service import dataset, planar_transform, stored_transform, tables, tilted  # noqa: F401 (fixtures)
from tests.test_service_contract import observe, pushing_poses
from tests.test_service_retry import long_shot_pose

GRASP = {"point": [0.0, 0.0, 0.1], "axis": [0.0, 0.0, -1.0]}


def push(within: bool | None, force: float | None = 2.5, limit: float = 10.0) -> dict:
    return {"required_force": force, "finger_force_limit": limit, "within_force_limit": within}


def reason(policy="value_iteration", pushes_left=None, action=3, v_s=0.4, grasp=GRASP, p_topple=0.5, p_near=0.45,
           after=0.6, within=True, failed=0, ruled=0, p_given=None) -> tuple[str, str]:
    """_decision as plan calls it (every argument given)."""
    return _decision(policy, pushes_left, action, v_s, grasp, p_topple, p_near, after, push(within), failed, ruled, p_given)


def test_a_push_s_reason_names_the_policy_its_probabilities_and_values():
    assert reason() == ("push", ("value_iteration pushes: P(topple) 0.5 (0.45 around it), expected V_s after the push 0.6 "
                                "vs V_s 0.4 now"))
    # A push within the finger's limit, or of unknown force, says nothing about force.
    assert reason(within=None) == reason()


@pytest.mark.parametrize("pushes_left, failed, ruled, prefix", [
    (1, 0, 0, "value_iteration (1 push left) pushes"),
    (2, 0, 0, "value_iteration (2 pushes left) pushes"),
    (None, 1, 1, "value_iteration, after 1 failed push (1 candidate ruled out), pushes"),
    (None, 2, 0, "value_iteration, after 2 failed pushes (0 candidates ruled out), pushes"),
    (3, 1, 2, "value_iteration (3 pushes left), after 1 failed push (2 candidates ruled out), pushes"),
])
def test_a_reason_counts_the_budget_and_the_failures_in_good_english(pushes_left, failed, ruled, prefix):
    decision, text = reason(pushes_left=pushes_left, failed=failed, ruled=ruled)
    assert decision == "push" and text.startswith(prefix + ": P(topple) 0.5"), text


def test_a_reason_after_failures_gives_the_believed_probability():
    _, text = reason(failed=1, ruled=4, p_given=0.123456)
    assert "P(topple) 0.5 (0.45 around it, 0.123 now that pushes here have failed)" in text


def test_a_push_beyond_the_finger_s_limit_says_not_to_execute_it():
    _, text = reason(within=False)
    assert text.endswith("vs V_s 0.4 now; it needs 2.5 N, more than the finger's limit of 10 N: do not execute it with "
                         "this finger")


def test_unknown_values_of_a_push_read_n_a():
    """A build may lack a value (stored NaN, served as null): the reason says n/a, not a 500."""
    _, text = reason(p_topple=None, p_near=None, after=None)
    assert "P(topple) n/a (n/a around it), expected V_s after the push n/a vs V_s 0.4 now" in text


@pytest.mark.parametrize("grasp, v_s, failed, expected", [
    (GRASP, 0.4, 0, ("grasp", "value_iteration does not push: grasp now at grasp (V_s = 0.4)")),
    (None, 0.4, 0, ("no_grasp", ("value_iteration does not push and this pose has no suction grasp (V_s = 0.4): no stored "
                                "push nor grasp helps; pick another object or another tool"))),
    (GRASP, 0.0, 1, ("no_grasp", ("value_iteration, after 1 failed push (0 candidates ruled out), does not push and this pose "
                                 "has no suction grasp (V_s = 0): no untried stored push nor grasp helps; pick another "
                                 "object or another tool"))),
])
def test_without_a_push_the_reason_is_grasp_or_no_grasp(grasp, v_s, failed, expected):
    assert _decision("value_iteration", None, NO_OP, v_s, grasp, None, None, None, None, failed, 0, None) == expected


def test_a_grasp_is_mapped_through_the_observed_pose_or_is_none_when_either_part_is_unknown():
    pose_to_world = np.eye(4)
    pose_to_world[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]  # a quarter turn about z
    pose_to_world[:3, 3] = [0.3, -0.2, 0.01]
    obj = SimpleNamespace(grasp_point=np.array([[0.01, 0.02, 0.05], [math.nan, 0.0, 0.0], [0.0, 0.0, 0.0]]),
                          grasp_axis=np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, math.nan, -1.0]]))
    grasp = world_grasp(obj, 0, pose_to_world)
    np.testing.assert_allclose(grasp["point"], [0.3 - 0.02, -0.2 + 0.01, 0.06], atol=1e-15)
    np.testing.assert_allclose(grasp["axis"], [0.0, 1.0, 0.0], atol=1e-15)
    assert world_grasp(obj, 1, pose_to_world) is None and world_grasp(obj, 2, pose_to_world) is None


def test_a_ros_pose_in_another_frame_is_refused_with_what_to_do():
    pose = {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}}
    request = PlanRequest.model_validate({"object_id": "a", "ros_pose": {**pose, "frame_id": "camera_link"}})
    with pytest.raises(UnknownFrame) as error:
        observed_pose(request, Settings())
    assert str(error.value) == ("ros_pose.frame_id is 'camera_link', but this service plans in 'world' (z up, table at z = 0); "
                                "transform the pose into it first (e.g. tf2)")
    same = PlanRequest.model_validate({"object_id": "a", "ros_pose": {**pose, "frame_id": "world"}})
    assert observed_pose(same, Settings()).tolist() == np.eye(4).tolist()


# --- plan() end to end on the test dataset: what it hands the pieces above ----------------------


def request(tables, object_id: str, pose: int, lift: float = 0.0, **extra):
    return PlanRequest(object_id=object_id, pose=observe(tables, object_id, pose, lift).tolist(), **extra)


def long_shot_store(dataset):
    """The test dataset's store with tests/test_service_retry.py's long-shot pose in it.
    returns : store, object_id, pose, failed, sure, long_shot, q_once (the long shot's and the sure
    push's Q had a failure counted at V_s, as a build without retries)"""
    s = long_shot_pose(dataset)
    s.store.objects[s.moved.object_id] = s.moved
    return s.store, s.moved.object_id, s.pose, s.failed, s.sure, s.long_shot, s.q_once


def test_after_a_failure_plan_ranks_by_the_build_s_own_belief(dataset, tables):
    """plan hands untried_push the build's gamma, k, retry rule and belief.  A build that believes
    failures (the test build: k = 2.1) ranks by Q1 = b Q0 + (1 - b) V1, b = p^(k-1) (MODEL.md
    (12.13)): the long shot, whose Q0 counts its retries.  Without that belief but with the map,
    the sure push after an unrelated failure; without the map (k = 1) the long shot the table
    prefers; a build without retries, the long shot alone still worth a try once the sure push failed too."""


    store, object_id, pose, failed, sure, long_shot, q_once = long_shot_store(dataset)
    assert (store.after_failure_power, store.believe_failures, store.retry_failed) == (2.1, True, True)
    obj, gamma = store.objects[object_id], store.gamma
    rows = obj.pose_rows(pose)
    q = {a: float(obj.q[rows.start + a]) for a in (failed, sure, long_shot)}
    b = {a: float(obj.p_topple[rows.start + a]) ** 1.1 for a in (failed, sure, long_shot)}
    v1 = max(float(obj.v_s[pose]), *(gamma * b[a] * q[a] / (1 - gamma + gamma * b[a]) for a in q))
    q1 = {a: b[a] * q[a] + (1 - b[a]) * v1 for a in (sure, long_shot)}
    assert q1[long_shot] > q1[sure] and gamma * q1[long_shot] > obj.v_s[pose]
    answer = plan(store, request(tables, object_id, pose, failed_actions=[failed]), Settings())
    assert answer["action"] == long_shot and answer["p_topple_given_failures"] == pytest.approx(0.3 ** 2.1, rel=1e-6)
    store.believe_failures = False
    answer = plan(store, request(tables, object_id, pose, failed_actions=[failed]), Settings())
    assert answer["action"] == sure and answer["p_topple_given_failures"] == pytest.approx(0.9 ** 2.1, rel=1e-6)
    store.after_failure_power = 1.0
    assert plan(store, request(tables, object_id, pose, failed_actions=[failed]), Settings())["action"] == long_shot
    store.after_failure_power, store.retry_failed = 2.1, False
    store.objects[object_id] = dataclasses.replace(obj, q=np.where(np.isnan(q_once), obj.q, q_once))
    both = request(tables, object_id, pose, failed_actions=[failed, sure])
    assert plan(store, both, Settings())["action"] == long_shot
    store.retry_failed = True  # read as if Q counted retries (V_T), the long shot is not worth a try
    assert plan(store, both, Settings())["action"] is None


def test_a_plan_s_reason_is_made_of_its_own_answer(dataset, tables):
    """The sentence names the request's policy, budget and failures and the answer's numbers."""
    store, object_id, pose, failed, _, long_shot, _ = long_shot_store(dataset)
    answer = plan(store, request(tables, object_id, pose, failed_actions=[failed]), Settings())
    ruled = answer["ruled_out"]
    assert answer["action"] == long_shot and answer["reason"] == (
        f"value_iteration, after 1 failed push ({ruled} candidate{'s' if ruled != 1 else ''} ruled out), pushes: "
        f"P(topple) 0.3 ({answer['p_topple_neighbourhood']:.3g} around it, {0.3 ** 2.1:.3g} now that pushes here have "
        f"failed), expected V_s after the push {answer['expected_v_s_after']:.3g} vs V_s {answer['v_s']:.3g} now")
    checked = 0
    for (object_id, pose) in tables["poses"]:
        answer = plan(store, request(tables, object_id, pose, pushes_left=2), Settings())
        if answer["action"] is not None:
            checked += 1
            assert answer["reason"].startswith(f"value_iteration (2 pushes left) pushes: P(topple) {answer['p_topple']:.3g} ")
            assert f"expected V_s after the push {answer['expected_v_s_after']:.3g} vs" in answer["reason"]
    assert checked > 0


def test_a_push_needing_exactly_the_finger_s_limit_is_within_it(dataset, tables):
    store = Store.load(dataset)
    object_id, pose, _ = pushing_poses(tables)[0]
    force = plan(store, request(tables, object_id, pose), Settings())["push"]["required_force"]
    answer = plan(store, request(tables, object_id, pose), Settings(finger_force_limit=force))
    assert answer["push"]["finger_force_limit"] == force and answer["push"]["within_force_limit"] is True
    assert "finger's limit" not in answer["reason"]


@pytest.mark.parametrize("lift, tolerance, words", [(0.25, 0.1, "250.0 mm above"), (-0.0125, 0.005, "12.5 mm below")])
def test_an_object_off_the_table_is_refused_with_its_height_in_millimetres(dataset, tables, lift, tolerance, words):
    object_id, pose = next(iter(sorted(tables["poses"])))
    with pytest.raises(OffTable) as error:
        plan(Store.load(dataset), request(tables, object_id, pose, lift=lift), Settings(height_tolerance=tolerance))
    body = error.value.body()
    assert body["object_id"] == object_id and body["pose"] == pose and body["z_offset"] == pytest.approx(lift, abs=1e-9)
    assert body["height_tolerance"] == tolerance
    assert body["detail"].startswith(f"'{object_id}' is observed {words} the table (pose {pose}'s support point at z = ")
    assert body["detail"].endswith(f" m, tolerance {tolerance * 1000:.1f} mm): it is not resting on the table z = 0, so no "
                                   "stored push applies; is the world frame's origin on the table?")


def test_an_orientation_that_is_no_stable_pose_is_refused_with_the_nearest_and_what_to_check(dataset, tables):
    observed, nearest = tilted(tables, "random_001", 0, math.radians(30))
    with pytest.raises(NoStablePose) as error:
        plan(Store.load(dataset), PlanRequest(object_id="random_001", pose=observed.tolist()), Settings())
    body = error.value.body()
    assert body["angle_error"] == pytest.approx(nearest, abs=1e-6) and body["angle_error"] > body["tolerance"]
    assert body["detail"] == (
        f"the observed orientation of 'random_001' is no stable pose: the nearest, pose {body['nearest_pose']}, is "
        f"{math.degrees(nearest):.1f} deg away (tolerance {math.degrees(body['tolerance']):.1f} deg); is the object resting "
        "on the table, and is the world frame z up?")
