"""Running one task per object on all local cores or on a dask cluster.

joblib drives both: its ``loky`` backend (worker processes on this machine) by
default, its ``dask`` backend when a ``dask.distributed`` scheduler address is
given.  Results come back as they finish (unordered); callers key them by object
id, so neither the number of workers nor the backend changes what is written.
Randomness is seeded per object and pose inside the tasks, never per worker.
"""

from __future__ import annotations

import contextlib
import sys
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from typing import Any

import joblib
from tqdm import tqdm

from ..numerics import blas_kernel

CONNECT_TIMEOUT_S = 10.0
"""How long to try reaching a dask scheduler before giving up (distributed retries within it)."""


class SchedulerError(RuntimeError):
    """The dask scheduler cannot be reached; the message is one line."""


def default_workers() -> int:
    """Usable cores (respects CPU affinity and container limits)."""
    return max(1, joblib.cpu_count())


@contextlib.contextmanager
def backend(workers: int | None = None, scheduler: str | None = None) -> Iterator[int]:
    """Context in which joblib runs on loky (``workers`` processes) or, with a
    ``scheduler`` address, on that dask.distributed cluster.  Yields ``n_jobs``."""
    if scheduler is None:
        yield workers or default_workers()
        return
    try:
        from distributed import Client
    except ImportError:
        raise SchedulerError("--scheduler needs dask.distributed (pip install 'dask[distributed]')") from None
    try:
        client = Client(scheduler, timeout=f"{CONNECT_TIMEOUT_S}s", set_as_default=True)
    except (OSError, TimeoutError, ValueError) as err:
        raise SchedulerError(f"cannot connect to the dask scheduler at {scheduler}: {err}") from None
    try:
        warning = kernel_mismatch(blas_kernel()["kernel"], client.run(blas_kernel))
        if warning:
            print(f"warning: {warning}", file=sys.stderr)
        with joblib.parallel_config(backend="dask"):
            yield -1  # the cluster decides how many tasks run at once
    finally:
        client.close()


def kernel_mismatch(own: str | None, workers: dict[str, dict]) -> str | None:
    """One line when some dask workers compute with another BLAS kernel than this process (a dask
    worker loads numpy before any task imports ``pipeline``, so ``pipeline.numerics`` cannot pin it),
    else None.  workers : ``client.run(blas_kernel)``, worker address -> ``blas_kernel()``"""
    other = sorted({str(info.get("kernel")) for info in workers.values() if info.get("kernel") != own})
    if not other:
        return None
    return (f"{sum(info.get('kernel') != own for info in workers.values())} of {len(workers)} dask workers compute with "
            f"BLAS kernel {', '.join(other)}, this process with {own}, so their shards may differ in the last bits from "
            f"a local build's; start them with OPENBLAS_CORETYPE={own} (docs/DATASET.md, \"Reproducible across machines\")")


def map_unordered(
    function: Callable[..., Any],
    arguments: Iterable[tuple],
    workers: int | None = None,
    scheduler: str | None = None,
    description: str | None = None,
    progress: bool = False,
) -> Iterator[Any]:
    """Yield ``function(*args)`` for each tuple of ``arguments`` as tasks finish.

    One task per item (``batch_size=1``: items are whole objects, seconds each, and a
    result must be handed back, and saved, as soon as it exists).  With ``workers=1``
    and no scheduler everything runs in this process, in order.
    """
    arguments = list(arguments)
    bar = tqdm(total=len(arguments), desc=description, unit="obj", disable=not progress, file=sys.stderr)
    with backend(workers, scheduler) as n_jobs:
        parallel = joblib.Parallel(n_jobs=n_jobs, batch_size=1, return_as="generator_unordered")
        results = parallel(joblib.delayed(function)(*args) for args in arguments)
        finished = False
        try:
            for result in results:
                bar.update(1)
                yield result
            finished = True
        finally:
            bar.close()
            if not finished:
                # Abandoned on purpose (--strict, an error, Ctrl-C): the cancelled tasks are
                # expected, so joblib's advice about them is noise for the user.
                with warnings.catch_warnings():
                    warnings.filterwarnings("ignore", message=r".*tasks which were still being processed", category=UserWarning)
                    results.close()
                if scheduler is None:
                    stop_local_workers()


def stop_local_workers() -> None:
    """Kill loky's worker processes now.  They outlive an abandoned run otherwise
    (an exception, Ctrl-C, SIGTERM, ``--strict``): loky keeps them for reuse, each
    holding its memory, and joblib warns about the tasks they were still running."""
    from joblib.externals.loky import reusable_executor

    with reusable_executor._executor_lock:  # loky's own handle on its pool (no public accessor)
        executor = reusable_executor._executor
    if executor is not None:
        executor.shutdown(wait=True, kill_workers=True)


class Progress:
    """Progress bar of a dataset build: objects done of total, poses done, failures,
    rate and ETA (tqdm's, over objects computed in this run)."""

    def __init__(self, total: int, already_done: int = 0, enabled: bool = True):
        self.poses = 0
        self.new_poses = 0
        self.failures = 0
        self.started = time.perf_counter()
        self.bar = tqdm(
            total=total,
            initial=already_done,
            desc="objects",
            unit="obj",
            disable=not enabled,
            file=sys.stderr,
            mininterval=0.5,
            dynamic_ncols=True,
        )
        self._postfix()

    def object_done(self, n_poses: int, failed: bool = False) -> None:
        self.poses += n_poses
        self.new_poses += n_poses
        self.failures += int(failed)
        self._postfix()
        self.bar.update(1)

    def _postfix(self) -> None:
        elapsed = max(time.perf_counter() - self.started, 1e-9)
        self.bar.set_postfix_str(
            f"poses={self.poses}, failed={self.failures}, {self.new_poses / elapsed:.2f} poses/s", refresh=False
        )

    def close(self) -> None:
        self.bar.close()
