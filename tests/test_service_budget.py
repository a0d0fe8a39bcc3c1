# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""POST /plan with ``pushes_left``: value iteration for a budget (schema.horizon), served."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from schema.horizon import MAX_PUSHES_LEFT
from tests.test_service import (  # noqa: F401 (fixtures)
    BUDGET_DIRECTION_Z,
    JSON,
    MIN_DIRECTION_Z,
    client,
    dataset,
    planar_transform,
    stored_transform,
    tables,
)


def plan(client, tables, object_id: str, pose: int, **extra) -> dict:
    observed = planar_transform(0.7, 0.3, -0.2) @ stored_transform(tables, object_id, pose)
    response = client.post("/plan", content=json.dumps({"object_id": object_id, "pose": observed.tolist(), **extra}), headers=JSON)
    assert response.status_code == 200, response.text
    return response.json()


def test_one_push_left_is_the_greedy_choice(client, tables):
    pushed = 0
    for (object_id, pose), row in tables["poses"].items():
        answer = plan(client, tables, object_id, pose, pushes_left=1)
        assert answer["pushes_left"] == 1
        greedy = {a: r["greedy"] for (o, p, a), r in tables["actions"].items() if (o, p) == (object_id, pose) and r["greedy"] is not None}
        # Only the pushes the budget may choose (mdp.budget_min_direction_z) compete.
        choosable = {a: g for a, g in greedy.items()
                     if np.float32(tables["actions"][(object_id, pose, a)]["direction_z"]) >= np.float32(BUDGET_DIRECTION_Z)}
        best = max(choosable.values(), default=-np.inf)
        assert answer["action"] is None or answer["action"] in choosable, (object_id, pose)
        if answer["action"] is None:
            assert best <= row["v_s"] + 1e-6, (object_id, pose)
            assert answer["expected_v_s_final"] is None
        else:
            pushed += 1
            # float32 transitions in the service, float64 in the tables: equal up to rounding.
            assert greedy[answer["action"]] == pytest.approx(best, abs=1e-6)
            assert answer["expected_v_s_final"] == pytest.approx(best, abs=1e-6)
            assert answer["expected_v_s_final"] == pytest.approx(answer["expected_v_s_after"], abs=1e-6)
    assert pushed > 0, "the test dataset should have poses worth pushing from"


def test_a_budget_chooses_only_pushes_the_build_lets_the_budget_choose(dataset, tables):
    """The served budget with a stricter mdp.budget_min_direction_z (0.2: mostly pushes from below):
    one push left is the best greedy value among those pushes, though better ones exist, whatever
    the policies' own cut."""
    import dataclasses

    from service.store import Store

    store = Store.load(dataset)
    masked = 0
    for object_id, obj in store.objects.items():
        strict = dataclasses.replace(obj, min_direction_z=-1.0, budget_direction_z=0.2)
        actions, values = strict.budget(1)
        for pose in range(len(strict.v_s)):
            rows = tables["actions"]
            greedy = {a: rows[(object_id, pose, a)]["greedy"] for a in range(int(strict.n_actions[pose]))
                      if rows[(object_id, pose, a)]["greedy"] is not None}
            allowed = {a: g for a, g in greedy.items() if np.float32(rows[(object_id, pose, a)]["direction_z"]) >= np.float32(0.2)}
            best = max(allowed.values(), default=-np.inf)
            masked += max(greedy.values(), default=-np.inf) > best + 1e-6
            if actions[pose] < 0:
                assert best <= strict.v_s[pose] + 1e-6
            else:
                assert actions[pose] in allowed and allowed[actions[pose]] == pytest.approx(best, abs=1e-6)
    assert masked > 0, "some pose's best push should be one the stricter build does not let the budget choose"


