"""``python -m service --dataset data/dataset [--host 127.0.0.1] [--port 8000]``.

Binds to 127.0.0.1 unless ``--host`` says otherwise: the service has no
authentication, so exposing it is a decision for whoever runs it.
"""

from __future__ import annotations

import argparse
import sys

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8000


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m service", description="Serve a toppledb dataset over HTTP.")
    parser.add_argument("--dataset", default="data/dataset", help="dataset directory (default: %(default)s)")
    parser.add_argument("--host", default=DEFAULT_HOST, help="address to bind (default: %(default)s, this machine only)")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port (default: %(default)s)")
    parser.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    import pyarrow as pa

    # Arrow's default pool (mimalloc) keeps ~120 MB of the load's transient buffers for
    # the life of the process; the system allocator gives them back.
    pa.set_memory_pool(pa.system_memory_pool())
    from .app import create_app
    from .store import DatasetError

    try:
        app = create_app(args.dataset)
    except DatasetError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    import uvicorn

    store = app.state.store
    print(
        f"toppledb: {store.counts['objects']} objects, {store.counts['poses']} poses, "
        f"{store.counts['actions']} actions loaded from {args.dataset} in {store.load_seconds:.1f} s",
        file=sys.stderr,
    )
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level)
    return 0


if __name__ == "__main__":
    sys.exit(main())
