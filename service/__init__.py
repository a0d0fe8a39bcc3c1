"""toppledb's HTTP service: a read-only FastAPI app over a finished dataset.

    python -m service --dataset data/dataset            # http://127.0.0.1:8000/docs

``create_app(dataset_dir)`` loads the dataset (``store``) and returns the app; the contract
for callers is docs/SERVICE.md.  Modules: ``app`` (factory, health, metrics, docs, OpenAPI),
``routers`` (thin routes), ``planning`` (plans from observed poses), ``batches`` and ``lane``
(batch bodies off the event loop), ``guard`` (token, body limits, content type, metrics),
``store`` (the dataset in memory, hot swap), ``runtime`` (what a worker serves, its life
and /health), ``staged`` (``python -m service``'s app: the control path first, FastAPI
after), ``handlers`` (errors as JSON), ``settings``, ``server`` (uvicorn with
connection limits), ``client`` (typed Python client), ``bench`` (make bench-service).
The service imports numpy, pyarrow and FastAPI only, never the geometry stack (trimesh,
fcl, embreex, scipy).
"""

__all__ = ["DatasetError", "Store", "create_app"]


def __getattr__(name: str):
    # Imported on first use, not with the package: ``python -m service`` starts checking the
    # served files (``prefetch``) before numpy, pyarrow and pydantic load, and answers /health
    # and /plan before it has imported FastAPI.
    if name == "create_app":
        from .app import create_app

        return create_app
    if name in ("DatasetError", "Store"):
        from . import store

        return getattr(store, name)
    raise AttributeError(f"module 'service' has no attribute {name!r}")
