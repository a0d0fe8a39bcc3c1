"""``make bench-service``: start the server on a dataset, load it over TCP, print one JSON line.

    python -m service.bench [--dataset data/dataset] [--workers 1] [--seconds 5] [--connections 32]

The load generator is a minimal HTTP/1.1 keep-alive client written on asyncio streams (uvloop
when installed), in its own process: a request is one ``write`` of prebuilt bytes and a
response one ``readuntil`` of the headers plus one ``readexactly`` of the body, about 20 us of
Python per request, so it stays far from being the bottleneck that httpx (~300 us) would be.
Bodies are real observations: each object's stable poses (GET /objects/{id}/poses/{p}) placed
at random yaws and positions (seeded).  Every phase is bounded in time (``--seconds``).

Phases and keys of the JSON line:
- start-up: ``startup_s`` from launching ``python -m service`` to the first answered /health
  (the control path, /health and POST /plan, is served from then on: ``service.staged``),
  ``api_s`` to the first answered GET /objects (the whole API, once FastAPI is built),
  ``ready_s`` until every worker has started (the server's processes idle); the load starts then;
  ``memory``: resident and proportional memory of the serving processes after the load
  (each worker, and its batch process, which shares the dataset copy-on-write).
- throughput: ``connections`` clients send POST /plan back to back: ``plan_rps``,
  ``plan_p50_ms``, ``plan_p99_ms``, ``plan_errors`` (non-200 or transport errors), and
  ``plan_server_cpu_us_per_request`` (the server's CPU time over requests served: the
  figure that holds when other work shares the cores, as ``load_average`` shows).
- isolation: a 50 Hz controller (one POST /plan every 20 ms on its own connection) alone
  (``controller_alone_p99_ms``), while two clients send 1,000-item /batch/plan back to back
  (``controller_batches_p99_ms``, ``controller_batches_max_ms``, ``batch_items_per_s``), and
  while one client sends 50 MB bodies (``controller_oversized_p99_ms``; those get 413), and
  while two clients send 10-object POST /heaps/plan back to back (``controller_heaps_p99_ms``,
  ``controller_heaps_max_ms``, ``heap_plans_per_s``; null when no heap of served objects fits
  the default bin).
- ``errors``: all unexpected answers over every phase; ``load_average``: the machine's
  1-minute load before the run (other work on the machine skews every number).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import math
import os
import random
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import orjson

ROOT = Path(__file__).resolve().parent.parent
SMALL_DATASET = ROOT / "build" / "bench-service-dataset"
CONTROLLER_HZ = 50.0
BATCH_ITEMS = 1000
OVERSIZED_BYTES = 50 * 1024 * 1024
HEAP_OBJECTS = 10
SEED = 20190101


class Connection:
    """One HTTP/1.1 keep-alive connection; ``request`` returns (status, body)."""

    def __init__(self, host: str, port: int):
        self.host, self.port = host, port
        self.reader = self.writer = None

    async def open(self) -> Connection:
        self.reader, self.writer = await asyncio.open_connection(self.host, self.port)
        return self

    async def request(self, raw: bytes) -> tuple[int, bytes]:
        if self.writer is None:
            await self.open()
        try:
            self.writer.write(raw)
            head = await self.reader.readuntil(b"\r\n\r\n")
            status = int(head[9:12])
            length = 0
            lower = head.lower()
            at = lower.find(b"content-length:")
            if at >= 0:
                length = int(lower[at + 15 : lower.find(b"\r\n", at)])
            body = await self.reader.readexactly(length) if length else b""
            if b"connection: close" in lower:
                self.close()
            return status, body
        except (OSError, asyncio.IncompleteReadError, ValueError):
            self.close()
            raise

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
        self.reader = self.writer = None


def post(path: str, body: bytes) -> bytes:
    return (f"POST {path} HTTP/1.1\r\nhost: bench\r\ncontent-type: application/json\r\ncontent-length: {len(body)}\r\n\r\n"
            .encode() + body)


def get(path: str) -> bytes:
    return f"GET {path} HTTP/1.1\r\nhost: bench\r\n\r\n".encode()


def percentile_ms(samples: list[float], q: float) -> float | None:
    return round(float(np.percentile(samples, q)) * 1000, 2) if samples else None


async def observations(conn: Connection, count: int, rng: random.Random) -> list[dict]:
    """``count`` plan requests: stable poses of the served objects at random planar placements."""
    _, body = await conn.request(get("/objects"))
    objects = [o["object_id"] for o in json.loads(body)["objects"]]
    transforms = []
    for object_id in rng.sample(objects, min(len(objects), 40)):
        _, body = await conn.request(get(f"/objects/{object_id}"))
        n_poses = len(json.loads(body)["poses"])
        for pose in range(min(n_poses, 6)):
            _, body = await conn.request(get(f"/objects/{object_id}/poses/{pose}"))
            transforms.append((object_id, np.array(json.loads(body)["transform"])))
    requests = []
    for _ in range(count):
        object_id, transform = rng.choice(transforms)
        yaw = rng.uniform(-math.pi, math.pi)
        planar = np.eye(4)
        planar[:2, :2] = [[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]]
        planar[:2, 3] = [rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5)]
        requests.append({"object_id": object_id, "pose": (planar @ transform).tolist(), "policy": "value_iteration"})
    return requests


async def hammer(host, port, bodies: list[bytes], seconds: float, connections: int) -> dict:
    """``connections`` clients send /plan back to back for ``seconds``."""
    latencies: list[float] = []
    errors = 0
    stop = time.perf_counter() + seconds

    async def client(k: int):
        nonlocal errors
        conn = Connection(host, port)
        i = k
        while time.perf_counter() < stop:
            raw = bodies[i % len(bodies)]
            i += connections
            started = time.perf_counter()
            try:
                status, _ = await conn.request(raw)
            except (OSError, asyncio.IncompleteReadError, ValueError):
                errors += 1
                continue
            latencies.append(time.perf_counter() - started)
            errors += status != 200
        conn.close()

    began = time.perf_counter()
    await asyncio.gather(*(client(k) for k in range(connections)))
    elapsed = time.perf_counter() - began
    return {"rps": round(len(latencies) / elapsed, 1), "elapsed": elapsed, "p50": percentile_ms(latencies, 50), "p99": percentile_ms(latencies, 99),
            "errors": errors}


async def controller(host, port, bodies: list[bytes], seconds: float, background=None) -> dict:
    """A 50 Hz controller's /plan latencies, optionally while ``background`` coroutines run."""
    stop_event = asyncio.Event()
    tasks = [asyncio.create_task(b(stop_event)) for b in (background or [])]
    await asyncio.sleep(0.2 if tasks else 0)  # let the background load start
    conn = Connection(host, port)
    latencies, errors = [], 0
    period = 1.0 / CONTROLLER_HZ
    next_at = time.perf_counter()
    stop = next_at + seconds
    i = 0
    while time.perf_counter() < stop:
        started = time.perf_counter()
        try:
            status, _ = await conn.request(bodies[i % len(bodies)])
            errors += status != 200
            latencies.append(time.perf_counter() - started)
        except (OSError, asyncio.IncompleteReadError, ValueError):
            errors += 1
        i += 1
        next_at += period
        await asyncio.sleep(max(0.0, next_at - time.perf_counter()))
    conn.close()
    stop_event.set()
    results = await asyncio.gather(*tasks)
    return {"p50": percentile_ms(latencies, 50), "p99": percentile_ms(latencies, 99),
            "max": round(max(latencies) * 1000, 2) if latencies else None, "errors": errors, "background": results}


