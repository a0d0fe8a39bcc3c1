# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""service.errors and service.batches' refusals: every 422 body is one ``detail`` that summarises its
``errors`` (each with ``loc``, ``msg`` and ``type``), a batch is refused in the words FastAPI refuses a single
request, and the 500s' tracebacks are rate-limited."""

from __future__ import annotations

import types

import pytest

from schema.api import PlanBatch, TransitionBatch
from service import errors
from service.batches import request_body
from service.errors import (
    NotFound,
    OtherBuild,
    RateLimit,
    UnknownAction,
    UnknownFrame,
    undecodable_body,
    validation_body,
)
from tests.test_service import JSON, client, dataset, stored_transform, tables  # noqa: F401
from tests.test_service_contract import observe, pushing_poses, ros_pose


def summary(errors_: list[dict]) -> str:
    """What ``detail`` says of at most ten errors: each located by its dotted ``loc``, joined by "; "."""
    return "; ".join(".".join(str(part) for part in e["loc"]) + ": " + e["msg"] for e in errors_)


def assert_422_body(response) -> list[dict]:
    """A 422 whose ``errors`` are plain dicts of loc, msg and a type, summarised by ``detail``."""
    assert response.status_code == 422, response.text
    body = response.json()
    assert set(body) == {"detail", "errors"}, body
    assert body["errors"] and all(set(e) == {"loc", "msg", "type"} for e in body["errors"]), body
    assert all(isinstance(e["type"], str) and e["type"] for e in body["errors"]), body
    assert body["detail"] == summary(body["errors"])
    return body["errors"]


def test_a_ros_pose_in_another_frame_and_an_unknown_failed_action_are_422s_like_pydantics(client, tables):
    """The two 422s pydantic cannot give (the frame is the service's setting; a failed action's range is known
    only once the pose is matched) are located and typed as pydantic's own, so one code path reads them all."""
    object_id, pose, _ = pushing_poses(tables)[0]
    observed = observe(tables, object_id, pose)
    frame = client.post("/plan", json={"object_id": object_id, "ros_pose": ros_pose(observed, frame_id="camera_link")})
    [error] = assert_422_body(frame)
    assert error["loc"] == ["body", "ros_pose", "frame_id"] and error["type"] == "unknown_frame"
    assert error["msg"].startswith("ros_pose.frame_id is 'camera_link', but this service plans in 'world'")
    count = sum(1 for (o, p, _) in tables["actions"] if (o, p) == (object_id, pose))
    action = client.post("/plan", json={"object_id": object_id, "pose": observed.tolist(), "failed_actions": [0, count]})
    [error] = assert_422_body(action)
    assert error["loc"] == ["body", "failed_actions", 1] and error["type"] == "unknown_action"
    assert error["msg"] == f"pose {pose} of '{object_id}' has no action {count}: its actions are 0..{count - 1}"
    missing = client.post("/plan", json={"pose": observed.tolist()})
    assert assert_422_body(missing) == [{"loc": ["body", "object_id"], "msg": "Field required", "type": "missing"}]
    two = client.post("/plan", json={"object_id": 3, "pose": observed.tolist(), "policy": "best"})
    assert len(assert_422_body(two)) == 2, "two problems, both listed and summarised"
    # The exceptions' bodies, as the handlers send them.
    assert UnknownAction("no such action", 4).body()["errors"] == [
        {"loc": ["body", "failed_actions", 4], "msg": "no such action", "type": "unknown_action"}]
    assert UnknownFrame("not the table's").body() == {
        "detail": "body.ros_pose.frame_id: not the table's",
        "errors": [{"loc": ["body", "ros_pose", "frame_id"], "msg": "not the table's", "type": "unknown_frame"}]}


@pytest.mark.parametrize(
    "body",
    [b"", b" \n", b'{"items": [,]}', b'{"items": [{"object_id": "\xff"}]}', b"[" * 20_000,
     b'{"items": ' + b"1" * 5000 + b"}"],
    ids=["empty", "whitespace", "broken", "not-utf8", "nested", "huge-integer"],
)
def test_a_batch_is_refused_as_fastapi_refuses_a_single_request(client, monkeypatch, body):
    """Batches are parsed outside FastAPI (in the batch lane), so their refusals are made to match its own:
    the same 422 body, error for error, as a FastAPI route given the same bytes."""
    from service import fastplan

    monkeypatch.setattr(fastplan, "PATH", "/not-the-fast-path")  # /plan through its FastAPI route
    single = client.post("/plan", content=body, headers=JSON)
    batch = client.post("/batch/plan", content=body, headers=JSON)
    assert_422_body(single)
    assert batch.json() == single.json() and batch.status_code == 422


