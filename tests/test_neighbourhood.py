# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""schema.neighbourhood: the mean P(topple) around a candidate push, and /plan reporting it."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schema.neighbourhood import MAX_ANGLE, RADIUS, neighbour_mean, neighbours
from tests.test_service import client, dataset, planar_transform, stored_transform, tables, xyz  # noqa: F401 (fixtures)


def test_neighbours_are_near_in_contact_and_direction_and_ok():
    x = np.array([1.0, 0.0, 0.0])
    points = np.array([[0, 0, 0], [0.015, 0, 0], [0.03, 0, 0], [0.005, 0, 0], [0.001, 0, 0]], dtype=float)
    turned = np.array([math.cos(0.6), math.sin(0.6), 0.0])  # 0.6 rad > MAX_ANGLE away
    directions = np.array([x, x, x, turned, x])
    values = np.array([0.9, 0.3, 0.0, 0.0, np.nan])  # the last is not ok: nobody's neighbour
    mean, count = neighbour_mean(points, directions, values)
    # 0: itself and 1 (15 mm); not 2 (30 mm), 3 (turned), 4 (not ok).
    assert count[0] == 2 and mean[0] == pytest.approx((0.9 + 0.3) / 2)
    assert count[2] == 2 and mean[2] == pytest.approx(0.15), "30 mm from 0, but 15 mm from 1"
    assert np.isnan(mean[4]) and count[4] == 0
    one, n = neighbour_mean(points, directions, values, rows=[1])
    assert one[0] == pytest.approx(mean[1]) and n[0] == count[1], "one row is that row of the whole"
    wider, _ = neighbour_mean(points, directions, values, radius=0.05, max_angle=1.0)
    assert wider[0] == pytest.approx(np.mean([0.9, 0.3, 0.0, 0.0]))
    assert RADIUS == 0.02 and MAX_ANGLE == 0.5
    # One candidate's neighbourhood, ok or not (what a failed push rules out): 0, 1 and 4.
    assert neighbours(points, directions, 0).tolist() == [True, True, False, False, True]
    assert neighbours(points, directions, 3).tolist() == [False, False, False, True, False], "only itself: turned"
    assert neighbours(points, directions, 0, radius=0.0).tolist() == [True, False, False, False, False]


def test_plan_reports_the_mean_p_topple_around_its_push(client, tables):
    rng = np.random.default_rng(3)
    checked = 0
    for (object_id, pose) in tables["poses"]:
        observed = planar_transform(rng.uniform(-math.pi, math.pi), *rng.uniform(-0.3, 0.3, 2)) @ stored_transform(
            tables, object_id, pose)
        body = client.post("/plan", json={"object_id": object_id, "pose": observed.tolist(), "policy": "greedy"}).json()
        if body["action"] is None:
            assert body["p_topple_neighbourhood"] is None
            continue
        # By hand from the analysts' tables: this pose's ok candidates within 2 cm and 0.5 rad.
        rows = [r for (o, p, _), r in tables["actions"].items() if o == object_id and p == pose and r["status"] == "ok"]
        chosen = tables["actions"][(object_id, pose, body["action"])]
        near = [r["p_topple"] for r in rows
                if np.linalg.norm(xyz(r, "point") - xyz(chosen, "point")) <= RADIUS + 1e-6
                and xyz(r, "direction") @ xyz(chosen, "direction") >= math.cos(MAX_ANGLE) - 1e-6]
        assert body["p_topple_neighbourhood"] == pytest.approx(np.mean(near), abs=1e-6)
        assert f"({body['p_topple_neighbourhood']:.3g} around it)" in body["reason"]
        checked += 1
    assert checked >= 5
