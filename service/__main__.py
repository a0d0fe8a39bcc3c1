"""``python -m service --dataset data/dataset [--host 127.0.0.1] [--port 8000] [--workers 2] [--token ...]``.

Binds to 127.0.0.1 unless ``--host`` says otherwise: exposing the service is a decision
for whoever runs it (then give it ``--token`` or ``TOPPLEDB_TOKEN``).  Every option that
is a setting of the app also reads its ``TOPPLEDB_*`` variable (``service.settings``).
"""

from __future__ import annotations

import argparse
import math
import os
import sys

from .server import DEFAULT_KEEP_ALIVE, DEFAULT_LIMIT_CONCURRENCY, DEFAULT_REQUEST_TIMEOUT

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8000


def _ranged(kind: type, low: float, high: float | None = None, low_open: bool = False):
    """An argparse type: ``kind`` in [low, high] (low excluded when ``low_open``), else a one-line
    usage error, so no option starts a service that cannot serve (workers 0, port 70000, ...)."""
    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expects {kind.__name__}, got {text!r}") from None
        if not math.isfinite(value) or (value <= low if low_open else value < low) or (high is not None and value > high):
            bound = f"{'>' if low_open else '>='} {low:g}" + (f" and <= {high:g}" if high is not None else "")
            raise argparse.ArgumentTypeError(f"must be {bound}, got {text}")
        return value
    return parse


def _name(text: str) -> str:
    """A frame's name: not empty, since a client could only match it by sending an empty frame_id."""
    if not text.strip():
        raise argparse.ArgumentTypeError("an empty name")
    return text


def build_parser(prog: str = "python -m service") -> argparse.ArgumentParser:
    """The options; ``prog`` is the command the usage names (``toppledb serve`` from ``pipeline.cli``)."""
    parser = argparse.ArgumentParser(prog=prog, description="Serve a toppledb dataset over HTTP.")
    parser.add_argument("--dataset", default=None, help="dataset directory (default: $TOPPLEDB_DATASET or data/dataset)")
    parser.add_argument("--host", default=DEFAULT_HOST, help="address to bind (default: %(default)s, this machine only)")
    parser.add_argument("--port", type=_ranged(int, 1, 65535), default=DEFAULT_PORT, help="TCP port (default: %(default)s)")
    parser.add_argument("--workers", type=_ranged(int, 1), default=1, help="worker processes, forked after the dataset is mapped (they share it)")
    parser.add_argument("--token", default=None, help="bearer token, at least 16 characters, for every endpoint except /health (better: $TOPPLEDB_TOKEN)")
    parser.add_argument("--max-body-bytes", type=int, default=None, help="largest request body, else 413")
    parser.add_argument("--height-tolerance", type=float, default=None, help="m, largest |z_offset| of an observed pose")
    parser.add_argument("--finger-force-limit", type=float, default=None, help="N, overrides the manifest's")
    parser.add_argument("--frame-id", type=_name, default=None, help="the table frame a ROS pose must be in (default world)")
    parser.add_argument("--watch-seconds", type=_ranged(float, 0), default=None, help="s between checks for a rebuilt dataset; 0: SIGHUP only")
    parser.add_argument("--limit-concurrency", type=_ranged(int, 2), default=DEFAULT_LIMIT_CONCURRENCY, help="503 beyond this many connections (at least 2: uvicorn counts the one being served)")
    parser.add_argument("--timeout-keep-alive", type=_ranged(int, 0), default=DEFAULT_KEEP_ALIVE, help="s an idle connection stays open")
    parser.add_argument("--request-timeout", type=_ranged(float, 0, low_open=True), default=DEFAULT_REQUEST_TIMEOUT, help="s to deliver a whole request")
    parser.add_argument("--access-log", action="store_true", help="log a line per request (off: /metrics counts them)")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    return parser


def main(argv: list[str] | None = None, prog: str = "python -m service") -> int:
    args = build_parser(prog).parse_args(argv)
    from .prefetch import Prefetch

    # The served files' check (SHA-256 of 180 MB) runs while the imports below do: a hint the load
    # takes only if it is the directory Settings names (DEFAULT_DATASET, as service.settings says).
    prefetch = Prefetch(args.dataset or os.environ.get("TOPPLEDB_DATASET") or "data/dataset")
    from .server import listen_problem

    problem = listen_problem(args.host, args.port, args.workers)  # before the load: a port in use is said at once, in a line
    if problem is not None:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    import pyarrow as pa

    # Arrow's default pool (mimalloc) keeps ~120 MB of the load's transient buffers for
    # the life of the process; the system allocator gives them back.
    pa.set_memory_pool(pa.system_memory_pool())
    from .runtime import Runtime
    from .server import run
    from .settings import Settings
    from .staged import StagedApp
    from .store import DatasetError

    try:
        settings = Settings.from_env(
            dataset=args.dataset, token=args.token, max_body_bytes=args.max_body_bytes, height_tolerance=args.height_tolerance,
            finger_force_limit=args.finger_force_limit, frame_id=args.frame_id, watch_seconds=args.watch_seconds,
        )
        runtime = Runtime.open(settings, prefetch)  # once: several workers are forked from this process
    except (DatasetError, ValueError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    store = runtime.live.store
    print(
        f"toppledb: {store.counts['objects']} objects, {store.counts['poses']} poses, "
        f"{store.counts['actions']} actions loaded from {settings.dataset} in {store.load_seconds:.2f} s",
        file=sys.stderr,
    )
    try:
        run(
            StagedApp(runtime), args.host, args.port, workers=args.workers, log_level=args.log_level,
            access_log=args.access_log, limit_concurrency=args.limit_concurrency,
            timeout_keep_alive=args.timeout_keep_alive, request_timeout=args.request_timeout,
        )
    except KeyboardInterrupt:
        # One worker: uvicorn shuts down gracefully on Ctrl-C, then raises it again; that is the
        # stop asked for, not a crash to show as a traceback (forked workers already end with 0).
        pass
    return 0


if __name__ == "__main__":
    sys.exit(main())