def test_the_default_budget_may_choose_the_pushes_from_above_a_cut_keeps_from_value_iteration(dataset):
    """The default build's budget takes every ok push (mdp.budget_min_direction_z = -1) where the test
    dataset's policies take only those with u_z >= -0.3 (docs/VALIDATION.md, "Choosing from above again")."""
    from schema.vocabulary import STATUS_OK
    from service.store import Store

    store = Store.load(dataset)
    assert store.manifest.parameters.mdp.budget_min_direction_z == BUDGET_DIRECTION_Z == -1.0 < MIN_DIRECTION_Z
    wider = 0
    for obj in store.objects.values():
        budget, policies = obj.budget_choosable(slice(None)), obj.choosable(slice(None))
        assert np.all(policies <= budget)
        # At -1 the store skips reading the directions: the same pushes as comparing every u_z.
        np.testing.assert_array_equal(budget, (obj.status == STATUS_OK) & (obj.directions[:, 2] >= np.float32(-1.0)))
        wider += int(np.count_nonzero(budget & ~policies))
    assert wider > 0, "the test dataset should have ok pushes from above"


def final_value(client, tables, object_id: str, pose: int, budget: int) -> float:
    """V_budget of a pose as served: expected_v_s_final when it pushes, else its V_s."""
    if budget == 0:
        return tables["poses"][(object_id, pose)]["v_s"]
    answer = plan(client, tables, object_id, pose, pushes_left=budget)
    return answer["v_s"] if answer["action"] is None else answer["expected_v_s_final"]


def reference(tables, object_id: str, budget: int, power: float | None = None):
    """The budget of (12.14) by explicit backward induction over the analysts' tables
    (``tests.test_horizon.reference_belief_budget``; k = ``power``, default the build's
    after_failure_power; k = 1 is the table's budget, (12.8)):
    per pose its candidates' rows, V_s, choosable mask, and Q0, Q1 for h = 1..budget."""
    from tests.test_horizon import reference_belief_budget

    poses = sorted(p for o, p in tables["poses"] if o == object_id)
    v_s = np.array([tables["poses"][(object_id, x)]["v_s"] for x in poses])
    rows, choosable, candidates = [], [], []
    for x in poses:
        actions = sorted(a for o, p, a in tables["actions"] if (o, p) == (object_id, x))
        matrix = np.full((len(actions), len(poses)), np.nan)
        for a in actions:
            row = tables["transitions"].get((object_id, x, a))
            if tables["actions"][(object_id, x, a)]["q"] is not None and row:
                matrix[a] = 0.0
                for target, probability in row.items():
                    matrix[a, target] = probability
                matrix[a] /= matrix[a].sum()  # float32 storage, renormalised as the service does
        rows.append(matrix)
        choosable.append(np.array([np.float32(tables["actions"][(object_id, x, a)]["direction_z"]) >= np.float32(MIN_DIRECTION_Z)
                                   for a in actions], dtype=bool))
        candidates.append(actions)
    power = tables["manifest"]["parameters"]["mdp"]["after_failure_power"] if power is None else power
    q0s, q1s = reference_belief_budget(rows, v_s, power, budget, choosable)
    return v_s, choosable, q0s, q1s


