"""POST /plan answered straight from ASGI: the control path without the framework's detour.

FastAPI spends about as much CPU per /plan request on routing, dependency resolution and
request-object plumbing as the planning itself.  This middleware sits just inside the guard
(which has already checked the token, the size and the content type, and read the body)
and answers a valid POST /plan directly: validate the body with the same pydantic model,
plan with the same ``service.planning.plan``, serialise with the same ``answer_json``.

A valid one that names another build (``x-toppledb-build``) it refuses itself with the route's
412, so that a controller whose dataset was rebuilt is told at once, also while the staged
server is still building FastAPI.  Anything else — another route, a body that does not
validate, an unknown object, a pose that matches nothing, a bug — goes on to the FastAPI
route, which answers it exactly as it always did (the 404/409/422 bodies, the OpenAPI
document, the error handlers).  So the
fast path can change how quickly /plan answers, never what it answers;
tests/test_service_fastplan.py holds the two paths to the same bytes.
"""

from __future__ import annotations

from types import SimpleNamespace

from schema.api import PlanRequest

from .errors import OtherBuild
from .guard import BUILD_SCOPE_KEY, answered_from, json_messages, replay, requested_build
from .planning import answer_json, plan
from .settings import Settings
from .store import LiveStore

PATH = "/plan"
HEADERS = [(b"content-type", b"application/json")]
ROUTE = SimpleNamespace(path="/plan")
"""What the guard's metrics read from ``scope["route"]`` (its ``path``, the route label)."""


class FastPlan:
    """ASGI middleware: see the module docstring."""

    def __init__(self, app, live: LiveStore, settings: Settings):
        self.app = app
        self.live = live
        self.settings = settings

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["path"] != PATH or scope["method"] != "POST":
            await self.app(scope, receive, send)
            return
        message = await receive()
        body = message.get("body", b"")
        if message["type"] != "http.request" or message.get("more_body", False):
            await self.app(scope, replay(message, receive), send)  # the guard hands bodies over whole; this is not one
            return
        try:
            request = PlanRequest.model_validate_json(body)
            answer = answer_json(plan(answered_from(scope, self.live.store, requested_build(scope)), request, self.settings))
        except OtherBuild as refused:  # as get_store refuses it on the route (the guard names the build)
            scope["route"] = ROUTE
            for reply in json_messages(refused.status_code, refused.body()):
                await send(reply)
            return
        except Exception:  # noqa: BLE001 (every other failure is the FastAPI route's to answer, bugs included)
            scope.pop(BUILD_SCOPE_KEY, None)  # the route names the build it answers from, if any
            await self.app(scope, replay(message, receive), send)
            return
        scope["route"] = ROUTE
        await send({"type": "http.response.start", "status": 200,
                    "headers": [*HEADERS, (b"content-length", str(len(answer)).encode())]})
        await send({"type": "http.response.body", "body": answer})