def batch_sender(host, port, raw: bytes, items_per_request: int = BATCH_ITEMS):
    """A client sending ``raw`` back to back (a batch of ``items_per_request`` items, or one heap plan)."""
    async def run(stop: asyncio.Event) -> dict:
        conn, items, errors = Connection(host, port), 0, 0
        began = time.perf_counter()
        while not stop.is_set():
            try:
                status, _ = await conn.request(raw)
                items += items_per_request if status == 200 else 0
                errors += status != 200
            except (OSError, asyncio.IncompleteReadError, ValueError):
                errors += 1
        conn.close()
        return {"items_per_s": items / (time.perf_counter() - began), "errors": errors}

    return run


async def heap_body(conn: Connection, requests: list[dict], rng: random.Random) -> bytes | None:
    """A POST /heaps/plan of HEAP_OBJECTS served objects, one per cell of a grid in the default
    bin (boundary_shear, the thesis's robot policy), that the server plans; None if too few fit.
    Observations are tried in a seeded order; one whose object reaches past a wall (409) is skipped."""
    cells = [(x, y) for y in (-0.1, 0.1) for x in (-0.18, -0.09, 0.0, 0.09, 0.18)]
    heap = []
    for request in rng.sample(requests, len(requests)):
        pose = np.array(request["pose"])
        pose[:2, 3] = cells[len(heap)]
        candidate = post("/heaps/plan", orjson.dumps({"objects": [*heap, {"object_id": request["object_id"], "pose": pose.tolist()}]}))
        status, _ = await conn.request(candidate)
        if status == 200:  # it fits in its cell
            heap.append({"object_id": request["object_id"], "pose": pose.tolist()})
            if len(heap) == HEAP_OBJECTS:
                return candidate
    return None


