# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""POST /plan with ``pushes_left``: value iteration for a budget (schema.horizon), served."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest

from schema.horizon import MAX_PUSHES_LEFT
from tests.test_service import (  # noqa: F401 (fixtures)
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
        # Only the pushes the policies may choose (mdp.min_direction_z) compete.
        choosable = {a: g for a, g in greedy.items()
                     if np.float32(tables["actions"][(object_id, pose, a)]["direction_z"]) >= np.float32(MIN_DIRECTION_Z)}
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


def test_a_budget_chooses_only_pushes_the_build_lets_the_policies_choose(dataset, tables):
    """The served budget with a stricter mdp.min_direction_z (0.2: mostly pushes from below):
    one push left is the best greedy value among those pushes, though better ones exist."""
    import dataclasses

    from service.store import Store

    store = Store.load(dataset)
    masked = 0
    for object_id, obj in store.objects.items():
        strict = dataclasses.replace(obj, min_direction_z=0.2)
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
    assert masked > 0, "some pose's best push should be one the stricter build does not let the policies choose"


def final_value(client, tables, object_id: str, pose: int, budget: int) -> float:
    """V_budget of a pose as served: expected_v_s_final when it pushes, else its V_s."""
    if budget == 0:
        return tables["poses"][(object_id, pose)]["v_s"]
    answer = plan(client, tables, object_id, pose, pushes_left=budget)
    return answer["v_s"] if answer["action"] is None else answer["expected_v_s_final"]


@pytest.mark.parametrize("budget", [2, 3])
def test_the_final_value_is_the_next_poses_values_for_one_push_less(client, tables, budget):
    checked = 0
    for object_id, pose in list(tables["poses"])[:12]:
        answer = plan(client, tables, object_id, pose, pushes_left=budget)
        if answer["action"] is None:
            continue
        expected = sum(n["probability"] * final_value(client, tables, object_id, n["next_pose"], budget - 1) for n in answer["next_poses"])
        assert answer["expected_v_s_final"] == pytest.approx(expected, abs=1e-5)
        assert answer["expected_v_s_final"] > answer["v_s"]
        checked += 1
    assert checked > 0


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
])
def test_bad_budgets_are_422(client, tables, extra):
    object_id, pose = next(iter(tables["poses"]))
    body = {"object_id": object_id, "pose": stored_transform(tables, object_id, pose).tolist(), **extra}
    response = client.post("/plan", content=json.dumps(body), headers=JSON)
    assert response.status_code == 422, response.text
    assert "pushes_left" in response.json()["detail"] or "policy" in response.json()["detail"]