def test_a_budget_believes_its_failures_as_the_build_does(client, tables):
    """The default build believes failures: with h pushes left /plan takes argmax Q0_h and reports
    V0_h, and once a push has failed argmax Q1_h over the pushes no failure rules out, reporting
    that Q1_h (docs/MODEL.md (12.14), by hand from the analysts' tables)."""
    from schema import retry

    assert tables["manifest"]["parameters"]["mdp"]["believe_failures"] is True
    fresh = failed = 0
    for object_id in sorted({o for o, _ in tables["poses"]}):
        v_s, choosable, q0s, q1s = reference(tables, object_id, 3)
        for x in range(len(v_s)):
            for h in (1, 2, 3):
                q0 = np.where(choosable[x], q0s[h - 1][x], np.nan)
                best = max(v_s[x], np.nanmax(q0, initial=-np.inf))
                answer = plan(client, tables, object_id, x, pushes_left=h)
                if answer["action"] is None:
                    assert best <= v_s[x] + 1e-5, (object_id, x, h)
                    continue
                fresh += 1
                # float32 transitions: equal up to their rounding
                assert answer["expected_v_s_final"] == pytest.approx(best, abs=1e-5), (object_id, x, h)
                assert q0[answer["action"]] == pytest.approx(best, abs=1e-5)
                after = plan(client, tables, object_id, x, pushes_left=h, failed_actions=[answer["action"]])
                points = np.array([[tables["actions"][(object_id, x, a)][f"point_{c}"] for c in "xyz"] for a in range(len(q0))])
                directions = np.array([[tables["actions"][(object_id, x, a)][f"direction_{c}"] for c in "xyz"] for a in range(len(q0))])
                allowed = choosable[x] & ~retry.ruled_out(points, directions, [answer["action"]])
                q1 = np.where(allowed, q1s[h - 1][x], np.nan)
                best_after = np.nanmax(q1, initial=-np.inf)
                if after["action"] is None:
                    assert best_after <= v_s[x] + 1e-5, (object_id, x, h)
                else:
                    failed += 1
                    assert after["expected_v_s_final"] == pytest.approx(best_after, abs=1e-5), (object_id, x, h)
                    assert q1[after["action"]] == pytest.approx(best_after, abs=1e-5)
    assert fresh > 0 and failed > 0


def test_a_build_that_does_not_believe_failures_serves_the_thesis_s_budget(dataset, tables):
    """``failure_power`` None (the thesis preset, k = 1, or a build from before (12.13)): the budget is
    (12.8) over the table, and a failure does not change how the budget ranks the untried pushes."""
    import dataclasses

    from schema import horizon
    from service.store import Store

    store = Store.load(dataset)
    differs = 0
    for obj in store.objects.values():
        assert obj.failure_power == store.after_failure_power  # the default build plans with its failures
        plain = dataclasses.replace(obj, failure_power=None)
        csr = (obj.action_offsets, obj.transition_offsets, obj.next_pose, obj.transition_probability)
        actions, values = horizon.budget_choices(obj.v_s, *csr, horizon.MAX_PUSHES_LEFT, obj.choosable(slice(None)))
        for h in (1, 2, 3):
            np.testing.assert_array_equal(plain.budget(h)[0], actions[h - 1])
            np.testing.assert_array_equal(plain.budget(h)[1], values[h - 1])
            differs += int(np.sum(np.abs(obj.budget(h)[1] - values[h - 1]) > 1e-9))
            previous = obj.v_s if h == 1 else values[h - 2]
            for x in range(obj.n_poses):
                rows = obj.pose_rows(x)
                expected = horizon.pose_q(previous, rows, obj.transition_offsets, obj.next_pose, obj.transition_probability)
                np.testing.assert_array_equal(plain.budget_q(x, h, after_failure=True), expected)
                np.testing.assert_array_equal(plain.budget_q(x, h, after_failure=False), expected)
        # (12.8) by explicit backward induction over the analysts' tables: (12.14) at k = 1.
        v_s, choosable, q0s, _ = reference(tables, obj.object_id, 3, power=1.0)
        for h in (1, 2, 3):
            expected = [max(v_s[x], np.nanmax(np.where(choosable[x], q0s[h - 1][x], np.nan), initial=-np.inf)) for x in range(len(v_s))]
            np.testing.assert_allclose(plain.budget(h)[1], expected, atol=1e-5)
    assert differs > 0, "believing failures should change some pose's budget value"


def test_a_bigger_budget_is_never_worth_less(client, tables):
    for object_id, pose in list(tables["poses"])[:12]:
        values = [final_value(client, tables, object_id, pose, h) for h in range(5)]
        assert all(b >= a - 1e-9 for a, b in itertools.pairwise(values)), (object_id, pose, values)


