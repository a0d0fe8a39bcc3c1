"""The application factory.

    create_app("data/dataset")                      # in code and tests
    uvicorn service.app:create_app --factory        # several workers: TOPPLEDB_DATASET=... --workers 2
    gunicorn -k uvicorn.workers.UvicornWorker 'service.app:create_app()'

``create_app`` loads the dataset (``service.store``), wraps the routes in the guard
(metrics, bearer token, body limits, ``service.guard``), serves /docs and /redoc from
local assets, and watches the dataset for a rebuild (``service.store.LiveStore``).
Settings come from arguments, else ``TOPPLEDB_*`` environment variables
(``service.settings``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
from pathlib import Path

import numpy as np
from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.openapi.utils import get_openapi
from fastapi.responses import HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

from schema.api import ErrorBody, Health, PlanBatch, TransitionBatch
from schema.version import CODE_VERSION

from . import handlers
from .fastplan import FastPlan
from .guard import OPEN_PATHS, Guard
from .metrics import CONTENT_TYPE
from .routers import heaps, objects, plan
from .runtime import Runtime
from .settings import Settings
from .store import Store

DESCRIPTION = """\
Read-only queries over a toppledb dataset: objects, stable poses, candidate pushes and
their next-pose distributions, Q-values, and plans from an observed pose (a 4x4 matrix or
a ROS pose). The contract for robot teams is docs/SERVICE.md.

