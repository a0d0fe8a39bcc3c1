"""Settings of one service process, from arguments or environment variables.

Every setting has an environment variable so that ``uvicorn --factory`` and gunicorn
workers (which call ``service.app:create_app()`` with no arguments) see the same values
as ``python -m service``:

    TOPPLEDB_DATASET            dataset directory (default data/dataset)
    TOPPLEDB_TOKEN              bearer token required on every endpoint except /health (unset: none)
    TOPPLEDB_MAX_BODY_BYTES     largest request body, else 413 (default 2 MiB: a full 1000-item plan batch is ~0.5 MB)
    TOPPLEDB_HEIGHT_TOLERANCE   m, largest |z_offset| of an observed pose, else 409 off_table (default schema.api.HEIGHT_TOLERANCE)
    TOPPLEDB_FINGER_FORCE_LIMIT N, overrides the manifest's topple.max_finger_force (default schema.api.FINGER_FORCE_LIMIT)
    TOPPLEDB_FRAME_ID           name of the table frame a ROS pose must be given in (default world)
    TOPPLEDB_WATCH_SECONDS      s between checks of manifest.json for a rebuilt dataset (default 2; 0: only on SIGHUP)
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, replace
from pathlib import Path

from schema.api import HEIGHT_TOLERANCE

DEFAULT_DATASET = "data/dataset"
DEFAULT_MAX_BODY_BYTES = 2 * 1024 * 1024
DEFAULT_FRAME_ID = "world"
DEFAULT_WATCH_SECONDS = 2.0
ENV_PREFIX = "TOPPLEDB_"


@dataclass(frozen=True)
class Settings:
    dataset: Path = Path(DEFAULT_DATASET)
    token: str | None = None
    max_body_bytes: int = DEFAULT_MAX_BODY_BYTES
    height_tolerance: float = HEIGHT_TOLERANCE
    finger_force_limit: float | None = None
    """N; None: the manifest's topple.max_finger_force, else schema.api.FINGER_FORCE_LIMIT."""
    frame_id: str = DEFAULT_FRAME_ID
    watch_seconds: float = DEFAULT_WATCH_SECONDS

    @classmethod
    def from_env(cls, environ: dict[str, str] | None = None, **overrides) -> Settings:
        """Defaults, then ``TOPPLEDB_*`` variables, then ``overrides`` that are not None.

        A malformed variable is a ``ValueError`` naming it (the server does not start).
        """
        env = os.environ if environ is None else environ
        values: dict = {}
        readers = {
            "dataset": Path, "token": str, "max_body_bytes": int, "height_tolerance": float,
            "finger_force_limit": float, "frame_id": str, "watch_seconds": float,
        }
        for name, read in readers.items():
            raw = env.get(ENV_PREFIX + name.upper())
            if raw is None or raw == "":
                continue
            try:
                values[name] = read(raw)
            except ValueError:
                raise ValueError(f"{ENV_PREFIX + name.upper()}={raw!r} is not a valid {read.__name__}") from None
        values.update({k: v for k, v in overrides.items() if v is not None})
        settings = replace(cls(), **values)
        settings.check()
        return settings

    def check(self) -> None:
        if self.max_body_bytes < 1024:
            raise ValueError(f"max_body_bytes {self.max_body_bytes} is below 1024: no plan request would fit")
        if not self.height_tolerance >= 0:
            raise ValueError(f"height_tolerance {self.height_tolerance} must be >= 0 m")
        if self.finger_force_limit is not None and not self.finger_force_limit > 0:
            raise ValueError(f"finger_force_limit {self.finger_force_limit} must be > 0 N")
        if not (math.isfinite(self.watch_seconds) and self.watch_seconds >= 0):
            raise ValueError(f"watch_seconds {self.watch_seconds} must be a finite number >= 0 s (0: SIGHUP only)")
        if self.token is not None and len(self.token) < 16:
            raise ValueError("the bearer token must have at least 16 characters")
