"""The batch lane: batch bodies are parsed, validated, answered and serialised away from
the event loop that serves the control path (/plan and the single lookups).

Two kinds, ``TOPPLEDB_BATCH_LANE``:

- ``process`` (default where ``fork`` exists): one child process per worker, forked from
  the worker after its dataset is loaded, so it shares the dataset's pages copy-on-write
  instead of loading a copy.  The event loop only hands it the body's bytes and gets the
  answer's bytes back; batch work never holds the worker's interpreter lock, so the
  controller's requests do not wait for it (the OS schedules the two processes on the
  machine's cores).  When the served dataset is swapped, the next batch forks a fresh child
  from the new state; a child that dies is replaced (that batch gets a 503).
- ``thread``: one thread per worker.  The interpreter lock still interleaves it with the
  event loop; the server lowers the switch interval (``SWITCH_INTERVAL``) so the loop waits
  at most about that long for each slice of batch work.

Either way batches queue one behind the other (one lane), at most ``MAX_QUEUED`` per
worker, beyond which a batch is refused at once with 503.
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import multiprocessing
import os
import signal
import sys
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from .errors import ServiceError

MAX_QUEUED = 16
"""Batches waiting for or running in the lane of one worker; more is a 503."""

SWITCH_INTERVAL = 0.0005
"""s, sys.setswitchinterval for the server process (default 0.005): the longest slice a
thread holds the interpreter lock before the event loop may run."""

LANE_ENV = "TOPPLEDB_BATCH_LANE"
PR_SET_PDEATHSIG = 1
"""Linux prctl option: a signal the kernel sends this process when its parent exits."""

_forked: tuple | None = None
"""(store, settings) the process lane's child answers from: set just before it is forked."""


class LaneBusy(ServiceError):
    status_code = 503


def _child_init(parent: int) -> None:
    """In the forked batch process: die with the worker, and leave signals to the worker.

    The fork inherits the server's signal handlers, which would keep the child alive on
    SIGTERM; and a worker killed outright must not leave its child behind."""
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group; the worker decides
    if sys.platform.startswith("linux"):
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the worker died before prctl took effect
        os._exit(0)


def _child_answer(kind: str, body: bytes) -> bytes:
    from .batches import answer_kind

    store, settings = _forked
    return answer_kind(kind, body, store, settings)


def default_kind() -> str:
    kind = os.environ.get(LANE_ENV) or ("process" if "fork" in multiprocessing.get_all_start_methods() else "thread")
    if kind not in ("process", "thread"):
        raise ValueError(f"{LANE_ENV}={kind!r}: expected process or thread")
    return kind


class Lane:
    def __init__(self, kind: str | None = None):
        self.kind = kind or default_kind()
        self.waiting = 0
        self._executor: Executor | None = None
        self._store = None

    def _executor_for(self, store, settings) -> Executor:
        if self.kind == "thread":
            if self._executor is None:
                self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="batch-lane")
            return self._executor
        if self._executor is None or self._store is not store:
            global _forked
            if self._executor is not None:
                self._executor.shutdown(wait=False)  # its running batch finishes on the old build, then it exits
            _forked = (store, settings)
            self._executor = ProcessPoolExecutor(
                max_workers=1, mp_context=multiprocessing.get_context("fork"), initializer=_child_init, initargs=(os.getpid(),)
            )
            self._store = store
        return self._executor

    async def run(self, kind: str, body: bytes, store, settings) -> bytes:
        """``batches.answer_kind(kind, body, store, settings)`` in the lane."""
        if self.waiting >= MAX_QUEUED:
            raise LaneBusy(f"{self.waiting} batches are queued in this worker; retry in a second", retry_after=1)
        self.waiting += 1
        try:
            executor = self._executor_for(store, settings)
            if self.kind == "thread":
                from .batches import answer_kind

                return await asyncio.wrap_future(executor.submit(answer_kind, kind, body, store, settings))
            try:
                return await asyncio.wrap_future(executor.submit(_child_answer, kind, body))
            except BrokenProcessPool:
                self._executor = None  # the next batch forks a new child
                raise LaneBusy("the batch process died (out of memory?); retry", retry_after=1) from None
        finally:
            self.waiting -= 1

    def close(self) -> None:
        """Stop the lane; a batch process is terminated (it holds no state worth waiting for)."""
        if self._executor is not None:
            for process in list(getattr(self._executor, "_processes", {}).values()):
                process.terminate()
            self._executor.shutdown(wait=False, cancel_futures=True)
            self._executor = None


def tune_interpreter() -> None:
    """Lower the interpreter's switch interval (see SWITCH_INTERVAL); called by the server, not by tests."""
    sys.setswitchinterval(SWITCH_INTERVAL)
