"""The public Python API covers one object end to end without a dataset: load, stable
poses, topple tables, V_s, value iteration, and the plan for an observed pose."""

from __future__ import annotations

import re

import numpy as np
import pytest
from shapes import random_object

import pipeline as toppledb
from schema import retry
from schema.frames import PoseMatch
from schema.neighbourhood import MAX_ANGLE, RADIUS
from schema.vocabulary import NO_OP, POLICIES, STATUS_OK

CONFIG = toppledb.Config().with_overrides({
    "contacts.n_contacts": 40, "topple.n_trials": 5, "suction.n_candidates": 20, "suction.n_samples": 5, "seed": 3,
    "mdp.choice_neighbours": 1,  # 40 contacts leave few pushes five neighbours within 20 mm (MODEL.md (12.15))
})


@pytest.fixture(scope="module")
def box():
    """(object, poses, a pose to observe, the object's evaluation): a random object that
    has poses worth toppling out of (a box is graspable in every pose)."""
    obj = random_object(1)
    poses = toppledb.stable_poses(obj, CONFIG.poses)
    return obj, poses, 0, toppledb.evaluate_object(obj, CONFIG)


def world(transform: np.ndarray, yaw: float, xy=(0.3, -0.1), z: float = 0.0) -> np.ndarray:
    """Object -> world for the object resting in ``transform``'s pose, turned by ``yaw``."""
    planar = np.eye(4)
    planar[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
    planar[:3, 3] = [*xy, z]
    return planar @ transform


def test_one_object_end_to_end_agrees_with_its_parts(box):
    obj, poses, _, result = box
    assert [p.index for p in result.poses] == [p.index for p in poses.poses]
    v_s = np.array([s.quality for s in result.suction])
    for pose in range(len(poses.poses)):
        assert toppledb.grasp_quality(obj, poses, pose, CONFIG).quality == v_s[pose]
    # The same tables, pose by pose through ``evaluate``, and value iteration over them.
    evaluations = [toppledb.evaluate(obj, poses, pose, config=CONFIG, seed=CONFIG.seed) for pose in range(len(v_s))]
    for evaluation, table in zip(evaluations, result.topple):
        np.testing.assert_array_equal(evaluation.table.p_topple, table.p_topple)
    solved = toppledb.solve(evaluations, v_s, CONFIG)
    for mine, theirs in zip(solved, result.values):
        np.testing.assert_array_equal(mine.q, theirs.q)
        assert mine.policies == theirs.policies
    # Toppling first never loses, and V_T is a discounted expected V_s.
    for pose, values in enumerate(result.values):
        assert v_s[pose] - 1e-12 <= values.value <= 1 + 1e-12
    assert any(values.policies["value_iteration"].action != NO_OP for values in result.values), "value iteration pushes"
    # Its push is the choice by neighbourhood over its own Q_T (MODEL.md (12.15)), not the argmax.
    from pipeline.model.mdp import neighbourhood_choice

    for pose, (values, actions) in enumerate(zip(result.values, result.actions)):
        expected = neighbourhood_choice(pose, v_s, values.q, actions.points, actions.directions, result.choosable[pose], CONFIG.mdp)
        assert values.policies["value_iteration"] == expected
    with pytest.raises(ValueError, match="one evaluation per stable pose"):
        toppledb.solve(evaluations[1:], v_s, CONFIG)


@pytest.mark.parametrize("policy", POLICIES)
def test_plan_for_an_observed_pose_is_the_stored_decision_in_the_world(box, policy):
    _, _, _, result = box
    yaw, table = 0.7, 0.75
    for pose in result.poses:
        observed = world(pose.transform, yaw, z=table)
        planned = toppledb.plan(result, observed, policy=policy, table_height=table, config=CONFIG)
        assert planned.match.pose == pose.index
        assert planned.match.angle_error < 1e-6 and abs(planned.match.z_offset) < 1e-9
        assert planned.match.yaw == pytest.approx(yaw)
        choice = result.values[pose.index].policies[policy]
        assert planned.value == choice.value
        if choice.action == NO_OP:
            assert planned.action is None and planned.push is None
            continue
        assert planned.action == choice.action
        local = result.actions[pose.index].points[choice.action]
        expected = world(np.eye(4), yaw, z=table)[:3] @ np.append(local, 1.0)
        np.testing.assert_allclose(planned.push["point"], expected, atol=1e-12)
        np.testing.assert_allclose(planned.push["start"] - planned.push["end"],
                                   (CONFIG.contacts.approach_offset + CONFIG.contacts.push_depth) * planned.push["normal"])
        assert planned.p_topple == result.topple[pose.index].p_topple[choice.action]
        assert sum(p for _, p in planned.next_poses) == pytest.approx(1.0)
        # The neighbourhood mean: this pose's ok candidates within RADIUS and MAX_ANGLE, by hand.
        actions, p_topple = result.actions[pose.index], result.topple[pose.index].p_topple
        near = ((np.linalg.norm(actions.points - local, axis=1) <= RADIUS + 1e-9)
                & (actions.directions @ actions.directions[choice.action] >= np.cos(MAX_ANGLE) - 1e-9)
                & np.isfinite(p_topple))
        assert planned.p_topple_neighbourhood == pytest.approx(p_topple[near].mean(), abs=1e-12)


def test_plan_for_a_budget_is_greedy_with_one_push_left_and_never_worth_less_with_more(box):
    _, _, _, result = box
    v_s = np.array([s.quality for s in result.suction])
    pushed = 0
    for pose in result.poses:
        observed = world(pose.transform, 0.3)
        # The pushes the policies may choose compete (mdp.min_direction_z): the others' greedy is NaN here.
        greedy = np.where(result.choosable[pose.index], result.values[pose.index].greedy, np.nan)
        one = toppledb.plan(result, observed, pushes_left=1, config=CONFIG)
        pushed += one.action is not None
        if one.action is None:
            assert np.nanmax(greedy, initial=-np.inf) <= v_s[pose.index] + 1e-9 and one.value == v_s[pose.index]
        else:
            assert greedy[one.action] == pytest.approx(np.nanmax(greedy), abs=1e-12) and one.value == pytest.approx(greedy[one.action])
        values = [toppledb.plan(result, observed, pushes_left=h, config=CONFIG).value for h in (1, 2, 3)]
        assert values[0] <= values[1] + 1e-12 <= values[2] + 2e-12
    assert pushed > 0, "some pose should be worth a push"
    with pytest.raises(ValueError, match="pushes_left"):
        toppledb.plan(result, world(result.poses[0].transform, 0.0), policy="greedy", pushes_left=2, config=CONFIG)
    with pytest.raises(ValueError, match="pushes_left"):
        toppledb.plan(result, world(result.poses[0].transform, 0.0), pushes_left=0, config=CONFIG)


def test_plan_for_a_budget_believes_failures_as_the_config_does(box):
    """With a config that plans with its failures (the default) the budget is (12.14): argmax Q0_h
    fresh, argmax Q1_h over the untried pushes after a failure, by explicit backward induction
    (``tests.test_horizon``); a config that does not believe them plans the table's budget."""
    from dataclasses import replace

    from schema import horizon
    from tests.test_horizon import reference_belief_budget

    _, _, _, result = box
    assert CONFIG.mdp.plans_with_failures
    v_s = np.array([s.quality for s in result.suction])
    rows = [np.asarray(t.next_pose, dtype=float) for t in result.topple]
    # The pushes a budget may choose (mdp.budget_min_direction_z), which may be more than the policies'.
    choosable = [horizon.choosable_pushes(a.directions[:, 2], CONFIG.mdp.budget_min_direction_z) for a in result.actions]
    q0s, q1s = reference_belief_budget(rows, v_s, CONFIG.mdp.after_failure_power, 3, choosable)
    plain_config = replace(CONFIG, mdp=replace(CONFIG.mdp, believe_failures=False))
    plain_actions, plain_values = horizon.budget_choices(v_s, *horizon.csr_from_rows(rows), 3, np.concatenate(choosable))
    after_failures = differs = 0
    for pose in result.poses:
        x, observed = pose.index, world(pose.transform, 0.3)
        for h in (1, 2, 3):
            q0 = np.where(choosable[x], q0s[h - 1][x], np.nan)
            first = toppledb.plan(result, observed, pushes_left=h, config=CONFIG)
            assert first.value == pytest.approx(max(v_s[x], np.nanmax(q0, initial=-np.inf)), abs=1e-12)
            plain = toppledb.plan(result, observed, pushes_left=h, config=plain_config)
            assert (-1 if plain.action is None else plain.action) == plain_actions[h - 1, x]
            assert plain.value == pytest.approx(plain_values[h - 1, x], abs=1e-12)
            differs += abs(plain.value - first.value) > 1e-9
            if first.action is None:
                continue
            assert q0[first.action] == pytest.approx(first.value, abs=1e-12)
            after = toppledb.plan(result, observed, pushes_left=h, config=CONFIG, failed_actions=[first.action])
            actions = result.actions[x]
            allowed = choosable[x] & ~retry.ruled_out(actions.points, actions.directions, [first.action])
            q1 = np.where(allowed, q1s[h - 1][x], np.nan)
            best = np.nanmax(q1, initial=-np.inf)
            if after.action is None:
                assert best <= v_s[x] + 1e-9
            else:
                after_failures += 1
                assert after.value == pytest.approx(best, abs=1e-12) and q1[after.action] == pytest.approx(best, abs=1e-12)
    assert after_failures > 0 and differs > 0


def test_plan_after_failed_pushes_chooses_among_the_rest_and_says_how_likely_now(box):
    _, _, _, result = box
    power = CONFIG.mdp.after_failure_power
    replaced = 0
    for pose in result.poses:
        observed = world(pose.transform, -0.2)
        for policy, budget in (("value_iteration", None), ("greedy", None), ("value_iteration", 2)):
            first = toppledb.plan(result, observed, policy=policy, pushes_left=budget, config=CONFIG)
            same = toppledb.plan(result, observed, policy=policy, pushes_left=budget, config=CONFIG, failed_actions=[])
            assert (same.action, same.value, same.p_topple) == (first.action, first.value, first.p_topple)
            assert first.ruled_out == same.ruled_out == 0 and first.p_topple_given_failures is None
            if first.action is None:
                continue
            after = toppledb.plan(result, observed, policy=policy, pushes_left=budget, config=CONFIG, failed_actions=[first.action])
            actions = result.actions[pose.index]
            excluded = retry.ruled_out(actions.points, actions.directions, [first.action])
            assert after.ruled_out == int((excluded & result.choosable[pose.index]).sum()) >= 1
            if after.action is None:
                assert after.value == result.suction[pose.index].quality and after.p_topple_given_failures is None
                continue
            replaced += 1
            assert not excluded[after.action] and after.value <= first.value + 1e-12, "the best was ruled out"
            assert after.p_topple_given_failures == pytest.approx(after.p_topple ** power, abs=1e-15)
            if budget is None:
                mine, p = result.values[pose.index], result.topple[pose.index].p_topple
                stay = result.suction[pose.index].quality
                # Value iteration ranks by what it believes after a failure, by hand: Q1 = b Q0 + (1 - b) V1,
                # b = p^(k-1), V1 the best of V_s and each choosable push's gamma b Q0 / (1 - gamma + gamma b)
                # (MODEL.md (12.13); CONFIG believes failures).
                assert CONFIG.mdp.believe_failures
                b, gamma = p ** (power - 1), CONFIG.mdp.gamma
                v1 = max(stay, np.nanmax(np.where(result.choosable[pose.index], gamma * b * mine.q / (1 - gamma + gamma * b), np.nan)))
                believed = b * mine.q + (1 - b) * v1
                values = believed if policy == "value_iteration" else mine.greedy
                allowed = np.where(result.choosable[pose.index] & ~excluded, values, np.nan)
                assert after.value == np.nanmax(allowed), "the policy's own rule over the rest"
    assert replaced > 0
    observed = world(result.poses[0].transform, 0.0)
    with pytest.raises(ValueError, match="max_height"):
        toppledb.plan(result, observed, policy="max_height", failed_actions=[0], config=CONFIG)
    with pytest.raises(ValueError, match="no actions of pose"):
        toppledb.plan(result, observed, failed_actions=[10**6], config=CONFIG)
    not_ok = int(np.flatnonzero(result.actions[0].status != STATUS_OK)[0])
    with pytest.raises(ValueError, match="not ok"):
        toppledb.plan(result, observed, failed_actions=[not_ok], config=CONFIG)


def test_plan_matches_a_symmetric_object_at_any_roll():
    import trimesh

    from pipeline.model.mesh import model_from_mesh

    can = model_from_mesh(trimesh.creation.cylinder(radius=0.03, height=0.1, sections=16), mass=0.2, name="can")
    result = toppledb.evaluate_object(can, CONFIG)
    assert len(result.poses) == 2 and [len(e) for e in result.equivalent_transforms] == [16, 2]
    side = result.poses[0].transform
    for facets in (0, 5):
        roll = trimesh.transformations.rotation_matrix(facets * 2 * np.pi / 16, [0, 0, 1])  # about the can's axis
        planned = toppledb.plan(result, world(side @ roll, 0.4), policy="max_height", config=CONFIG)
        assert planned.match.pose == 0 and planned.match.angle_error < 1e-6  # arccos near 1: ~1e-8
        if planned.push is not None:  # placed through the turn that matched: on the can as observed
            local = np.linalg.inv(world(side @ roll, 0.4)) @ np.append(planned.push["point"], 1.0)
            assert abs(can.mesh.nearest.signed_distance([local[:3]])[0]) < 1e-6


def test_match_pose_defaults_height_offset_and_refusals(box):
    obj, poses, standing, result = box
    transform = poses.poses[standing].transform
    lifted = world(transform, 0.2, z=0.05)
    match = toppledb.match_pose(lifted, poses)
    assert isinstance(match, toppledb.ObservedPose) and match.pose == standing
    assert match.z_offset == pytest.approx(0.05)
    assert toppledb.match_pose(lifted, poses, table_height=0.05).z_offset == pytest.approx(0.0)
    with pytest.raises(toppledb.NotResting, match="50.0 mm off the table"):
        toppledb.plan(result, lifted)
    edge = 0
    for pose in result.poses:  # lifted by exactly the tolerance: on the table, whatever the rounding
        for z in (0.005, -0.005):
            at_edge = world(pose.transform, 0.7, z=z)
            edge += abs(toppledb.match_pose(at_edge, poses).z_offset) > 0.005
            assert toppledb.plan(result, at_edge, height_tolerance=0.005).match.pose == pose.index
        with pytest.raises(toppledb.NotResting, match=r" 5\.0010 mm off the table"):
            toppledb.plan(result, world(pose.transform, 0.7, z=0.005 + 1e-6), height_tolerance=0.005)
    assert edge > 0, "some pose rounds past the edge, or this would not test it"

    tilt = np.eye(4)
    tilt[:3, :3] = [[1, 0, 0], [0, np.cos(0.35), -np.sin(0.35)], [0, np.sin(0.35), np.cos(0.35)]]  # 20 deg
    tilted = world(transform, 0.0) @ np.linalg.inv(transform) @ tilt @ transform
    assert toppledb.match_pose(tilted, poses).pose == -1, "beyond the default 10 deg"
    assert toppledb.match_pose(tilted, poses, tolerance=np.radians(25)).pose == standing
    with pytest.raises(toppledb.NotResting, match="no stable pose"):
        toppledb.plan(result, tilted)
    with pytest.raises(ValueError, match="unknown policy"):
        toppledb.plan(result, lifted, policy="best")

    # The array form (README) is unchanged.
    old = toppledb.match_pose(world(transform, 0.2), poses.downs, poses.transforms, np.radians(10))
    assert isinstance(old, PoseMatch) and old.pose == standing


@pytest.mark.parametrize("policy", POLICIES)
def test_plan_says_where_to_grasp_in_the_world(box, policy):
    # The pose's best suction grasp, carried to the world as the push is: turned by the yaw and
    # moved to where the object stands; the policy's name whether it pushes or not.
    _, _, _, result = box
    yaw, xy, table = -1.1, (0.4, 0.25), 0.7
    turn = world(np.eye(4), yaw, xy=xy, z=table)
    for pose in result.poses:
        planned = toppledb.plan(result, world(pose.transform, yaw, xy=xy, z=table), policy=policy, table_height=table,
                                config=CONFIG)
        assert planned.policy == policy
        suction = result.suction[pose.index]
        if not np.all(np.isfinite(suction.point)):
            assert planned.grasp is None
            continue
        point, axis = planned.grasp
        np.testing.assert_allclose(point, turn[:3, :3] @ suction.point + turn[:3, 3], atol=1e-12)
        np.testing.assert_allclose(axis, turn[:3, :3] @ suction.axis, atol=1e-12)


def test_observe_returns_where_the_object_stands_and_refuses_what_is_not_a_pose(box):
    _, poses, standing, _ = box
    observed = world(poses.poses[standing].transform, 0.4, xy=(0.2, -0.3))
    match = toppledb.match_pose(observed, poses)
    np.testing.assert_allclose(match.translation, [0.2, -0.3], atol=1e-12)
    np.testing.assert_allclose(match.pose_to_world, world(np.eye(4), 0.4, xy=(0.2, -0.3)), atol=1e-12)
    assert match.z_offset == pytest.approx(0.0, abs=1e-12)  # the table is at z = 0 unless told
    for bad in (np.eye(3), np.full((4, 4), np.nan)):
        with pytest.raises(ValueError, match=r"observed must be a finite \(4, 4\) object-to-world transform"):
            toppledb.match_pose(bad, poses)


def test_evaluate_takes_its_overrides_and_explicit_pushes(box):
    obj, poses, pose, _ = box
    few = toppledb.evaluate(obj, poses, pose, n_contacts=12, n_trials=3, config=CONFIG, seed=CONFIG.seed)
    assert len(few.actions.status) in (12, 13)  # the contacts, and Max-Height's push where the pose has one
    assert few.table.outcomes.shape == (len(few.actions.status), 3)
    thesis = toppledb.evaluate(obj, poses, pose, n_contacts=12, n_trials=3, variant="baseline", config=CONFIG, seed=CONFIG.seed)
    np.testing.assert_array_equal(thesis.actions.points, few.actions.points)
    assert thesis.table.outcomes.shape == (len(thesis.actions.status), 1), "the thesis's baseline draws no noise: one trial"
    # Explicit pushes: snapped to the surface, pushed along the given direction or else the inward normal.
    surface = few.actions.points[:2]
    given = toppledb.evaluate(obj, poses, pose, points=surface, directions=-few.actions.normals[:2], config=CONFIG)
    np.testing.assert_allclose(given.actions.points, surface, atol=1e-9)
    np.testing.assert_allclose(given.actions.directions, -few.actions.normals[:2], atol=1e-9)
    inward = toppledb.evaluate(obj, poses, pose, points=surface, config=CONFIG)
    np.testing.assert_allclose(inward.actions.directions, -inward.actions.normals, atol=1e-12)
    assert given.table.p_topple.shape == (2,)


def test_explicit_pushes_are_predicted_among_the_poses_candidates_as_the_dataset_predicts_them(box):
    """The default smooths and maps a row over the pose's candidates (MODEL.md C.12-C.19): a candidate asked
    about explicitly gets the very row the object's evaluation stores, whatever else is asked beside it, and
    another push is a probe, averaged over the candidates near it."""
    obj, poses, _, result = box
    assert CONFIG.topple.needs_candidates
    for pose in range(len(poses.poses)):
        actions, table = result.actions[pose], result.topple[pose]
        ok = np.flatnonzero(actions.status == STATUS_OK)
        if len(ok) >= 4 and np.nanmax(table.p_topple[ok]) > 0:
            break
    chosen = ok[np.argsort(-table.p_topple[ok], kind="stable")[:4]]  # the pose's likeliest topples, where rows differ most
    # A probe 0.3 mm from the first of them, on the surface: a push no candidate is.
    normal = actions.normals[chosen[0]]
    along = np.cross(normal, [0.0, 0.0, 1.0] if abs(normal[2]) < 0.9 else [1.0, 0.0, 0.0])
    probe = actions.points[chosen[0]] + 3e-4 * along / np.linalg.norm(along)
    points = np.vstack([actions.points[chosen[:2]], probe, actions.points[chosen[2:]]])
    directions = np.vstack([actions.directions[chosen[:2]], actions.directions[chosen[0]], actions.directions[chosen[2:]]])
    asked = toppledb.evaluate(obj, poses, pose, points=points, directions=directions, config=CONFIG, seed=CONFIG.seed)
    rows = [0, 1, 3, 4]
    np.testing.assert_array_equal(asked.table.p_topple[rows], table.p_topple[chosen])
    np.testing.assert_array_equal(asked.table.next_pose[rows], table.next_pose[chosen])
    np.testing.assert_array_equal(asked.table.outcomes[rows], table.outcomes[chosen])
    alone = toppledb.evaluate(obj, poses, pose, points=points[rows[2:]], directions=directions[rows[2:]], config=CONFIG,
                              seed=CONFIG.seed)
    np.testing.assert_array_equal(alone.table.p_topple, table.p_topple[chosen[2:]])
    assert asked.table.next_pose[2].sum() == pytest.approx(1.0)
    with pytest.raises(ValueError, match="one direction per point"):
        toppledb.evaluate(obj, poses, pose, points=points, directions=directions[:1], config=CONFIG, seed=CONFIG.seed)
    # The dataset's seed is the default: the same rows without naming it.
    np.testing.assert_array_equal(toppledb.evaluate(obj, poses, pose, points=points, directions=directions, config=CONFIG).table.p_topple,
                                  asked.table.p_topple)
    # Averaged over the candidates near it, the probe reads much as its neighbour does.
    assert abs(asked.table.p_topple[2] - table.p_topple[chosen[0]]) < 0.15


def test_an_objects_result_carries_its_identity_and_what_each_stage_cost(box):
    obj, poses, _, _ = box
    timings, per_pose = {}, {}
    result = toppledb.evaluate_object(obj, CONFIG, object_id="renamed", timings=timings, pose_seconds=per_pose)
    assert result.object_id == "renamed" and toppledb.evaluate_object(obj, CONFIG).object_id == obj.name
    assert result.mass == obj.mass and result.repairs == obj.repairs
    np.testing.assert_array_equal(result.center_mass, obj.center_mass)
    np.testing.assert_array_equal(result.hull_vertices, obj.hull.vertices)
    np.testing.assert_array_equal(result.hull_faces, obj.hull.faces)
    assert result.timings is timings and set(timings) == {"poses", "contacts", "topple", "suction", "mdp"}
    assert all(seconds >= 0 for seconds in timings.values())
    # make bench's wall seconds: per pose for three stages, per object for the other two.
    n = len(poses.poses)
    assert {name: len(seconds) for name, seconds in per_pose.items()} == {
        "shared_contacts": 1, "actions": n, "topple": n, "suction": n, "mdp": 1}


# --- what the API refuses, and what it still takes ------------------------------------------


def test_evaluate_refuses_a_pose_the_object_does_not_have(box):
    obj, poses, pose, _ = box
    last = len(poses.poses) - 1
    for bad in (last + 1, 99, -1, True, 1.0, "0"):
        with pytest.raises(ValueError, match=rf"pose must be an integer from 0 to {last} \(the object has {last + 1} stable poses\), got"):
            toppledb.evaluate(obj, poses, bad, n_contacts=12, n_trials=3, config=CONFIG)
    with pytest.raises(ValueError, match=rf"pose must be an integer from 0 to {last}"):
        toppledb.grasp_quality(obj, poses, -1, CONFIG)
    # A numpy integer names the same pose, with the same table, and the result says which pose as an int.
    plain = toppledb.evaluate(obj, poses, pose, n_contacts=12, n_trials=3, config=CONFIG)
    numpy = toppledb.evaluate(obj, poses, np.int64(pose), n_contacts=12, n_trials=3, config=CONFIG)
    assert type(numpy.pose) is int and numpy.pose == pose
    np.testing.assert_array_equal(numpy.actions.points, plain.actions.points)
    np.testing.assert_array_equal(numpy.table.next_pose, plain.table.next_pose)
    np.testing.assert_array_equal(numpy.table.outcomes, plain.table.outcomes)


def test_evaluate_refuses_n_contacts_outside_the_configs_range(box):
    from pipeline.model.config import ContactConfig, field_range

    obj, poses, pose, _ = box
    accepted = field_range(ContactConfig, "n_contacts")  # the bounds --set and a TOML file are held to
    for bad in (0, -3, int(accepted.hi) + 1, True, 12.0):
        with pytest.raises(ValueError, match=rf"n_contacts must be an integer {re.escape(accepted.text())}, got"):
            toppledb.evaluate(obj, poses, pose, n_contacts=bad, n_trials=3, config=CONFIG)
    assert len(toppledb.evaluate(obj, poses, pose, n_contacts=np.int32(1), n_trials=3, config=CONFIG).actions.status) in (1, 2)


def test_evaluate_refuses_malformed_pushes(box):
    obj, poses, pose, result = box
    point = result.actions[pose].points[0]
    inward = result.actions[pose].directions[0]
    refusals = [
        ({"points": [[0.0, 0.0]]}, r"points must be a \(k, 3\) array .* got shape \(1, 2\)"),
        ({"points": []}, r"points must be a \(k, 3\) array"),
        ({"points": [[0.0, 0.0, 0.1], [0.0, 0.1]]}, r"points must be a \(k, 3\) array of numbers"),
        ({"points": [point, [np.nan, 0.0, 0.05]]}, r"points must be finite: row 1 is \[nan, 0.0, 0.05\]"),
        ({"points": [point], "directions": [[1.0, 0.0]]}, r"directions must be a \(k, 3\) array"),
        ({"points": [point], "directions": [inward, inward]}, r"one direction per point \(or none\): 1 points, 2 directions"),
        ({"points": [point], "directions": [[np.inf, 0.0, 0.0]]}, r"directions must be finite: row 0"),
        ({"points": [point, point], "directions": [inward, [0.0, 0.0, 0.0]]},
         r"directions must be non-zero: direction 1 is \[0.0, 0.0, 0.0\]"),
    ]
    for given, message in refusals:
        with pytest.raises(ValueError, match=message):
            toppledb.evaluate(obj, poses, pose, config=CONFIG, **given)
    # A direction is only a direction: one whose square leaves float64 is pushed along, as its unit vector is.
    from pipeline.model.contacts import explicit_actions

    transform = poses.poses[pose].transform
    plain = explicit_actions(obj, transform, [point, point], [inward, [1.0, 0.0, 0.0]])
    for scale in (1e200, 1e-170, 1e-320):
        scaled = explicit_actions(obj, transform, [point, point], [inward, [scale, 0.0, 0.0]])
        np.testing.assert_array_equal(scaled.directions, plain.directions)


def test_evaluate_refuses_a_point_off_the_surface_and_snaps_one_within_the_tolerance(box):
    from pipeline.model.contacts import SNAP_TOLERANCE, explicit_actions, snap_to_surface

    obj, poses, pose, result = box
    actions = result.actions[pose]
    ok = int(np.flatnonzero(actions.status == STATUS_OK)[0])
    point, normal, direction = actions.points[ok], actions.normals[ok], actions.directions[ok]
    assert SNAP_TOLERANCE == 1e-3
    where = r"points are in metres in the pose frame \(z up, table at z = 0, centre of mass over the origin\)"
    with pytest.raises(ValueError, match=rf"point 0 \[1.0, 1.0, 1.0\] is \d+ mm from the object's surface, more than the 1 mm tolerance; {where}"):
        toppledb.evaluate(obj, poses, pose, points=[[1.0, 1.0, 1.0]], config=CONFIG)
    # Just past the tolerance, out along the normal: refused, naming how far.
    with pytest.raises(ValueError, match=r"point 1 .* is 1.5 mm from the object's surface, more than the 1 mm tolerance"):
        toppledb.evaluate(obj, poses, pose, points=[point, point + 1.5e-3 * normal], config=CONFIG)
    # Within it: snapped back onto the surface, where the candidate is.
    near = toppledb.evaluate(obj, poses, pose, points=[point + 0.9e-3 * normal], directions=[direction], config=CONFIG)
    np.testing.assert_allclose(near.actions.points, [point], atol=1e-9)
    assert near.table.p_topple.shape == (1,) and np.isfinite(near.table.p_topple[0])
    # Internal callers that mean to snap however far (a test's hand-placed push) say so.
    transform, off = poses.poses[pose].transform, (point + 0.02 * normal)[None]
    with pytest.raises(ValueError, match=r"mm from the object's surface, more than the 1 mm tolerance"):
        explicit_actions(obj, transform, off, None)
    _, _, moved = snap_to_surface(obj, transform, explicit_actions(obj, transform, off, None, tolerance=np.inf).points)
    assert moved[0] < 1e-9, "snapped onto the surface"


def test_a_logged_push_is_scored_as_before(box):
    """The validation scorer snaps logged pushes through the same check: the logs' pushes lie within
    2.2e-6 m of the surface (scratch/s70/api/snap_distances.py), far inside the tolerance, so a push
    logged that far off is taken and snapped exactly as the unchecked snapping did."""
    from pipeline.model.contacts import explicit_actions
    from pipeline.studies.logreader import LogError, LoggedObject, Push, PushLog
    from pipeline.studies.scoring import Scorer

    obj, poses, pose, result = box
    actions = result.actions[pose]
    rows = np.flatnonzero(actions.status == STATUS_OK)[:3]
    points = actions.points[rows] + 2.2e-6 * actions.normals[rows]  # as far off as the furthest logged push
    pushes = [Push(obj.name, i, pose, p, d, np.array([pose, pose])) for i, (p, d) in enumerate(zip(points, actions.directions[rows]))]
    log = PushLog({obj.name: LoggedObject(obj.name, obj, poses, "")}, pushes)
    (group,) = Scorer(log).groups
    unchecked = explicit_actions(obj, poses.poses[pose].transform, points, actions.directions[rows], tolerance=np.inf)
    for name in ("points", "normals", "directions", "status"):
        np.testing.assert_array_equal(getattr(group.actions, name), getattr(unchecked, name))
    asked = toppledb.evaluate(obj, poses, pose, points=points, directions=actions.directions[rows], config=CONFIG)
    np.testing.assert_array_equal(asked.actions.points, unchecked.points)
    # A log whose push lies a centimetre off the surface was recorded on another mesh or frame: refused, naming it.
    far = [Push(obj.name, 7, pose, points[0] + 0.01 * actions.normals[rows[0]], actions.directions[rows[0]], np.array([pose]))]
    with pytest.raises(LogError, match=rf"^{obj.name}, pose {pose}, pushes \[7\]: a logged push is not on the surface of the mesh read "
                                        rf"here \(point 0 .* is 9.8\d* mm from the object's surface, more than the 1 mm tolerance\): "
                                        r"was the log recorded with another mesh or scale\?$"):
        Scorer(PushLog(log.objects, far))


def test_settle_refuses_what_is_not_a_rotation(box):
    obj, poses, _, _ = box
    for pose in poses.poses:  # a rotation, in float64 or float32: the pose it is
        assert toppledb.settle(poses, obj, pose.transform[:3, :3]) == pose.index
        assert toppledb.settle(poses, obj, pose.transform[:3, :3].astype(np.float32)) == pose.index
    with pytest.raises(ValueError, match=r"got a \(4, 4\) matrix: pass its upper-left 3x3 \(transform\[:3, :3\]\)"):
        toppledb.settle(poses, obj, np.eye(4))
    with pytest.raises(ValueError, match=r"is not a rotation: its columns are not orthonormal .*; got \[\[2., 0., 0.\]"):
        toppledb.settle(poses, obj, 2 * np.eye(3))
    with pytest.raises(ValueError, match=r"is not a rotation: det = -1, expected \+1 \(a reflection\?\)"):
        toppledb.settle(poses, obj, np.diag([-1.0, 1.0, 1.0]))
    for bad in (np.eye(2), np.full((3, 3), np.nan), [[1, 0, 0], [0, 1]]):
        with pytest.raises(ValueError, match=r"must be a finite \(3, 3\) rotation, got"):
            toppledb.settle(poses, obj, bad)


def test_plan_says_a_reflection_is_no_rotation_as_the_service_does(box):
    from schema.api import check_rigid

    _, poses, standing, result = box
    reflection = np.diag([-1.0, 1.0, 1.0, 1.0])
    with pytest.raises(ValueError) as service:
        check_rigid(reflection.tolist())
    for call in (lambda m: toppledb.plan(result, m, config=CONFIG), lambda m: toppledb.match_pose(m, poses)):
        with pytest.raises(ValueError, match=r"det = -1, expected \+1 \(a reflection\?\)") as refused:
            call(reflection)
        assert not isinstance(refused.value, toppledb.NotResting) and str(service.value) in str(refused.value)
        with pytest.raises(ValueError, match=r"columns are not orthonormal"):
            call(world(2 * poses.poses[standing].transform, 0.0))
        skewed = world(poses.poses[standing].transform, 0.0)
        skewed[3] = [0.0, 0.0, 0.1, 1.0]
        with pytest.raises(ValueError, match=r"the last row must be \[0, 0, 0, 1\]"):
            call(skewed)