SI units (m, kg, N, rad). World frame: z up, table at z = 0. Pose frame: a stable pose's
canonical frame (z up, table at z = 0, centre of mass over the origin). Matrices are 4x4,
row-major. Errors are JSON `{"detail": "..."}`: 401 missing or wrong bearer token (when the
service has one), 404 unknown ids, 409 no matching stable pose or not on the table, 412 the
request names (`x-toppledb-build`) a build other than the one served, 413 body too large, 415 body
not JSON, 422 malformed input, 503 overloaded (retry).
"""

DOCS_ASSETS = "/docs-assets"
"""Where Swagger UI and ReDoc's files are served from (the fastapi-offline package's copies),
so /docs and /redoc work on a robot network without internet access."""


def _docs_assets() -> Path | None:
    try:
        import fastapi_offline
    except ImportError:
        return None
    path = Path(fastapi_offline.__file__).parent / "static"
    return path if (path / "swagger-ui-bundle.js").is_file() else None


def create_app(dataset_dir: str | Path | None = None, settings: Settings | None = None) -> FastAPI:
    """Load the dataset and return the app serving it.

    dataset_dir : overrides ``settings.dataset`` (default ``TOPPLEDB_DATASET`` or data/dataset)
    settings : default ``Settings.from_env()``

    Raises ``service.DatasetError`` when the directory is not a finished dataset of this
    schema version, ``ValueError`` for a malformed setting.
    """
    settings = settings or Settings.from_env()
    if dataset_dir is not None:
        settings = dataclasses.replace(settings, dataset=Path(dataset_dir))
    runtime = Runtime.open(settings)
    app = build_api(runtime)

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        async with runtime.serving():
            runtime.solve_budgets()
            yield

    app.router.lifespan_context = lifespan
    app.add_middleware(FastPlan, live=runtime.live, settings=settings)  # inside the guard: after its checks
    app.add_middleware(Guard, metrics=runtime.metrics, token=settings.token, max_body_bytes=settings.max_body_bytes)
    return app


def build_api(runtime: Runtime) -> FastAPI:
    """The FastAPI app over ``runtime``: routes, error handlers, /docs, the OpenAPI document.

    Without the guard, the fast /plan path and a lifespan: ``create_app`` adds those, and
    ``service.staged`` runs this app behind its own.
    """
    assets = _docs_assets()
    app = FastAPI(
        title="toppledb", version=CODE_VERSION, description=DESCRIPTION, docs_url=None, redoc_url=None,
        # /metrics is the service's telemetry; FastAPI's OpenTelemetry hooks would check their
        # providers on every request (about 25 us of a /plan's CPU) to find nothing configured.
        telemetry={"tracing": False, "metrics": False, "logs": False},
    )
    app.state.live = runtime.live
    app.state.settings = runtime.settings
    app.state.metrics = runtime.metrics
    app.state.lane = runtime.lane
    runtime.on_swap.append(lambda: setattr(app, "openapi_schema", None))  # its examples name the served objects
    handlers.install(app)
    # /plan first: the control path's route is matched before the others are tried.
    app.include_router(plan.router)
    app.include_router(objects.router)
    app.include_router(objects.batch)
    app.include_router(plan.batch)
    app.include_router(heaps.router)

    @app.get("/health", response_model=Health, tags=["service"], summary="Liveness and which build is served")
    async def health(request: Request) -> Response:
        return Response(runtime.health_json(request.scope), media_type="application/json")

    metrics = runtime.metrics

    @app.get(
        "/metrics", tags=["service"], summary="Prometheus metrics of this worker",
        response_class=Response,
        responses={200: {"content": {CONTENT_TYPE.split(";")[0]: {"schema": {"type": "string"}}},
                         "description": "Prometheus text format 0.0.4"}},
    )
    async def get_metrics() -> Response:
        return Response(metrics.render(), media_type=CONTENT_TYPE)

    if assets is not None:
        app.mount(DOCS_ASSETS, StaticFiles(directory=assets), name="docs-assets")

        @app.get("/docs", include_in_schema=False)
        async def swagger() -> HTMLResponse:
            return get_swagger_ui_html(
                openapi_url=app.openapi_url, title="toppledb - Swagger UI",
                swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js", swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css",
                swagger_favicon_url=f"{DOCS_ASSETS}/favicon.png",
            )

        @app.get("/redoc", include_in_schema=False)
        async def redoc() -> HTMLResponse:
            return get_redoc_html(
                openapi_url=app.openapi_url, title="toppledb - ReDoc", redoc_js_url=f"{DOCS_ASSETS}/redoc.standalone.js",
                redoc_favicon_url=f"{DOCS_ASSETS}/favicon.png", with_google_fonts=False,
            )

    app.openapi = lambda: _openapi(app)
    return app


def _example_pose(transform: np.ndarray) -> list[list[float]]:
    """A stable pose's transform placed on the table at yaw 30 deg, x 0.4 m, y -0.1 m."""
    yaw = math.radians(30.0)
    planar = np.eye(4)
    planar[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
    planar[:2, 3] = [0.4, -0.1]
    return np.round(planar @ transform, 6).tolist()


def _openapi(app: FastAPI) -> dict:
    """FastAPI's document, plus: the batch bodies (parsed in the lane, not by FastAPI),
    examples from the served dataset, and the guard's 401/413/415/503."""
    if app.openapi_schema:
        return app.openapi_schema
    schema = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
    components = schema.setdefault("components", {}).setdefault("schemas", {})
    for model in (PlanBatch, TransitionBatch):
        model_schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
        for name, definition in model_schema.pop("$defs", {}).items():
            components.setdefault(name, definition)
        components[model.__name__] = model_schema
    components.setdefault("ErrorBody", ErrorBody.model_json_schema(ref_template="#/components/schemas/{model}"))

    store: Store = app.state.live.store
    example = store.example_object()
    if example is not None:
        object_id, pose, transform = example
        plan_example = {"object_id": object_id, "pose": _example_pose(transform), "policy": "value_iteration"}
        components["PlanRequest"]["examples"] = [plan_example]
        components["PlanBatch"]["examples"] = [{"items": [plan_example]}]
        components["TransitionBatch"]["examples"] = [{"items": [{"object_id": object_id, "pose": pose, "action": 0}]}]
    error = {"content": {"application/json": {"schema": {"$ref": "#/components/schemas/ErrorBody"}}}}
    settings: Settings = app.state.settings
    for path, operations in schema.get("paths", {}).items():
        for method, operation in operations.items():
            responses = operation.setdefault("responses", {})
            if example is not None:
                for parameter in operation.get("parameters", []):
                    if parameter.get("name") == "object_id":
                        parameter["example"] = example[0]
            if settings.token is not None and path not in OPEN_PATHS:
                responses.setdefault("401", {"description": "Missing or wrong bearer token", **error})
                operation["security"] = [{"bearer": []}]
            if method in ("post", "put", "patch"):
                responses.setdefault("413", {"description": f"Body over {settings.max_body_bytes} bytes", **error})
                responses.setdefault("415", {"description": "Body not sent as application/json", **error})
            if path.startswith("/batch/"):
                responses.setdefault("503", {"description": "Too many batches queued in this worker; retry", **error})
    if settings.token is not None:
        schema["components"]["securitySchemes"] = {"bearer": {"type": "http", "scheme": "bearer"}}
    app.openapi_schema = schema
    return schema
