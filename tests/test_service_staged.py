# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""``python -m service``'s staged app answers what ``create_app`` answers, serves the control
path before FastAPI is built, and never imports a web framework before it is needed."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys
import threading

from fastapi.testclient import TestClient

from service import app as service_app
from service import create_app
from service.runtime import Runtime
from service.settings import Settings
from service.staged import StagedApp
from tests.test_service import JSON, ROOT, dataset, tables  # noqa: F401 (fixtures)
from tests.test_service_fastplan import requests as plan_bodies

VOLATILE = ("loaded_at",)
"""Health fields that differ between two loads of one dataset."""


def staged_app(dataset) -> StagedApp:
    return StagedApp(Runtime.open(Settings.from_env(dataset=dataset)))


def valid_plan(tables) -> bytes:
    """A /plan body the control path answers itself."""
    return next(body for body in plan_bodies(tables) if b'"value_iteration"' in body)


def comparable(response) -> tuple:
    if response.request.url.path == "/health":
        body = json.loads(response.content)
        body["dataset"] = {k: v for k, v in body["dataset"].items() if k not in VOLATILE}
        body.pop("load_seconds")
        return response.status_code, body
    return response.status_code, response.content


def test_staged_app_answers_what_create_app_answers(dataset, tables):
    object_id, pose = next(iter(tables["poses"]))
    gets = ["/health", "/objects", f"/objects/{object_id}", f"/objects/{object_id}/poses/{pose}",
            f"/objects/{object_id}/poses/{pose}/q?top=3", "/objects/no_such_object", "/openapi.json", "/docs", "/nowhere"]
    posts = [("/plan", body) for body in plan_bodies(tables)]
    posts += [("/batch/plan", b'{"items": []}'), ("/plan", b"not json")]
    with TestClient(staged_app(dataset)) as staged, TestClient(create_app(dataset)) as eager:
        for path in gets:
            assert comparable(staged.get(path)) == comparable(eager.get(path)), path
        for path, body in posts:
            assert comparable(staged.post(path, content=body, headers=JSON)) == comparable(
                eager.post(path, content=body, headers=JSON)), body[:100]
        metrics = staged.get("/metrics").text
    assert 'route="/health",status="200"' in metrics and 'route="/plan",status="200"' in metrics


def test_head_on_health_answers_the_get_without_its_body_on_both_apps(dataset):
    """Uptime monitors probe with HEAD: /health answers it as its GET, headers and all, with no body; any
    other path keeps its HEAD answer (405 on a GET route), also without a body. Counted under HEAD."""
    with TestClient(staged_app(dataset)) as staged, TestClient(create_app(dataset)) as eager:
        for client in (staged, eager):
            get, head = client.get("/health"), client.head("/health")
            assert head.status_code == 200 and head.content == b""
            assert head.headers["content-type"] == get.headers["content-type"] == "application/json"
            assert int(head.headers["content-length"]) == len(get.content) > 0
            other = client.head("/objects")
            assert other.status_code == 405 and other.content == b""
            assert 'method="HEAD",route="/health",status="200"' in client.get("/metrics").text


def test_health_names_its_build_in_the_header_as_the_routes_that_read_the_dataset_do(dataset, tables):
    """A HEAD probe sees which build is served (and a swap) without a body to parse: /health sends the
    build its body names as x-toppledb-build, on both apps, and a request naming another build is still
    answered (liveness never refuses)."""
    served = hashlib.sha256((dataset / "manifest.json").read_bytes()).hexdigest()
    object_id, _ = next(iter(tables["poses"]))
    with TestClient(staged_app(dataset)) as staged, TestClient(create_app(dataset)) as eager:
        for client in (staged, eager):
            get, head = client.get("/health"), client.head("/health")
            assert get.headers["x-toppledb-build"] == head.headers["x-toppledb-build"] == served
            assert get.json()["dataset"]["manifest_sha256"] == served
            assert get.headers["x-toppledb-build"] == client.get(f"/objects/{object_id}").headers["x-toppledb-build"]
            other = client.get("/health", headers={"x-toppledb-build": "f" * 64})
            assert other.status_code == 200 and other.headers["x-toppledb-build"] == served
            # Refused before any route runs: no build answered it, so none is named.
            assert "x-toppledb-build" not in client.post("/plan", content=b"{}").headers


def test_health_and_plan_answer_while_the_api_is_being_built(dataset, tables, monkeypatch):
    release = threading.Event()
    real_build = service_app.build_api

    def slow_build(runtime):
        assert release.wait(30), "the test never released the build"
        return real_build(runtime)

    monkeypatch.setattr(service_app, "build_api", slow_build)
    app = staged_app(dataset)
    valid = valid_plan(tables)
    with TestClient(app) as client:
        assert client.get("/health").json()["status"] == "ok"
        assert client.post("/plan", content=valid, headers=JSON).status_code == 200
        # A controller whose dataset was rebuilt since its failed pushes is told so at once too.
        stale = client.post("/plan", content=valid, headers={**JSON, "x-toppledb-build": "f" * 64})
        assert stale.status_code == 412 and stale.json()["build"] == stale.headers["x-toppledb-build"]
        assert app.api is None, "the control path must not have waited for the FastAPI app"
        waiting: dict = {}
        caller = threading.Thread(target=lambda: waiting.setdefault("response", client.get("/objects")))
        caller.start()
        caller.join(0.3)
        assert caller.is_alive() and "response" not in waiting, "/objects answered before the API existed"
        release.set()
        caller.join(30)
        assert waiting["response"].status_code == 200 and app.api is not None


def test_a_failed_build_leaves_health_and_plan_and_answers_the_rest_with_500(dataset, tables, monkeypatch):
    def broken(runtime):
        raise RuntimeError("a broken install")

    monkeypatch.setattr(service_app, "build_api", broken)
    valid = valid_plan(tables)
    with TestClient(staged_app(dataset)) as client:
        assert client.get("/health").status_code == 200
        assert client.post("/plan", content=valid, headers=JSON).status_code == 200
        response = client.get("/objects")
    assert response.status_code == 500 and "failed to start" in response.json()["detail"]


def test_the_server_entry_point_imports_no_web_framework():
    # What python -m service imports before its workers serve; FastAPI comes later, in a thread.
    code = ("import sys, service.__main__, service.staged, service.runtime\n"
            "print(sorted(m for m in ('fastapi', 'starlette') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_the_token_guards_the_early_routes_too(dataset, tables):
    token = "a-sixteen-char-secret"
    app = StagedApp(Runtime.open(Settings.from_env(dataset=dataset, token=token)))
    valid = valid_plan(tables)
    with TestClient(app) as client:
        assert client.get("/health").status_code == 200  # open, as with create_app
        assert client.post("/plan", content=valid, headers=JSON).status_code == 401
        ok = client.post("/plan", content=valid, headers={**JSON, "authorization": f"Bearer {token}"})
    assert ok.status_code == 200
