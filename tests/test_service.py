"""The HTTP service over a tiny dataset built here (3 random objects, 30 pushes x 5 trials).

Every answer is checked against the dataset's own tables (read with pyarrow), the plan
round trip against the frame arithmetic of pipeline/frames.py, and malformed requests
against the error contract: 404 unknown ids, 409 no stable pose, 422 malformed input,
never a 500.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pyarrow.dataset as ds
import pyarrow.parquet as pq
import pytest
from fastapi.testclient import TestClient

from pipeline.build.corpus import read_list
from pipeline.build.dataset import build_dataset
from pipeline.model.config import Config
from schema import SCHEMA_VERSION
from schema.vocabulary import STATUS_NAMES, STATUS_OK
from service import DatasetError, create_app
from service.__main__ import main
from service.routers.objects import grasp_model
from service.store import Store, widen

SPARSE_CHOICE_FROM_THE_SIDE = {"mdp.min_direction_z": -0.3, "mdp.choice_neighbours": 1}
"""The test dataset's value iteration: the default's choice by neighbourhood (MODEL.md (12.15)), but 30
contacts a pose leave few pushes the five neighbours within 20 mm it asks for, so one will do; and from the
side, so that the tests can tell the pushes the budgets may choose from those the policies may."""
MIN_DIRECTION_Z = SPARSE_CHOICE_FROM_THE_SIDE["mdp.min_direction_z"]
"""The pushes the test dataset's policies may choose."""
BUDGET_DIRECTION_Z = Config().mdp.budget_min_direction_z
"""The pushes its budgets (``pushes_left``) may choose."""

OBJECTS = ["random_000", "random_001", "random_002"]
ROOT = Path(__file__).resolve().parent.parent
JSON = {"content-type": "application/json"}


@pytest.fixture(scope="session")
def dataset(tmp_path_factory) -> Path:
    """The tiny dataset, built once per session (the tests/test_service_*.py modules import
    this fixture; the fixed directory under the session's base temp lets them share it)."""
    directory = tmp_path_factory.getbasetemp() / "service-dataset"
    if (directory / "dataset" / "manifest.json").is_file():
        return directory / "dataset"
    directory.mkdir(exist_ok=True)
    corpus = directory / "corpus.csv"
    corpus.write_text(
        "object_id,source,path,scale,mass\n"
        + "".join(f"{n},pybullet_data/random_urdfs,random_urdfs/{n[-3:]}/{n[-3:]}.obj,0.015,0.1\n" for n in OBJECTS)
    )
    config = Config().with_overrides(
        {"contacts.n_contacts": 30, "topple.n_trials": 5, "suction.n_candidates": 20, "suction.n_samples": 5,
         **SPARSE_CHOICE_FROM_THE_SIDE}
    )
    out = directory / "dataset"
    build_dataset(read_list(corpus, default_mass=0.25), config, out, workers=1, progress=False, log=lambda _: None)
    return out


@pytest.fixture(scope="session")
def client(dataset):
    with TestClient(create_app(dataset)) as client:  # one event loop thread for the session
        yield client


@pytest.fixture(scope="session")
def tables(dataset) -> dict:
    """The dataset as analysts read it: rows keyed by (object_id, pose[, action])."""
    poses = {(r["object_id"], r["pose"]): r for r in pq.read_table(dataset / "poses.parquet").to_pylist()}
    actions = ds.dataset(dataset / "actions", format="parquet", partitioning="hive").to_table().to_pylist()
    transitions: dict[tuple, dict[int, float]] = {}
    for r in ds.dataset(dataset / "transitions", format="parquet", partitioning="hive").to_table().to_pylist():
        transitions.setdefault((r["object_id"], r["pose"], r["action"]), {})[r["next_pose"]] = r["probability"]
    return {
        "poses": poses,
        "actions": {(r["object_id"], r["pose"], r["action"]): r for r in actions},
        "transitions": transitions,
        "manifest": json.loads((dataset / "manifest.json").read_text()),
    }


def xyz(row: dict, prefix: str) -> np.ndarray:
    return np.array([row[f"{prefix}_{a}"] for a in "xyz"], dtype=float)