def test_a_malformed_batch_item_is_refused_as_the_same_single_request_located_in_the_batch(client, tables, monkeypatch):
    """A batch's items are validated by pydantic outside FastAPI: each error is the one /plan's route gives for
    the item alone, located under ``body.items.<i>`` (a null still said to be one)."""
    from service import fastplan

    monkeypatch.setattr(fastplan, "PATH", "/not-the-fast-path")
    object_id, pose = next(iter(sorted(tables["poses"])))
    good = {"object_id": object_id, "pose": stored_transform(tables, object_id, pose).tolist()}
    bad = {"pose": None, "pushes_left": -1}
    single = assert_422_body(client.post("/plan", json=bad))
    batch = assert_422_body(client.post("/batch/plan", json={"items": [good, bad]}))
    assert len(single) == 3 and batch == [{**e, "loc": ["body", "items", 1, *e["loc"][1:]]} for e in single]


def test_openapi_documents_the_batch_bodies_the_routes_parse_themselves(client):
    """The batch routes read their bodies as bytes, so FastAPI would document none: each names its model,
    required, and the model is in the document's schemas."""
    document = client.get("/openapi.json").json()
    for path, model in (("/batch/plan", PlanBatch), ("/batch/transitions", TransitionBatch)):
        documented = document["paths"][path]["post"]["requestBody"]
        assert documented == {"required": True, "content": {"application/json": {"schema": {
            "$ref": f"#/components/schemas/{model.__name__}"}}}}
        assert model.__name__ in document["components"]["schemas"]
        # The routes call it when the app is defined (at import); called here, it must give what they documented.
        assert request_body(model) == {"requestBody": documented}


def test_validation_body_names_ten_problems_and_counts_the_rest():
    def problems(n):
        return [{"loc": ("body", "items", i), "msg": f"bad {i}", "type": "value_error"} for i in range(n)]

    ten = validation_body(problems(10))
    assert ten["detail"] == "; ".join(f"body.items.{i}: bad {i}" for i in range(10))
    assert ten["errors"] == [{"loc": ["body", "items", i], "msg": f"bad {i}", "type": "value_error"} for i in range(10)]
    eleven = validation_body(problems(11))
    assert eleven["detail"] == ten["detail"] + "; ... 1 more" and len(eleven["errors"]) == 11
    assert validation_body(problems(25))["detail"] == ten["detail"] + "; ... 15 more"
    assert validation_body([]) == {"detail": "malformed request", "errors": []}
    assert validation_body([{"loc": ("body",), "msg": "Value error, odd", "type": "value_error"}])["detail"] == "body: odd"


def test_an_undecodable_body_says_why():
    try:
        b"\xff".decode()
    except UnicodeDecodeError as err:
        assert undecodable_body(err) == "JSON decode error: not UTF-8 text"
    assert undecodable_body(RecursionError()) == "JSON decode error: nested too deeply"
    try:
        int("1" * 5000)
    except ValueError as err:
        assert undecodable_body(err) == "JSON decode error: a number of more than 4300 digits"
    generic = undecodable_body(None)
    assert generic.startswith("JSON decode error (") and undecodable_body(ValueError("another")) == generic


def test_an_error_body_is_its_detail_and_only_a_409_names_a_reason(client):
    assert NotFound("unknown object 'x'").body() == {"detail": "unknown object 'x'"}
    assert client.get("/objects/nope").json().keys() == {"detail"}
    refusal = OtherBuild("\u00e9" * 100, "0" * 64)
    assert refusal.body()["requested"] == "\\xe9" * 20, "printable ASCII, at most 80 characters of it"
    assert refusal.detail.endswith(f"but build {'0' * 64} answers it: action indices name one build's candidates; "
                                   "clear them and ask again")


def test_tracebacks_are_limited_to_a_fixed_number_a_minute(monkeypatch):
    """A fixed window of 60 s from the first event after the last window: ``per_minute`` events are allowed,
    the rest counted, and the count is handed to the next allowed event (the log says how many it skipped)."""
    now = [1000.0]
    monkeypatch.setattr(errors, "time", types.SimpleNamespace(monotonic=lambda: now[0]))
    limit = RateLimit(3)
    assert [limit.allow() for _ in range(5)] == [(True, 0)] * 3 + [(False, 0)] * 2
    now[0] = 1059.5
    assert limit.allow() == (False, 0)
    now[0] = 1060.0  # exactly a minute after the window opened: a new one
    assert [limit.allow() for _ in range(4)] == [(True, 3), (True, 0), (True, 0), (False, 0)]
    now[0] = 1200.0
    assert limit.allow() == (True, 1)
    # A service started at boot may fail within the first minute of the monotonic clock: its first window is that minute.
    now[0] = 0.0
    early = RateLimit(3)
    assert [early.allow() for _ in range(4)] == [(True, 0)] * 3 + [(False, 0)]
    now[0] = 60.0
    assert early.allow() == (True, 1)
    assert errors.tracebacks.per_minute == errors.TRACEBACKS_PER_MINUTE == 10

