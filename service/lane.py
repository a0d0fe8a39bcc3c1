"""The batch lane: batch bodies are parsed, validated, answered and serialised in one
dedicated thread, never on the event loop that serves the control path (/plan and the
single lookups).

One thread, so that batches queue behind each other instead of multiplying the work
that competes with the event loop for the interpreter; ``MAX_QUEUED`` bounds the
queue, beyond which a batch is refused at once with 503 and ``Retry-After``.  The GIL
still interleaves the lane with the loop; the service lowers the interpreter's switch
interval (``SWITCH_INTERVAL``) so that a request on the loop waits at most about that
long for each slice of batch work, instead of the default 5 ms.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

from .errors import ServiceError

MAX_QUEUED = 16
"""Batches waiting for or running in the lane of one worker; more is a 503."""

SWITCH_INTERVAL = 0.0005
"""s, sys.setswitchinterval for the server process (default 0.005): the longest slice a
batch thread holds the GIL before the event loop may run."""


class LaneBusy(ServiceError):
    status_code = 503


class Lane:
    def __init__(self, name: str = "batch-lane"):
        self.executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self.waiting = 0

    async def run(self, fn: Callable, *args):
        if self.waiting >= MAX_QUEUED:
            raise LaneBusy(f"{self.waiting} batches are queued in this worker; retry in a second", retry_after=1)
        self.waiting += 1
        try:
            return await asyncio.wrap_future(self.executor.submit(fn, *args))
        finally:
            self.waiting -= 1

    def close(self) -> None:
        self.executor.shutdown(wait=False, cancel_futures=True)


def tune_interpreter() -> None:
    """Lower the GIL switch interval (see SWITCH_INTERVAL); called by the server, not by tests."""
    sys.setswitchinterval(SWITCH_INTERVAL)
