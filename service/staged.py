"""``python -m service``'s app: the control path answers first, the rest of the API a moment later.

Importing FastAPI and building its routes takes about 0.5 s of a 2-core machine's start-up,
more than everything else together; a robot controller waiting for the service needs only
/health and POST /plan.  So a worker serves through this ASGI app:

- from the first moment: the guard (token, body limits, content type, metrics), /health
  (``Runtime.health_json``, the same body as the FastAPI route) and every valid POST /plan
  (``service.fastplan``: the same validation, planning and bytes as the FastAPI route);
- everything else — other routes, /plan requests that do not validate or match no pose
  (their 404/409/422 come from the FastAPI route), /docs, /openapi.json — is passed to the
  FastAPI app (``service.app.build_api``), which a thread builds from the worker's start.
  A request that arrives before it is ready waits for it (about half a second at most).
  Another thread then solves every object's push budgets (``Store.solve_budgets``).

``create_app`` serves the same routes with the same answers from one FastAPI app (tests,
``uvicorn --factory``, gunicorn); tests/test_service_staged.py holds the two to the same
bytes.  Imports no web framework until the thread does.
"""

from __future__ import annotations

import asyncio
import logging
import time
import traceback
from types import SimpleNamespace

from .fastplan import HEADERS, FastPlan
from .guard import Guard, error_messages
from .runtime import Runtime

log = logging.getLogger("service")

HEALTH = SimpleNamespace(path="/health")
"""What the guard's metrics read from ``scope["route"]`` (the route label)."""
BUILD_FAILED = "the service's API failed to start (logged by the service); only /health and /plan are served"


class StagedApp:
    """ASGI app over a ``Runtime``: see the module docstring."""

    def __init__(self, runtime: Runtime):
        self.runtime = runtime
        self.api = None
        """The FastAPI app, once built."""
        self._building: asyncio.Future | None = None
        settings = runtime.settings
        self._guarded = Guard(
            FastPlan(self._route, live=runtime.live, settings=settings),
            metrics=runtime.metrics, token=settings.token, max_body_bytes=settings.max_body_bytes,
        )

    async def __call__(self, scope, receive, send):
        if scope["type"] == "lifespan":
            await self._lifespan(receive, send)
        else:
            await self._guarded(scope, receive, send)

    async def _route(self, scope, receive, send):
        if scope["type"] == "http" and scope["path"] == "/health" and scope["method"] == "GET":
            body = self.runtime.health_json(scope)
            scope["route"] = HEALTH
            await send({"type": "http.response.start", "status": 200,
                        "headers": [*HEADERS, (b"content-length", str(len(body)).encode())]})
            await send({"type": "http.response.body", "body": body})
            return
        try:
            api = self.api or await self.ready()
        except Exception:  # noqa: BLE001 (any failure to build: logged once by _build)
            for message in error_messages(500, BUILD_FAILED):
                await send(message)
            return
        await api(scope, receive, send)

    def start_building(self) -> None:
        """Start building the FastAPI app in a thread (once; needs the running loop)."""
        if self._building is None:
            self._building = asyncio.ensure_future(asyncio.to_thread(self._build))
            # A failure is _build's to log: retrieved here, asyncio does not log it again at exit.
            self._building.add_done_callback(lambda done: done.cancelled() or done.exception())

    async def ready(self):
        """The FastAPI app, waiting for it to be built."""
        self.start_building()
        # shield: a waiting request that is cancelled (its client left) must not cancel the build.
        return await asyncio.shield(self._building)

    def _build(self):
        started = time.perf_counter()
        try:
            from .app import build_api

            api = build_api(self.runtime)
        except Exception:
            log.exception("building the FastAPI app failed: only /health and valid /plan requests are served")
            raise
        log.info("the full API is served (FastAPI built in %.2f s)", time.perf_counter() - started)
        self.api = api
        self.runtime.solve_budgets()  # after the build, not beside it: one thread at a time beside the event loop
        return api

    async def _lifespan(self, receive, send) -> None:
        # The ASGI lifespan protocol, as Starlette's router speaks it, around Runtime.serving.
        await receive()  # lifespan.startup
        started = False
        try:
            async with self.runtime.serving():
                self.start_building()
                await send({"type": "lifespan.startup.complete"})
                started = True
                await receive()  # lifespan.shutdown
        except Exception:
            # The traceback, as Starlette sends it: the server logs this message and nothing else.
            failed = "lifespan.shutdown.failed" if started else "lifespan.startup.failed"
            await send({"type": failed, "message": traceback.format_exc()})
            raise
        await send({"type": "lifespan.shutdown.complete"})