def planar_transform(yaw: float, x: float, y: float) -> np.ndarray:
    planar = np.eye(4)
    planar[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    planar[:2, 3] = [x, y]
    return planar


def rotation_about(axis, angle: float) -> np.ndarray:
    """(4, 4) rotation by ``angle`` rad about ``axis`` (Rodrigues)."""
    axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    out = np.eye(4)
    out[:3, :3] = np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k
    return out


def stored_transform(tables, object_id: str, pose: int) -> np.ndarray:
    return np.array(tables["poses"][(object_id, pose)]["transform"]).reshape(4, 4)


def no_op(action: int) -> int | None:
    return None if action == -1 else action


# --- listing and lookups ---------------------------------------------------------------


def test_health_reports_schema_version_and_counts(client, tables):
    body = client.get("/health").json()
    assert body["status"] == "ok" and body["schema_version"] == SCHEMA_VERSION
    manifest_counts = tables["manifest"]["counts"]
    assert body["counts"] == {k: manifest_counts[k] for k in body["counts"]}


def test_objects_list_and_details(client, tables, dataset):
    objects = {r["object_id"]: r for r in pq.read_table(dataset / "objects.parquet", columns=["object_id", "sha256", "com_x", "com_y", "com_z"]).to_pylist()}
    listing = client.get("/objects").json()
    assert listing["count"] == 3 and [o["object_id"] for o in listing["objects"]] == OBJECTS
    for entry in listing["objects"]:
        n_poses = sum(1 for (o, _) in tables["poses"] if o == entry["object_id"])
        assert entry["n_poses"] == n_poses and entry["mass"] == 0.1
        assert entry["source"] == "pybullet_data/random_urdfs"

        detail = client.get(f"/objects/{entry['object_id']}").json()
        assert detail["scale"] == 0.015 and detail["sha256"] == objects[entry["object_id"]]["sha256"]
        assert detail["center_mass"] == xyz(objects[entry["object_id"]], "com").tolist()
        assert [p["pose"] for p in detail["poses"]] == list(range(n_poses))
        assert client.get(f"/objects/{entry['object_id']}/poses").json()["poses"] == detail["poses"]
        for summary in detail["poses"]:
            row = tables["poses"][(entry["object_id"], summary["pose"])]
            assert summary["probability"] == row["probability"] and summary["v_t"] == row["v_t"]
            assert summary["value_iteration_action"] == no_op(row["value_iteration_action"])


def test_pose_detail_matches_the_poses_table(client, tables):
    for (object_id, pose), row in tables["poses"].items():
        body = client.get(f"/objects/{object_id}/poses/{pose}").json()
        np.testing.assert_array_equal(body["transform"], stored_transform(tables, object_id, pose))
        np.testing.assert_array_equal(body["down"], xyz(row, "down"))
        assert (body["v_s"], body["v_t"], body["height"]) == (row["v_s"], row["v_t"], row["height"])
        assert (body["probability"], body["com_height"]) == (row["probability"], row["com_height"])
        for policy in ("value_iteration", "greedy", "max_height"):
            assert body["policies"][policy] == {"action": no_op(row[f"{policy}_action"]), "value": row[f"{policy}_value"]}
        counts = body["action_counts"]
        assert sum(counts.values()) == body["n_actions"] == row["n_actions"] and counts["ok"] == row["n_ok_actions"]
        # Every status is named, those no push of the pose has with 0.
        statuses = [a["status"] for (o, p, _), a in tables["actions"].items() if (o, p) == (object_id, pose)]
        assert counts == {name: statuses.count(name) for name in STATUS_NAMES}
        if row["grasp_point_x"] is None:
            assert body["grasp"] is None
        else:
            np.testing.assert_array_equal(body["grasp"]["point"], xyz(row, "grasp_point"))
            np.testing.assert_array_equal(body["grasp"]["axis"], xyz(row, "grasp_axis"))


def test_a_pose_without_some_status_counts_it_as_zero(dataset):
    # Every pose of the test dataset has a push of the last status (finger_collision): take them away.
    obj = Store.load(dataset).objects["random_001"]
    rows = obj.pose_rows(2)
    obj.status = obj.status.copy()
    obj.status[rows] = STATUS_OK
    assert obj.action_counts(2) == {name: rows.stop - rows.start if name == "ok" else 0 for name in STATUS_NAMES}


def check_action(body: dict, row: dict, expected_next: dict[int, float] | None) -> None:
    """An action as served against its rows of the actions and transitions tables."""
    assert body["status"] == row["status"] and body["is_max_height"] == row["is_max_height"]
    for name in ("point", "normal", "direction"):
        np.testing.assert_allclose(body[name], xyz(row, name), rtol=1e-6, atol=1e-9)
    assert body["q"] == row["q"] and body["greedy"] == row["greedy"]
    assert body["mean_force"] == (None if row["mean_force"] is None else pytest.approx(row["mean_force"], rel=1e-6))
    assert body["choosable"] == (row["status"] == "ok" and np.float32(row["direction_z"]) >= np.float32(MIN_DIRECTION_Z))
    if row["status"] != "ok":
        assert not body["executable"] and body["next_poses"] == [] and expected_next is None
        assert body["p_topple"] is None and body["q"] is None
        return
    assert body["executable"] and body["p_topple"] == pytest.approx(row["p_topple"], abs=1e-7)
    outcome = {n["next_pose"]: n["probability"] for n in body["next_poses"]}
    assert sum(outcome.values()) == pytest.approx(1.0, abs=1e-6)
    assert outcome.keys() == expected_next.keys()
    assert all(outcome[k] == pytest.approx(expected_next[k], abs=1e-7) for k in expected_next)
    assert body["p_topple"] == pytest.approx(1.0 - outcome.get(body["pose"], 0.0), abs=1e-6)


def test_every_action_and_its_next_pose_distribution(client, tables):
    keys = sorted(tables["actions"])
    # One batch covers every action; single GETs a sample (each costs a few ms in TestClient).
    results = client.post("/batch/transitions", json={"items": [dict(zip(("object_id", "pose", "action"), k)) for k in keys]})
    assert results.status_code == 200
    for key, result in zip(keys, results.json()["results"]):
        assert result["error"] is None
        check_action(result["result"], tables["actions"][key], tables["transitions"].get(key))
    for object_id, pose, action in keys[::9]:
        body = client.get(f"/objects/{object_id}/poses/{pose}/actions/{action}").json()
        check_action(body, tables["actions"][(object_id, pose, action)], tables["transitions"].get((object_id, pose, action)))


def test_a_grasp_is_served_only_when_both_its_point_and_its_axis_are_known():
    point, axis, unknown = np.array([0.01, 0.0, 0.02]), np.array([0.0, 1.0, 0.0]), np.full(3, np.nan)
    assert grasp_model(point, unknown) is None and grasp_model(unknown, axis) is None and grasp_model(unknown, unknown) is None
    assert grasp_model(point, axis).model_dump() == {"point": point.tolist(), "axis": axis.tolist()}


def test_float32_storage_is_served_as_short_decimals():
    assert widen(np.float32(0.6)) == 0.6 and widen(np.float32(0.0123)) == 0.0123
    assert np.isnan(widen(np.float32("nan")))


@pytest.mark.parametrize("by", ["q", "greedy", "p_topple"])
def test_q_values_and_top_k_sorted(client, tables, by):
    for (object_id, pose), row in tables["poses"].items():
        body = client.get(f"/objects/{object_id}/poses/{pose}/q", params={"top": 5, "by": by}).json()
        actions = [tables["actions"][(object_id, pose, a)] for a in range(row["n_actions"])]
        assert body["q"] == [a["q"] for a in actions] and body["gamma"] == 0.95
        assert (body["v_s"], body["v_t"]) == (row["v_s"], row["v_t"])
        scores = [body_item[by] for body_item in body["top"]]
        assert scores == sorted(scores, reverse=True)
        assert len(body["top"]) == min(5, row["n_ok_actions"])
        assert all(actions[item["action"]]["status"] == "ok" for item in body["top"])
        ok_scores = [a[by] for a in actions if a["status"] == "ok"]
        if ok_scores:
            assert scores[0] == pytest.approx(max(ok_scores), abs=1e-7)
        # The order: highest score first, ties to the lower action (P(topple) ranked as stored, float32).
        stored = np.float32 if by == "p_topple" else float
        ok = [u for u, a in enumerate(actions) if a["status"] == "ok"]
        assert [item["action"] for item in body["top"]] == sorted(ok, key=lambda u: (-stored(actions[u][by]), u))[:5]
        for item in body["top"]:
            action = actions[item["action"]]
            assert (item["q"], item["greedy"], item["is_max_height"]) == (action["q"], action["greedy"], action["is_max_height"])
            # P(topple) leaves as the shortest decimal of its float32 (service.store.widen).
            assert item["p_topple"] == pytest.approx(action["p_topple"], abs=1e-7) and str(item["p_topple"]) == str(np.float32(item["p_topple"]))
        choosable = [a["status"] == "ok" and np.float32(a["direction_z"]) >= np.float32(MIN_DIRECTION_Z) for a in actions]
        assert [item["choosable"] for item in body["top"]] == [choosable[item["action"]] for item in body["top"]]
        if by == "q" and row["value_iteration_action"] != -1:
            # Value iteration's push is the best Q among the pushes it may choose (ties: the first).
            best = max((a["q"], -u) for u, a in enumerate(actions) if choosable[u])
            assert row["value_iteration_action"] == -best[1]


def test_q_ranks_the_ten_best_by_q_unless_asked(client, tables):
    assert tables["poses"][("random_001", 0)]["n_ok_actions"] > 10
    url = "/objects/random_001/poses/0/q"
    assert client.get(url).json() == client.get(url, params={"top": 10, "by": "q"}).json()
    assert len(client.get(url, params={"top": 10_000}).json()["top"]) == tables["poses"][("random_001", 0)]["n_ok_actions"]


# --- planning ------------------------------------------------------------------------


def test_plan_round_trip_recovers_pose_planar_transform_and_push(client, tables):
    approach = tables["manifest"]["parameters"]["contacts"]["approach_offset"]
    depth = tables["manifest"]["parameters"]["contacts"]["push_depth"]
    rng = np.random.default_rng(7)
    pushes = 0
    for (object_id, pose), row in tables["poses"].items():
        yaw, x, y = rng.uniform(-math.pi, math.pi), *rng.uniform(-0.5, 0.5, 2)
        planar = planar_transform(yaw, x, y)
        observed = planar @ stored_transform(tables, object_id, pose)
        for policy in ("value_iteration", "greedy", "max_height"):
            response = client.post("/plan", json={"object_id": object_id, "pose": observed.tolist(), "policy": policy})
            assert response.status_code == 200, response.text
            body = response.json()
            match = body["match"]
            assert match["pose"] == pose and match["angle_error"] < 1e-6
            assert match["yaw"] == pytest.approx(yaw, abs=1e-9)
            np.testing.assert_allclose(match["translation"], [x, y], atol=1e-12)
            np.testing.assert_allclose(match["planar"], planar, atol=1e-12)
            assert match["z_offset"] == pytest.approx(0.0, abs=1e-12)
            assert body["action"] == no_op(row[f"{policy}_action"])
            assert body["v_s"] == row["v_s"] and body["v_t"] == row["v_t"]
            if row["grasp_point_x"] is not None:
                np.testing.assert_allclose(body["grasp"]["point"], (planar @ [*xyz(row, "grasp_point"), 1])[:3], atol=1e-12)
            if body["action"] is None:
                assert body["push"] is None and body["next_poses"] == [] and body["p_topple"] is None
                assert body["q_value"] is None and body["expected_v_s_after"] is None
                assert row[f"{policy}_value"] == row["v_s"], "a policy that grasps is worth V_s"
                no_grasp = row["grasp_point_x"] is None or row["v_s"] == 0
                assert body["decision"] == ("no_grasp" if no_grasp else "grasp") and (body["grasp"] is None) <= no_grasp
                continue
            pushes += 1
            assert body["decision"] == "push"
            action = tables["actions"][(object_id, pose, body["action"])]
            assert action["status"] == "ok"
            # Same meaning for every policy: Q_T and E[V_s(next)] of the chosen push, as stored.
            assert body["q_value"] == action["q"] and body["expected_v_s_after"] == action["greedy"]
            if policy == "value_iteration":
                assert row[f"{policy}_value"] == body["q_value"]
            else:
                assert row[f"{policy}_value"] == body["expected_v_s_after"]
            point = (planar @ [*xyz(action, "point"), 1.0])[:3]
            normal = planar[:3, :3] @ xyz(action, "normal")
            push = body["push"]
            np.testing.assert_allclose(push["point"], point, atol=1e-7)
            np.testing.assert_allclose(push["normal"], normal, atol=1e-7)
            np.testing.assert_allclose(push["direction"], planar[:3, :3] @ xyz(action, "direction"), atol=1e-7)
            np.testing.assert_allclose(push["start"], point + approach * normal, atol=1e-7)
            np.testing.assert_allclose(push["end"], point - depth * normal, atol=1e-7)
            expected = tables["transitions"][(object_id, pose, body["action"])]
            assert {n["next_pose"]: pytest.approx(n["probability"], abs=1e-7) for n in body["next_poses"]} == expected
    assert pushes >= 5, "the tiny dataset should have poses where a policy pushes"


def tilted(tables, object_id: str, pose: int, angle: float) -> tuple[np.ndarray, float]:
    """An observed pose tilted by ``angle`` about a horizontal axis, chosen so that no
    stable pose is within tolerance; returns it and the nearest pose's angle."""
    tolerance = tables["manifest"]["parameters"]["poses"]["same_pose_angle"]
    downs = np.array([xyz(r, "down") for (o, _), r in sorted(tables["poses"].items()) if o == object_id])
    base = planar_transform(0.3, 0.1, 0.2) @ stored_transform(tables, object_id, pose)
    for heading in np.linspace(0, 2 * math.pi, 24, endpoint=False):
        observed = rotation_about([math.cos(heading), math.sin(heading), 0.0], angle) @ base
        nearest = float(np.arccos(np.clip(downs @ (observed[:3, :3].T @ [0, 0, -1.0]), -1, 1)).min())
        if nearest > tolerance + 0.01:
            return observed, nearest
    raise AssertionError("every tilt lands near another stable pose")


def test_plan_tilted_30_degrees_is_409_naming_the_nearest_pose(client, tables):
    observed, nearest = tilted(tables, "random_001", 0, math.radians(30))
    response = client.post("/plan", json={"object_id": "random_001", "pose": observed.tolist()})
    assert response.status_code == 409
    body = response.json()
    assert "no stable pose" in body["detail"] and f"{math.degrees(nearest):.1f} deg" in body["detail"]
    assert body["angle_error"] == pytest.approx(nearest) and body["angle_error"] > body["tolerance"]
    assert f"pose {body['nearest_pose']}" in body["detail"]


def _identity_with(row: int, col: int, value) -> list:
    matrix = np.eye(4).tolist()
    matrix[row][col] = value
    return matrix


MALFORMED = [
    ('{"object_id": "random_001", "pose": [[NaN,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}', "finite number"),
    ('{"object_id": "random_001", "pose": [[1,0,0,Infinity],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}', "finite number"),
    ('{"object_id": "random_001", "pose": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,-1e999]]}', "finite number"),
    (json.dumps({"object_id": "random_001", "pose": np.diag([2.0, 1, 1, 1]).tolist()}), "not a rotation"),
    (json.dumps({"object_id": "random_001", "pose": np.diag([1.0, 1, -1, 1]).tolist()}), "det = -1"),
    (json.dumps({"object_id": "random_001", "pose": _identity_with(0, 1, 0.1)}), "not orthonormal"),
    (json.dumps({"object_id": "random_001", "pose": _identity_with(3, 2, 0.5)}), "last row must be [0, 0, 0, 1]"),
    # A translated pose sent column-major: the translation lands in the last row, and the message says so.
    (json.dumps({"object_id": "random_001", "pose": np.array([[1.0, 0, 0, 0.3], [0, 1, 0, -0.1], [0, 0, 1, 0], [0, 0, 0, 1]]).T.tolist()}),
     "the last column is [0, 0, 0, 1]: is the matrix column-major? send it row by row"),
    # Far beyond any robot's frame (metres sent for millimetres, or garbage): the push's offsets would vanish in float64.
    (json.dumps({"object_id": "random_001", "pose": _identity_with(0, 3, 1.7e308)}), "is beyond 1e+06 m"),
    (json.dumps({"object_id": "random_001", "pose": _identity_with(2, 3, -1.000001e6)}), "is beyond 1e+06 m"),
    (json.dumps({"object_id": "random_001", "ros_pose": {"position": {"x": 0, "y": 2e6, "z": 0},
                 "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}, "frame_id": "world"}}),
     "body.ros_pose.position.y: Input should be less than or equal to 1000000"),
    (json.dumps({"object_id": "random_001", "pose": np.eye(3).tolist()}), "at least 4 items"),
    (json.dumps({"object_id": "random_001", "pose": np.eye(4).ravel().tolist()}), "at most 4 items"),
    (json.dumps({"object_id": "random_001", "pose": _identity_with(1, 1, "one")}), "valid number"),
    (json.dumps({"object_id": "random_001", "pose": _identity_with(0, 0, True)}), "body.pose.0.0: Input should be a valid number"),
    (json.dumps({"object_id": "random_001", "pose": np.eye(4).tolist(), "policy": "random"}), "body.policy"),
    (json.dumps({"object_id": "random_001"}), "body: give exactly one of pose (a 4x4 matrix) and ros_pose"),
    (json.dumps({"object_id": "random_001", "pose": np.eye(4).tolist(), "frame": "world"}), "body.frame: Extra inputs"),
    (json.dumps([1, 2, 3]), "valid dictionary"),
    ("{not json", "JSON decode error"),
    # An unset optional written as null (a dict's None, std::optional): said to be one, with what to do instead.
    (json.dumps({"object_id": "random_001", "pose": np.eye(4).tolist(), "pushes_left": None}),
     ("body.pushes_left: Input should be a valid integer, got null (null is never read as absent: send a value, or leave "
      "an optional field out)")),
    (json.dumps({"object_id": "random_001", "ros_pose": None, "pose": np.eye(4).tolist()}),
     "body.ros_pose: Input should be a valid dictionary or object to extract fields from, got null"),
    (json.dumps({"object_id": None, "pose": np.eye(4).tolist()}), "body.object_id: Input should be a valid string, got null"),
]


def assert_malformed(client, path: str, body: str, message: str) -> None:
    """POST ``body`` to ``path``: a 422 whose one-line ``detail`` contains ``message``, with ``errors``."""
    response = client.post(path, content=body, headers=JSON)
    assert response.status_code == 422, response.text
    detail = response.json()["detail"]
    assert isinstance(detail, str) and message in detail, detail
    assert response.json()["errors"]


@pytest.mark.parametrize("body,message", MALFORMED)
def test_malformed_plan_requests_are_422_with_a_message(client, body, message):
    assert_malformed(client, "/plan", body, message)


def test_an_unknown_id_is_repeated_only_in_part(client):
    # A 60 kB id costs the service a 404, not a 60 kB echo.
    long_id = "x" * 60_000
    response = client.post("/plan", json={"object_id": long_id, "pose": np.eye(4).tolist()})
    detail = response.json()["detail"]
    assert response.status_code == 404 and len(detail) < 200, detail
    assert f"unknown object '{'x' * 64}...' (60000 characters)" in detail
    # An id of exactly the echoed length is repeated whole.
    detail = client.get(f"/objects/{'y' * 64}").json()["detail"]
    assert detail == f"unknown object '{'y' * 64}' (3 objects; GET /objects lists them)"


@pytest.mark.parametrize("path", ["/plan", "/batch/plan", "/batch/transitions"])
def test_a_body_that_is_not_json_says_why_and_where(client, path):
    # The parser's reason and the character it stopped at: where a client's serialiser went wrong.
    body = '{"object_id": "random_001", "pose": [[1, 0, 0, 0],, [0, 1, 0, 0]]}'
    where = body.index(",,") + 1
    assert_malformed(client, path, body, f"JSON decode error: Expecting value at character {where}")


@pytest.mark.parametrize(
    "url,message",
    [
        ("/objects/random_001/poses/x", "path.pose"),
        ("/objects/random_001/poses/0/q?top=0", "greater than or equal to 1"),
        ("/objects/random_001/poses/0/q?top=10001", "less than or equal to 10000"),
        ("/objects/random_001/poses/0/q?by=height", "query.by"),
        ("/objects/random_001/poses/0/actions/1.5", "path.action"),
    ],
)
def test_malformed_query_and_path_parameters_are_422(client, url, message):
    response = client.get(url)
    assert response.status_code == 422 and message in response.json()["detail"], response.text


@pytest.mark.parametrize(
    "url,message",
    [
        ("/objects/mug", "unknown object 'mug'"),
        ("/objects/random_001/poses/99", "has no pose 99: its poses are 0..7"),
        ("/objects/random_001/poses/-1", "has no pose -1"),
        ("/objects/random_001/poses/0/actions/31", "has no action 31: its actions are 0..30"),
        ("/objects/random_001/poses/99/q", "has no pose 99"),
        ("/objects/mug/poses/0/actions/0", "unknown object"),
        ("/nowhere", "Not Found"),
    ],
)
def test_unknown_ids_are_404_with_a_message(client, url, message):
    response = client.get(url)
    assert response.status_code == 404 and message in response.json()["detail"], response.text


def test_the_first_pose_and_action_past_the_last_are_404(client, tables):
    """For every pose, not only the first (an action's row is counted from its pose's first row)."""
    for object_id in OBJECTS:
        n_poses = sum(1 for (o, _) in tables["poses"] if o == object_id)
        response = client.get(f"/objects/{object_id}/poses/{n_poses}")
        assert response.status_code == 404 and f"has no pose {n_poses}: its poses are 0..{n_poses - 1}" in response.json()["detail"]
    for (object_id, pose), row in tables["poses"].items():
        n = row["n_actions"]
        response = client.get(f"/objects/{object_id}/poses/{pose}/actions/{n}")
        assert response.status_code == 404 and f"has no action {n}: its actions are 0..{n - 1}" in response.json()["detail"]


def test_plan_for_an_unknown_object_is_404(client):
    response = client.post("/plan", json={"object_id": "mug", "pose": np.eye(4).tolist()})
    assert response.status_code == 404 and "unknown object 'mug'" in response.json()["detail"]


LONE_SURROGATE_ID = '"\\ud800"'
"""A JSON string holding a lone UTF-16 surrogate: valid JSON, but no UTF-8 response can echo it."""


ROS_POSE_IN_FRAME = ('{"object_id": "random_000", "ros_pose": {"position": {"x": 0, "y": 0, "z": 0}, '
                     '"orientation": {"x": 0, "y": 0, "z": 0, "w": 1}, "frame_id": ID}}')


@pytest.mark.parametrize("path, body", [
    ("/plan", '{"object_id": ID, "pose": POSE}'),
    ("/batch/plan", '{"items": [{"object_id": ID, "pose": POSE}]}'),
    ("/heaps/plan", '{"objects": [{"object_id": ID, "pose": POSE}], "policy": "free_space"}'),
    ("/plan", ROS_POSE_IN_FRAME),
])
def test_a_lone_surrogate_in_an_id_is_422_not_500(client, path, body):
    text = body.replace("ID", LONE_SURROGATE_ID).replace("POSE", json.dumps(np.eye(4).tolist()))
    response = client.post(path, content=text.encode(), headers={"content-type": "application/json"})
    assert response.status_code == 422, response.text
    assert "lone UTF-16 surrogate" in response.json()["detail"]


def test_a_lone_surrogate_in_a_batch_of_transitions_is_422(client):
    text = '{"items": [{"object_id": ID, "pose": 0, "action": 0}]}'.replace("ID", LONE_SURROGATE_ID)
    transitions = client.post("/batch/transitions", content=text.encode(), headers={"content-type": "application/json"})
    assert transitions.status_code == 422 and "body.items.0.object_id" in transitions.json()["detail"]


def test_an_id_with_a_surrogate_pair_is_text_and_unknown(client):
    # An escaped pair is one character (U+1F600), valid Unicode: the id is simply not in the dataset.
    text = '{"object_id": "mug\\ud83d\\ude00", "pose": POSE}'.replace("POSE", json.dumps(np.eye(4).tolist()))
    response = client.post("/plan", content=text.encode(), headers={"content-type": "application/json"})
    assert response.status_code == 404 and "unknown object 'mug\U0001f600'" in response.json()["detail"]


# --- batches -------------------------------------------------------------------------


def test_batch_transitions_answer_each_item(client, tables):
    items = [{"object_id": o, "pose": p, "action": a} for (o, p, a) in list(tables["actions"])[:40]]
    items += [{"object_id": "mug", "pose": 0, "action": 0}, {"object_id": "random_000", "pose": 0, "action": 999}]
    response = client.post("/batch/transitions", json={"items": items})
    assert response.status_code == 200
    results = response.json()["results"]
    assert len(results) == len(items)
    for item, result in zip(items[:40], results):
        single = client.get(f"/objects/{item['object_id']}/poses/{item['pose']}/actions/{item['action']}").json()
        assert result == {"result": single, "error": None}
    assert results[-2]["result"] is None and results[-2]["error"]["status"] == 404
    assert "has no action 999" in results[-1]["error"]["detail"]

    too_many = client.post("/batch/transitions", json={"items": [items[0]] * 1001})
    assert too_many.status_code == 422 and "at most 1000" in too_many.json()["detail"]
    bad = client.post("/batch/transitions", json={"items": [items[0], {"object_id": "random_000", "pose": "zero", "action": 0}]})
    assert bad.status_code == 422 and "body.items.1.pose" in bad.json()["detail"]


def test_batch_plan_answers_each_item_and_rejects_malformed_batches(client, tables):
    observed = planar_transform(1.0, 0.2, -0.1) @ stored_transform(tables, "random_002", 3)
    tilt, _ = tilted(tables, "random_001", 0, math.radians(30))
    items = [
        {"object_id": "random_002", "pose": observed.tolist()},
        {"object_id": "mug", "pose": np.eye(4).tolist()},
        {"object_id": "random_001", "pose": tilt.tolist(), "policy": "greedy"},
    ]
    response = client.post("/batch/plan", json={"items": items})
    assert response.status_code == 200
    first, unknown, no_match = response.json()["results"]
    assert first == {"result": client.post("/plan", json=items[0]).json(), "error": None}
    assert first["result"]["match"]["pose"] == 3
    assert unknown == {"result": None, "error": {"status": 404, "detail": "unknown object 'mug' (3 objects; GET /objects lists them)"}}
    assert no_match["error"]["status"] == 409 and "no stable pose" in no_match["error"]["detail"]
    # A 409 item names its cause as the single route's body does, so a client need not parse the English.
    lifted = observed.copy()
    lifted[2, 3] += 0.1
    items.append({"object_id": "random_002", "pose": lifted.tolist()})
    causes = [r["error"] and r["error"].get("reason") for r in client.post("/batch/plan", json={"items": items}).json()["results"]]
    alone = [(r.json().get("reason") if r.status_code != 200 else None) for r in (client.post("/plan", json=i) for i in items)]
    assert causes == alone == [None, None, "no_stable_pose", "off_table"]

    # A translation at the bound is a pose like any other; past it the whole batch is malformed.
    far = observed.copy()
    far[0, 3] = 1e6
    assert client.post("/batch/plan", json={"items": [{"object_id": "random_002", "pose": far.tolist()}]}).status_code == 200
    far[0, 3] = np.nextafter(1e6, 2e6)
    beyond = client.post("/batch/plan", json={"items": [{"object_id": "random_002", "pose": far.tolist()}]})
    assert beyond.status_code == 422 and "body.items.0.pose: the translation [1000000.0000000001, " in beyond.json()["detail"]

    nan = json.dumps({"items": items[:1]}).replace("1.0]]", "NaN]]", 1)
    assert "NaN" in nan
    malformed = client.post("/batch/plan", content=nan, headers=JSON)
    assert malformed.status_code == 422 and "body.items.0.pose" in malformed.json()["detail"]
    too_many = client.post("/batch/plan", json={"items": items[:1] * 1001})
    assert too_many.status_code == 422 and "at most 1000" in too_many.json()["detail"]
    # A null is said to be one, as /plan says it (the batch is parsed outside FastAPI).
    for path, item in (("/batch/plan", {**items[0], "pushes_left": None}), ("/batch/transitions", {"object_id": "random_002", "pose": None, "action": 0})):
        null = client.post(path, json={"items": [item]})
        assert null.status_code == 422 and ", got null (null is never read as absent" in null.json()["detail"], null.text
    assert ", got null" not in beyond.json()["detail"] + too_many.json()["detail"]


def test_openapi_documents_every_endpoint(client):
    paths = client.get("/openapi.json").json()["paths"]
    assert {
        "/health", "/objects", "/objects/{object_id}", "/objects/{object_id}/poses", "/objects/{object_id}/poses/{pose}",
        "/objects/{object_id}/poses/{pose}/actions/{action}", "/objects/{object_id}/poses/{pose}/q",
        "/plan", "/batch/transitions", "/batch/plan",
    } <= set(paths)
    assert {"404", "409", "422"} <= set(paths["/plan"]["post"]["responses"])


# --- loading and running -------------------------------------------------------------


def test_a_mismatched_schema_version_is_refused(tmp_path, capsys):
    (tmp_path / "manifest.json").write_text(json.dumps({"schema_version": "0.9"}))
    with pytest.raises(DatasetError, match=f"schema version '0.9', this code reads '{SCHEMA_VERSION}'"):
        create_app(tmp_path)
    (tmp_path / "building").mkdir()
    with pytest.raises(DatasetError, match="no manifest.json in .*: not a dataset, or its build did not finish"):
        create_app(tmp_path / "building")
    assert main(["--dataset", str(tmp_path / "nowhere")]) == 2
    assert capsys.readouterr().err.startswith("error: ")


def test_the_service_does_not_import_the_geometry_stack(dataset):
    code = (
        "import sys\n"
        "from fastapi.testclient import TestClient\n"
        "from service.app import create_app\n"
        f"client = TestClient(create_app({str(dataset)!r}))\n"
        "assert client.post('/plan', json={'object_id': 'random_001', 'pose': [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}).status_code in (200, 409)\n"
        "print(sorted(m for m in ('trimesh', 'fcl', 'embreex', 'scipy', 'h5py', 'pybullet') if m in sys.modules))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"