def test_a_budget_push_reports_its_neighbourhood_as_the_served_policies_do(client, tables):
    # Where the budget's push is value iteration's, the per-request mean must equal the served column's.
    same = 0
    for object_id, pose in tables["poses"]:
        stationary = plan(client, tables, object_id, pose)
        for budget in (1, 2, 3, MAX_PUSHES_LEFT):
            answer = plan(client, tables, object_id, pose, pushes_left=budget)
            if answer["action"] is None:
                assert answer["p_topple_neighbourhood"] is None
            elif answer["action"] == stationary["action"]:
                assert answer["p_topple_neighbourhood"] == stationary["p_topple_neighbourhood"]
                same += 1
            else:
                assert 0.0 <= answer["p_topple_neighbourhood"] <= 1.0
    assert same > 0


def test_without_a_budget_nothing_changes(client, tables):
    object_id, pose = next(iter(tables["poses"]))
    answer = plan(client, tables, object_id, pose)
    assert answer["pushes_left"] is None and answer["expected_v_s_final"] is None
    assert answer["action"] == (None if tables["poses"][(object_id, pose)]["value_iteration_action"] == -1
                                else tables["poses"][(object_id, pose)]["value_iteration_action"])


@pytest.mark.parametrize("extra", [
    {"pushes_left": 0}, {"pushes_left": MAX_PUSHES_LEFT + 1}, {"pushes_left": None}, {"pushes_left": 1.5},
    {"pushes_left": 2, "policy": "greedy"},
    # Integers only, as failed_actions: a client's true, 2.0 or "2" is a bug to report, not a budget to guess.
    {"pushes_left": True}, {"pushes_left": 2.0}, {"pushes_left": "2"},
])
def test_bad_budgets_are_422(client, tables, extra):
    object_id, pose = next(iter(tables["poses"]))
    body = {"object_id": object_id, "pose": stored_transform(tables, object_id, pose).tolist(), **extra}
    response = client.post("/plan", content=json.dumps(body), headers=JSON)
    assert response.status_code == 422, response.text
    assert "pushes_left" in response.json()["detail"] or "policy" in response.json()["detail"]


@pytest.mark.parametrize("mdp, believes", [
    ({}, True),  # the default build: believe_failures true, k 2.1
    ({"believe_failures": False}, False),  # the thesis preset's rule
    ({"after_failure_power": 1.0}, False),  # k = 1 believes nothing
    ({"after_failure_power": None, "believe_failures": False}, False),  # a manifest from before the map
])
def test_the_store_reads_from_the_manifest_whether_its_budgets_believe_failures(dataset, tmp_path, mdp, believes):
    import shutil

    from schema import horizon
    from service.store import Store

    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["parameters"]["mdp"].update(mdp)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    store = Store.load(copy)
    for obj in store.objects.values():
        assert (obj.failure_power is not None) == believes
        csr = (obj.action_offsets, obj.transition_offsets, obj.next_pose, obj.transition_probability)
        plain = horizon.budget_choices(obj.v_s, *csr, 3, obj.choosable(slice(None)))[1]
        if not believes:
            np.testing.assert_array_equal(obj.budget(3)[1], plain[2])
    with pytest.raises(ValueError, match="pushes_left must be 1"):
        next(iter(store.objects.values())).budget(0)


def test_the_store_reads_from_the_manifest_which_pushes_a_budget_may_choose(dataset, tmp_path):
    import shutil

    from schema.vocabulary import STATUS_OK
    from service.store import Store

    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["parameters"]["mdp"]["budget_min_direction_z"] = 0.2
    (copy / "manifest.json").write_text(json.dumps(manifest))
    for obj in Store.load(copy).objects.values():
        assert obj.budget_direction_z == 0.2 and obj.min_direction_z == MIN_DIRECTION_Z
        expected = (obj.status == STATUS_OK) & (obj.directions[:, 2] >= np.float32(0.2))
        np.testing.assert_array_equal(obj.budget_choosable(slice(None)), expected)


