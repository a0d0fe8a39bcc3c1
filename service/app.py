"""The application factory: ``create_app(dataset_dir)`` loads the dataset and mounts the routers."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI

from schema.api import Counts, Health
from schema.version import CODE_VERSION

from . import errors
from .dependencies import StoreDep
from .routers import objects, plan
from .store import Store

DESCRIPTION = """\
Read-only queries over a toppledb dataset: objects, stable poses, candidate pushes and
their next-pose distributions, Q-values, and plans from an observed 4x4 world pose.

SI units (m, kg, N, rad). World frame: z up, table at z = 0. Pose frame: a stable pose's
canonical frame (z up, table at z = 0, centre of mass over the origin). Matrices are 4x4,
row-major. Errors are JSON `{"detail": "..."}`: 404 unknown ids, 409 no matching stable
pose, 422 malformed input.
"""


def create_app(dataset_dir: str | Path) -> FastAPI:
    """Load the dataset under ``dataset_dir`` (once) and return the app serving it.

    Raises ``service.DatasetError`` when the directory is not a finished dataset of
    this schema version.
    """
    store = Store.load(dataset_dir)
    app = FastAPI(title="toppledb", version=CODE_VERSION, description=DESCRIPTION)
    app.state.store = store
    errors.install(app)
    app.include_router(objects.router)
    app.include_router(objects.batch)
    app.include_router(plan.router)
    app.include_router(plan.batch)

    @app.get("/health", response_model=Health, tags=["service"], summary="Liveness, schema version, counts")
    async def health(store: StoreDep) -> Health:
        return Health(
            status="ok",
            schema_version=store.schema_version,
            counts=Counts(**store.counts),
            load_seconds=round(store.load_seconds, 3),
        )

    return app
