"""toppledb's HTTP service: a read-only FastAPI app over a finished dataset.

    python -m service --dataset data/dataset            # http://127.0.0.1:8000/docs

``create_app(dataset_dir)`` loads the dataset once (``service.store``) and returns the
app.  The service imports numpy, pyarrow and FastAPI only, never the geometry stack
(trimesh, fcl, embreex, scipy), so it starts in about a second plus the load.
"""

from .app import create_app
from .store import DatasetError, Store

__all__ = ["DatasetError", "Store", "create_app"]