def test_belief_horizon_vi_plans_what_plan_serves_a_client_that_sends_its_budget_and_failures(dataset):
    """``belief_horizon_vi``'s tables (``pipeline.studies.robust_policy.belief_budget_tables``: its push per fresh
    pose with h pushes left, and the Q1_h it ranks the untried pushes by once a push from the pose has failed)
    choose, for every pose and every h, the push ``/plan`` serves a client that sends ``pushes_left`` h: the
    stored budget's push (``ObjectData.budget``) while nothing failed, ``service.planning.untried_push`` with
    ``failed_actions`` after (the failed push taken to be the budget's own).  The tiny dataset's budgets all push
    as value iteration does, so each object is also planned under random grasp values V_s, where the push depends
    on h and on the failure, which the test asserts it meets.  With
    ``tests/test_robust_policy.py::test_aware_and_belief_vi_play_their_own_rule_after_a_failure``, which holds
    the plays to these tables, the study's ``belief_horizon_vi`` is docs/SERVICE.md's client that sends its
    failures and its pushes left."""
    import dataclasses

    from pipeline.studies.policies_physics import open_trials
    from pipeline.studies.robust_policy import belief_budget_tables, next_pose_rows, read_candidates
    from schema import horizon, neighbourhood, retry
    from schema.api import PlanRequest
    from schema.vocabulary import NO_OP
    from service.planning import untried_push
    from service.store import Store

    budget = 3
    store = Store.load(dataset)
    data, config, _, _, _ = open_trials(dataset, 8, 1)  # the dataset as the study opens it, and its config
    mdp = dataclasses.replace(config.mdp, after_failure_power=data.manifest.parameters.mdp.after_failure_power)
    rng = np.random.default_rng(0)
    compared = by_budget = by_failure = 0
    for object_id, stored in store.objects.items():
        candidates = read_candidates(data, object_id)
        rows = next_pose_rows(data, object_id, [len(c.q) for c in candidates])
        choosable = [horizon.choosable_pushes(c.directions[:, 2], mdp.budget_min_direction_z) for c in candidates]
        for v_s in (stored.v_s, *rng.random((3, len(stored.v_s)))):
            obj = dataclasses.replace(stored, v_s=np.asarray(v_s, dtype=stored.v_s.dtype))
            actions, q1s = belief_budget_tables(np.asarray(obj.v_s, dtype=float), rows, mdp, budget, choosable)  # row k: budget - k left
            for k in range(budget):
                left = budget - k
                served = obj.budget(left)[0]
                for x, c in enumerate(candidates):
                    fresh = int(actions[k, x])
                    assert fresh == int(served[x]), (object_id, x, left)
                    compared += 1
                    by_budget += fresh != int(actions[0, x])
                    if fresh == NO_OP:
                        continue
                    ruled_out = neighbourhood.neighbours(c.points, c.directions, fresh)
                    ours = retry.best_untried(q1s[k][x], choosable[x] & ~ruled_out, float(obj.v_s[x]), horizon.IMPROVEMENT)
                    request = PlanRequest(object_id=object_id, pose=np.eye(4).tolist(), pushes_left=left, failed_actions=[fresh])
                    assert ours == untried_push(obj, x, request, store.gamma, store.after_failure_power, store.retry_failed,
                                                believes=store.believe_failures)[0], (object_id, x, left)
                    fresh_values = obj.budget_q(x, left, after_failure=False)
                    by_failure += ours != retry.best_untried(fresh_values, choosable[x] & ~ruled_out, float(obj.v_s[x]),
                                                             horizon.IMPROVEMENT)
    assert compared > 0
    assert by_budget > 0, "some push depends on the pushes left: the test tells the budgets apart"
    assert by_failure > 0, "some push after a failure is not the one a fresh pose would take: the test tells Q1_h from Q0_h"
