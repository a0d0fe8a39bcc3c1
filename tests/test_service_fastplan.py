# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""POST /plan's direct ASGI path (service.fastplan) answers exactly what the FastAPI route does.

Each request is sent twice to one app: once as is (the fast path answers a valid /plan), and
once with the fast path pointed elsewhere (``fastplan.PATH`` patched), so the FastAPI route
answers.  The bytes must be the same, for pushes, grasps, tilted and lifted observations,
ROS poses, unknown objects and malformed bodies alike.
"""

from __future__ import annotations

import asyncio
import json
import math

import numpy as np
from fastapi.testclient import TestClient

from schema.api import PlanRequest, PlanResponse
from service import create_app, fastplan
from service.planning import answer_json, plan
from service.settings import Settings
from service.store import LiveStore, Store
from tests.test_service import JSON, dataset, planar_transform, rotation_about, stored_transform, tables  # noqa: F401 (fixtures)


def both_paths(client, monkeypatch, body: bytes):
    """(fast path response, FastAPI route response) to POST /plan with ``body``."""
    fast = client.post("/plan", content=body, headers=JSON)
    with monkeypatch.context() as patch:
        patch.setattr(fastplan, "PATH", "/not-the-fast-path")
        slow = client.post("/plan", content=body, headers=JSON)
    return fast, slow


def quaternion(rotation: np.ndarray) -> list[float]:
    """(x, y, z, w) of a rotation matrix (w > 0 branch; fine for the test's rotations)."""
    w = math.sqrt(max(1.0 + np.trace(rotation), 1e-12)) / 2
    return [(rotation[2, 1] - rotation[1, 2]) / (4 * w), (rotation[0, 2] - rotation[2, 0]) / (4 * w),
            (rotation[1, 0] - rotation[0, 1]) / (4 * w), w]


def requests(tables) -> list[bytes]:
    rng = np.random.default_rng(11)
    bodies = []
    for object_id, pose in tables["poses"]:
        observed = planar_transform(rng.uniform(-math.pi, math.pi), *rng.uniform(-0.4, 0.4, 2)) @ stored_transform(
            tables, object_id, pose)
        tilt = observed.copy()
        tilt = rotation_about([1.0, 0.3, 0.0], math.radians(3)) @ observed
        lifted = observed.copy()
        lifted[2, 3] += 0.2
        for policy in ("value_iteration", "greedy", "max_height"):
            for matrix in (observed, tilt, lifted):
                bodies.append(json.dumps({"object_id": object_id, "pose": matrix.tolist(), "policy": policy}).encode())
        for budget in (1, 3):
            bodies.append(json.dumps({"object_id": object_id, "pose": observed.tolist(), "pushes_left": budget}).encode())
        rotation = observed[:3, :3]
        if np.trace(rotation) > -0.9:
            x, y, z, w = quaternion(rotation)
            for orientation in ({"x": x, "y": y, "z": z, "w": w}, {"x": w, "y": x, "z": y, "w": z}):  # and sent w first
                bodies.append(json.dumps({"object_id": object_id, "ros_pose": {
                    "position": dict(zip("xyz", observed[:3, 3].tolist())), "orientation": orientation,
                    "frame_id": "world"}}).encode())
    identity = np.eye(4).tolist()
    bodies += [
        json.dumps({"object_id": "no_such_object", "pose": identity}).encode(),
        json.dumps({"object_id": next(iter(tables["poses"]))[0], "pose": identity, "policy": "telepathy"}).encode(),
        b'{"object_id": "random_000", "pose": [[NaN, 0, 0, 0]]}',
        b'{"object_id": ',
        b"[]",
        json.dumps({"object_id": "random_000", "pose": identity, "unexpected": 1}).encode(),
        json.dumps({"object_id": "random_000", "pose": identity, "pushes_left": None}).encode(),
        json.dumps({"object_id": "random_000", "pose": [[1, 0, 0, 1.7e308], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}).encode(),
    ]
    return bodies


def test_fast_path_answers_byte_for_byte_what_the_route_answers(dataset, tables, monkeypatch):
    statuses = set()
    with TestClient(create_app(dataset)) as client:
        for body in requests(tables):
            fast, slow = both_paths(client, monkeypatch, body)
            assert (fast.status_code, fast.content) == (slow.status_code, slow.content), body[:120]
            assert fast.headers["content-type"] == slow.headers["content-type"]
            statuses.add(fast.status_code)
    assert {200, 404, 409, 422} <= statuses, "the requests should reach every kind of answer"


def test_fast_path_requests_are_counted_under_the_plan_route(dataset, tables):
    object_id, pose = next(iter(tables["poses"]))
    body = {"object_id": object_id, "pose": stored_transform(tables, object_id, pose).tolist()}
    with TestClient(create_app(dataset)) as client:
        for _ in range(3):
            assert client.post("/plan", json=body).status_code == 200
        # The fast path's own refusal of a request naming another build is counted under the route too.
        assert client.post("/plan", json=body, headers={"x-toppledb-build": "f" * 64}).status_code == 412
        metrics = client.get("/metrics").text
    for status, count in (("200", 3.0), ("412", 1.0)):
        counted = [line for line in metrics.splitlines() if line.startswith("toppledb_requests_total")
                   and 'route="/plan"' in line and f'status="{status}"' in line]
        assert counted and float(counted[0].rsplit(" ", 1)[1]) == count, counted


def test_plan_answers_are_the_response_model_exactly(dataset, tables):
    """planning.plan builds plain dicts for speed: they must be PlanResponse, field for field
    and byte for byte as the model would serialise them."""


    store, settings = Store.load(dataset), Settings()
    kinds = set()
    for body in requests(tables):
        try:
            request = PlanRequest.model_validate_json(body)
            answer = plan(store, request, settings)
        except Exception:  # noqa: BLE001, S112 (malformed and unanswerable requests are the route's; see above)
            continue
        model = PlanResponse.model_validate(answer)
        assert answer_json(answer) == model.model_dump_json().encode()
        assert json.loads(answer_json(answer)) == model.model_dump(mode="json")
        kinds.add(answer["decision"])
    assert {"push", "grasp"} <= kinds


# --- the middleware by itself: which requests it answers, and how it hands the others on ---------


DISCONNECT = {"type": "http.disconnect"}


class Inner:
    """The app behind FastPlan: records what it is handed, reads the body and then waits for a
    disconnect as a route may, and answers 599 (a stand-in for FastAPI)."""
    def __init__(self):
        self.calls = []

    async def __call__(self, scope, receive, send):
        self.calls.append((scope, receive, [await receive(), await receive()] if scope["type"] == "http" else []))
        await send({"type": "http.response.start", "status": 599, "headers": []})


def call(middleware, scope: dict, *messages: dict) -> list[dict]:
    """Run one request through ``middleware``; returns what it sent.  ``messages``: what receive yields."""
    queue = list(messages) + [DISCONNECT]
    sent = []

    async def receive():
        return queue.pop(0)

    async def send(message):
        sent.append(message)

    asyncio.run(middleware(scope, receive, send))
    return sent


def http(path="/plan", method="POST") -> dict:
    return {"type": "http", "path": path, "method": method, "headers": []}


def test_the_middleware_answers_a_valid_plan_itself_with_the_planned_bytes(dataset, tables):
    """A valid POST /plan never reaches the framework: 200, JSON, its length, the plan's own bytes,
    and the route label the guard's metrics read."""
    store, settings, inner = Store.load(dataset), Settings(), Inner()
    middleware = fastplan.FastPlan(inner, LiveStore(store), settings)
    object_id, pose = next(iter(tables["poses"]))
    body = json.dumps({"object_id": object_id, "pose": stored_transform(tables, object_id, pose).tolist()}).encode()
    scope = http()
    sent = call(middleware, scope, {"type": "http.request", "body": body})  # no more_body: the whole body (ASGI)
    expected = answer_json(plan(store, PlanRequest.model_validate_json(body), settings))
    assert inner.calls == []
    assert sent == [{"type": "http.response.start", "status": 200,
                     "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(expected)).encode())]},
                    {"type": "http.response.body", "body": expected}]
    assert scope["route"].path == "/plan"


def test_the_middleware_hands_everything_else_on_whole(dataset, tables):
    """Other routes, methods and scope types reach the app untouched, even with a body that would
    plan; a POST /plan body that does not plan, or comes in pieces, reaches it replayed from its
    first message."""
    live = LiveStore(Store.load(dataset))
    object_id, pose = next(iter(tables["poses"]))
    valid = json.dumps({"object_id": object_id, "pose": stored_transform(tables, object_id, pose).tolist()}).encode()
    request = {"type": "http.request", "body": valid, "more_body": False}
    for scope in (http("/objects"), http("/plan", "GET"), http("/plan", "PUT"), http("/plan/", "POST"), {"type": "lifespan"}):
        inner = Inner()
        sent = call(fastplan.FastPlan(inner, live, Settings()), scope, request)
        assert len(inner.calls) == 1 and inner.calls[0][0] is scope and "route" not in scope
        assert inner.calls[0][2] == ([request, DISCONNECT] if scope["type"] == "http" else []), scope  # its own messages
        assert sent[0]["status"] == 599
    unknown = {"type": "http.request", "body": b'{"object_id": "no_such_object", "pose": []}', "more_body": False}
    for message in (unknown, {"type": "http.request", "body": valid, "more_body": True}, {"type": "http.request"}):
        inner, scope = Inner(), http()
        sent = call(fastplan.FastPlan(inner, live, Settings()), scope, message)
        assert len(inner.calls) == 1 and inner.calls[0][2] == [message, DISCONNECT] and "route" not in scope
        assert [m.get("status") for m in sent] == [599]