def oversized_sender(host, port):
    async def run(stop: asyncio.Event) -> dict:
        head = (f"POST /batch/plan HTTP/1.1\r\nhost: bench\r\ncontent-type: application/json\r\n"
                f"content-length: {OVERSIZED_BYTES}\r\n\r\n").encode()
        first = b" " * (1024 * 1024)  # the first MB of the 50; the server answers before it needs more
        sent, unexpected = 0, 0
        while not stop.is_set():
            writer = None
            try:
                reader, writer = await asyncio.open_connection(host, port)
                writer.write(head + first)
                head_in = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), 5)
                unexpected += int(head_in[9:12]) != 413
            except (TimeoutError, OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
                unexpected += 1
            finally:
                if writer is not None:
                    writer.close()
            sent += 1
            await asyncio.sleep(0)
        return {"oversized_sent": sent, "errors": unexpected}

    return run


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def ensure_dataset(dataset: Path | None) -> Path:
    """``dataset``, else data/dataset when built, else a small one built here (3 objects)."""
    if dataset is not None:
        return dataset
    if (ROOT / "data" / "dataset" / "manifest.json").is_file():
        return ROOT / "data" / "dataset"
    if not (SMALL_DATASET / "manifest.json").is_file():
        print(f"bench-service: no data/dataset; building a small one in {SMALL_DATASET}", file=sys.stderr)
        subprocess.run(
            [sys.executable, "-m", "pipeline", "dataset", "--out", str(SMALL_DATASET), "--limit", "3", "--contacts", "200",
             "--trials", "5", "--workers", "1", "--no-progress"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL,
        )
    return SMALL_DATASET


def memory_mb(pid: int) -> dict:
    """Resident and proportional (PSS: shared pages split between sharers) MB of the server's
    processes over 50 MB: the worker(s), and each worker's forked batch process, which shares
    the dataset's pages copy-on-write (so their RSS double-counts; their PSS does not)."""
    import psutil

    parent = psutil.Process(pid)
    processes = [p for p in [parent, *parent.children(recursive=True)] if p.memory_info().rss > 50e6]
    info = [p.memory_full_info() for p in processes]
    return {"rss_mb": [round(i.rss / 1e6, 1) for i in info], "pss_mb": [round(i.pss / 1e6, 1) for i in info],
            "pss_mb_total": round(sum(i.pss for i in info) / 1e6, 1)}


def cpu_seconds(pid: int) -> float:
    """User + system CPU s of the server and its workers so far."""
    import psutil

    parent = psutil.Process(pid)
    total = 0.0
    for process in [parent, *parent.children(recursive=True)]:
        times = process.cpu_times()
        total += times.user + times.system
    return total


async def run_load(host: str, port: int, seconds: float, connections: int, pid: int) -> dict:
    rng = random.Random(SEED)
    conn = await Connection(host, port).open()
    requests = await observations(conn, 2000, rng)
    plan_bodies = [post("/plan", orjson.dumps(r)) for r in requests]
    batch_body = post("/batch/plan", orjson.dumps({"items": requests[:BATCH_ITEMS]}))
    heap = await heap_body(conn, requests, rng)
    conn.close()

    cpu_before = cpu_seconds(pid)
    throughput = await hammer(host, port, plan_bodies, seconds, connections)
    served = throughput["rps"] * throughput["elapsed"]
    cpu_per_request_us = round((cpu_seconds(pid) - cpu_before) / max(served, 1) * 1e6, 1)
    alone = await controller(host, port, plan_bodies, seconds)
    batches = await controller(host, port, plan_bodies, seconds, [batch_sender(host, port, batch_body) for _ in range(2)])
    oversized = await controller(host, port, plan_bodies, seconds, [oversized_sender(host, port)])
    heaps = (await controller(host, port, plan_bodies, seconds, [batch_sender(host, port, heap, 1) for _ in range(2)])
             if heap is not None else {"p99": None, "max": None, "errors": 0, "background": []})
    errors = throughput["errors"] + alone["errors"] + batches["errors"] + oversized["errors"] + heaps["errors"]
    errors += sum(b["errors"] for phase in (batches, oversized, heaps) for b in phase["background"])
    return {
        "plan_rps": throughput["rps"], "plan_p50_ms": throughput["p50"], "plan_p99_ms": throughput["p99"],
        "plan_errors": throughput["errors"], "connections": connections, "plan_server_cpu_us_per_request": cpu_per_request_us,
        "controller_alone_p99_ms": alone["p99"],
        "controller_batches_p99_ms": batches["p99"], "controller_batches_max_ms": batches["max"],
        "batch_items_per_s": round(sum(b["items_per_s"] for b in batches["background"]), 1),
        "controller_oversized_p99_ms": oversized["p99"],
        "oversized_bodies_refused": sum(b["oversized_sent"] for b in oversized["background"]),
        "controller_heaps_p99_ms": heaps["p99"], "controller_heaps_max_ms": heaps["max"],
        "heap_plans_per_s": round(sum(b["items_per_s"] for b in heaps["background"]), 1),
        "errors": errors,
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m service.bench", description=__doc__.split("\n")[0])
    parser.add_argument("--dataset", type=Path, default=None, help="default: data/dataset if built, else a small one")
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=5.0, help="length of each phase")
    parser.add_argument("--connections", type=int, default=32)
    parser.add_argument("--attach", type=int, metavar="PID", default=None,
                        help="load an already running server (this process id, --port) instead of starting one")
    parser.add_argument("--port", type=int, default=None, help="with --attach: its port on 127.0.0.1")
    args = parser.parse_args(argv)
    if args.attach is not None:
        import uvloop

        result = uvloop.run(run_load("127.0.0.1", args.port, args.seconds, args.connections, args.attach))
        print(json.dumps({"attached": args.attach, **result, "memory": memory_mb(args.attach),
                          "load_average": round(os.getloadavg()[0], 2)}))
        return 0
    dataset = ensure_dataset(args.dataset)
    port = free_port()
    load_average = os.getloadavg()[0]
    launched = time.perf_counter()
    server = subprocess.Popen(
        [sys.executable, "-m", "service", "--dataset", str(dataset), "--port", str(port), "--workers", str(args.workers),
         "--log-level", "warning", "--watch-seconds", "0"],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, start_new_session=True,
    )
    try:
        startup = _wait_for("/health", port, server, launched)
        api = _wait_for("/objects", port, server, launched)
        ready = _wait_until_idle(server.pid, launched)  # the other workers may still be starting
        try:
            import uvloop

            runner = uvloop.run
        except ImportError:
            runner = asyncio.run
        result = runner(run_load("127.0.0.1", port, args.seconds, args.connections, server.pid))
        memory = memory_mb(server.pid)
    finally:
        stop_group(server)
    line = {"dataset": str(dataset), "workers": args.workers, "startup_s": round(startup, 3), "api_s": round(api, 3), "ready_s": round(ready, 3), **result,
            "memory": memory, "load_average": round(load_average, 2)}
    print(json.dumps(line))
    return 0 if result["errors"] == 0 else 1


def stop_group(server: subprocess.Popen) -> None:
    """SIGTERM the server's whole process group (workers, batch processes), SIGKILL what is left."""
    import signal

    try:
        os.killpg(server.pid, signal.SIGTERM)
        server.wait(timeout=20)
    except subprocess.TimeoutExpired:
        pass
    except ProcessLookupError:
        return
    with contextlib.suppress(ProcessLookupError):
        os.killpg(server.pid, signal.SIGKILL)
    server.wait()


IDLE_CPU = 0.1
"""Share of one core below which the server's processes count as idle (every worker loaded)."""


def _wait_until_idle(pid: int, launched: float, window: float = 0.3, timeout: float = 60.0) -> float:
    """s from launch until the server's process group uses less than ``IDLE_CPU`` of a core over
    ``window`` s: with several workers, the first answers /health while the others still import
    and map the dataset, and load phases started then would measure their start-up."""
    import psutil

    def cpu() -> float:
        total = 0.0
        with contextlib.suppress(psutil.Error):
            parent = psutil.Process(pid)
            for process in [parent, *parent.children(recursive=True)]:
                with contextlib.suppress(psutil.Error):
                    times = process.cpu_times()
                    total += times.user + times.system
        return total

    deadline = time.perf_counter() + timeout
    before = cpu()
    while time.perf_counter() < deadline:
        time.sleep(window)
        now = cpu()
        if now - before < IDLE_CPU * window:
            return time.perf_counter() - window - launched
        before = now
    return time.perf_counter() - launched


def _wait_for(path: str, port: int, server: subprocess.Popen, launched: float, timeout: float = 120.0) -> float:
    """s from launch to the first 200 on GET ``path``."""
    raw = get(path)
    while time.perf_counter() - launched < timeout:
        if server.poll() is not None:
            raise SystemExit(f"bench-service: the server exited: {server.stderr.read().decode()[-2000:]}")
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1) as s:
                s.sendall(raw)
                if s.recv(16)[9:12] == b"200":
                    return time.perf_counter() - launched
        except OSError:
            pass
        time.sleep(0.01)
    raise SystemExit(f"bench-service: no answer from {path} in {timeout:.0f} s")


if __name__ == "__main__":
    sys.exit(main())
