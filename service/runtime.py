"""What a worker serves, apart from the HTTP framework: the live dataset, the settings, the
metrics and the batch lane; their life (watching for a rebuild, SIGHUP) and /health's answer.

Both ways of serving stand on one ``Runtime``: ``service.app.create_app`` (the FastAPI app,
for tests, ``uvicorn --factory`` and gunicorn) and ``service.staged`` (``python -m service``,
whose control path answers before FastAPI is imported).  Imports no web framework.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import threading
from collections.abc import Callable
from dataclasses import dataclass, field

from schema.api import Counts, DatasetIdentity, Health
from schema.version import CODE_VERSION

from .guard import answered_from
from .lane import Lane
from .metrics import Metrics
from .prefetch import Prefetch
from .settings import Settings
from .store import LiveStore, Store

log = logging.getLogger("service")


@dataclass
class Runtime:
    settings: Settings
    live: LiveStore
    metrics: Metrics
    lane: Lane
    on_swap: list[Callable[[], None]] = field(default_factory=list)
    """Called after a rebuilt dataset is swapped in (the OpenAPI document names served objects)."""

    @classmethod
    def open(cls, settings: Settings, prefetch: Prefetch | None = None) -> Runtime:
        """Map the dataset ``settings.dataset``; raises ``service.DatasetError`` if it is not one.
        ``prefetch``: its served files mapped and hashed already (``service.prefetch``)."""
        live = LiveStore(Store.load(settings.dataset, prefetch))
        runtime = cls(settings, live, Metrics(), Lane())
        live.on_failure = runtime.metrics.reload_failures.inc  # counted where it happens, once however many reloads overlap
        runtime.metrics.serving(live.store.manifest_sha256, live.store.manifest.created)
        return runtime

    def health(self, store: Store) -> Health:
        """/health's answer: liveness and which build this worker serves (``store``, the one it serves now)."""
        return Health(
            status="ok",
            schema_version=store.schema_version,
            service_version=CODE_VERSION,
            dataset=DatasetIdentity(
                path=str(store.root),
                manifest_sha256=store.manifest_sha256,
                created=store.manifest.created,
                code_version=store.code_version,
                parameters_sha256=store.parameters_sha256,
                loaded_at=store.loaded_at,
            ),
            counts=Counts(**store.counts),
            load_seconds=round(store.load_seconds, 3),
            reloads=self.live.reloads,
            reload_error=self.live.reload_error,
        )

    def health_json(self, scope: dict) -> bytes:
        """/health's body.  ``reload_error`` is left out while there is none, so that a client from before it
        existed (whose models forbid fields they do not know) reads a healthy answer as before; while a reload
        is failing such a client cannot read /health (docs/SERVICE.md).

        scope : the request's ASGI scope, noted with the build the body names (``guard.answered_from``, as every
          route that reads the dataset notes it; the guard sends it as ``x-toppledb-build``, so that a HEAD probe
          sees a swap too). A build the request names is not checked: liveness never refuses.
        """
        health = self.health(answered_from(scope, self.live.store, None))
        return health.model_dump_json(exclude=None if health.reload_error is not None else {"reload_error"}).encode()

    def solve_budgets(self) -> None:
        """Solve every object's push budgets (``Store.solve_budgets``, about 0.6 s for the full
        dataset) in a thread of its own, so that no /plan with pushes_left pays for it."""
        threading.Thread(target=self.live.store.solve_budgets, name="budgets", daemon=True).start()

    async def reload(self, force: bool = False) -> bool:
        """Swap in a rebuilt dataset (in a thread: loading takes seconds); True when swapped."""
        swapped = await asyncio.to_thread(self.live.reload, force)
        if swapped:
            for callback in self.on_swap:
                callback()
            self.metrics.serving(self.live.store.manifest_sha256, self.live.store.manifest.created)
            self.metrics.reloads.inc()
        return swapped

    async def _watch(self) -> None:
        """Check manifest.json every ``watch_seconds``; reload when it changed."""
        while True:
            await asyncio.sleep(self.settings.watch_seconds)
            try:
                if self.live.changed():
                    await self.reload()
            except Exception:
                log.exception("dataset watcher: reload failed")

    @contextlib.asynccontextmanager
    async def serving(self):
        """A worker's life on its event loop (the app's lifespan): the watcher, the SIGHUP
        handler, and the batch lane closed at the end."""
        # Per worker: forked workers (service.server.serve_forked) report their own pid.
        self.metrics.serving(self.live.store.manifest_sha256, self.live.store.manifest.created)
        if self.live.changed():  # forked to replace a dead worker after the others swapped in a rebuild
            await self.reload()
        watcher = asyncio.create_task(self._watch()) if self.settings.watch_seconds > 0 else None
        loop = asyncio.get_running_loop()
        hup, before = False, None
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError, AttributeError):
            before = signal.getsignal(signal.SIGHUP)
            loop.add_signal_handler(signal.SIGHUP, lambda: asyncio.ensure_future(self.reload(force=True)))
            hup = True
        try:
            yield
        finally:
            if watcher is not None:
                watcher.cancel()
            if hup:
                # asyncio leaves SIG_DFL behind; a worker started under nohup (SIG_IGN) must not die of a
                # SIGHUP while it shuts down, so the disposition it had comes back.
                loop.remove_signal_handler(signal.SIGHUP)
                if before is not None:
                    signal.signal(signal.SIGHUP, before)
            self.lane.close()
