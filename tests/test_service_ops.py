# ruff: noqa: F811  (pytest fixture imported from tests/test_service.py)
"""Operating the service: swapping to a rebuilt dataset without failing a request, SIGHUP,
closing connections that never finish their request, no access log by default, and the
forked workers of ``--workers N`` (the tiny dataset of tests/test_service.py)."""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace

import httpx
import psutil
import pytest
from fastapi.testclient import TestClient

from service import create_app
from service.__main__ import DEFAULT_HOST, build_parser
from service.client import plan_item
from service.runtime import Runtime
from service.settings import Settings
from service.store import DatasetError, LiveStore, Store
from tests.test_service import ROOT, dataset, tables  # noqa: F401 (fixtures)

DEADLINE = 30.0
"""s, the most any wait here takes before the test fails (generous: 2 shared cores)."""


def rebuilt(directory: Path, created: str) -> None:
    """Stand-in for a rebuild: the same tables under a new manifest (written atomically, as the pipeline does)."""
    manifest = json.loads((directory / "manifest.json").read_text())
    manifest["created"] = created
    tmp = directory / "manifest.json.tmp"
    tmp.write_text(json.dumps(manifest))
    os.replace(tmp, directory / "manifest.json")


def wait_for(predicate, what: str):
    deadline = time.monotonic() + DEADLINE
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise AssertionError(f"timed out waiting for {what}")


def test_live_store_swaps_only_for_a_new_readable_build(dataset, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    live = LiveStore(Store.load(copy))
    first = live.store
    assert not live.changed() and not live.reload()
    rebuilt(copy, "2030-01-01T00:00:00+00:00")
    assert live.changed() and live.reload() and live.reloads == 1
    assert live.store is not first and live.store.manifest.created == "2030-01-01T00:00:00+00:00"
    assert live.store.manifest_sha256 != first.manifest_sha256
    # A half-written rebuild is refused; the good build keeps being served, and is not retried until it changes.
    good = (copy / "manifest.json").read_bytes()
    (copy / "manifest.json").write_text("{")
    served = live.store
    assert live.reload_error is None and live.failed_reloads == 0
    assert live.changed() and not live.reload() and live.store is served and not live.changed()
    assert live.failed_reloads == 1 and "manifest.json" in live.reload_error
    # The served build written back: nothing to swap, and nothing wrong any more.
    (copy / "manifest.json").write_bytes(good)
    assert live.changed() and not live.reload() and live.store is served
    assert live.reload_error is None and live.failed_reloads == 1 and live.reloads == 1
    # Broken again, then the served manifest renamed back into place: its stamp is the served one, so no
    # reload is tried, and the error goes with the broken file.
    (copy / "manifest.json").rename(copy / "served.json")
    (copy / "manifest.json").write_text("{")
    assert live.changed() and not live.reload() and live.reload_error is not None and live.failed_reloads == 2
    failures = []
    live.on_failure = lambda: failures.append(1)
    (copy / "served.json").replace(copy / "manifest.json")
    assert not live.changed() and live.reload_error is None
    # Overlapping reloads of one broken build count it once.
    (copy / "manifest.json").write_text("[]")
    with concurrent.futures.ThreadPoolExecutor(4) as pool:
        assert not any(pool.map(lambda force: live.reload(force=force), [False, True, True, True]))
    assert failures == [1] and live.failed_reloads == 3 and live.store is served


def test_live_store_keeps_an_identical_build_swaps_when_forced_and_logs_each_swap_and_failure_once(dataset, tmp_path, caplog):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    live = LiveStore(Store.load(copy))
    first = live.store
    # The same bytes written again as a new file: nothing to swap, and nothing to look at until it changes again.
    tmp = copy / "manifest.json.tmp"
    tmp.write_bytes((copy / "manifest.json").read_bytes())
    os.replace(tmp, copy / "manifest.json")
    assert live.changed() and not live.reload() and live.store is first and not live.changed()
    with caplog.at_level(logging.WARNING, logger="service"):
        assert live.reload(force=True) and live.store is not first and live.reloads == 1  # SIGHUP: the same build again
        rebuilt(copy, "2030-01-01T00:00:00+00:00")
        assert live.reload() and live.reloads == 2
        serving = live.store.manifest_sha256[:12]
        refused = []
        for broken, again in (("{", True), ("[]", False)):  # two failed builds, each logged once, even when forced again
            (copy / "manifest.json").write_text(broken)
            with pytest.raises(DatasetError) as error:
                Store.load(copy)
            refused.append(str(error.value))
            assert not live.reload() and not live.reload(force=again) and live.reloads == 2
    messages = [record.getMessage() for record in caplog.records]
    swaps = [m for m in messages if m.startswith("now serving")]
    assert len(swaps) == 2 and swaps[1].startswith(f"now serving {copy} manifest {serving} (3 objects, loaded in ")
    failures = [m for m in messages if m.startswith("reload of")]
    assert failures == [f"reload of {copy} failed, still serving manifest {serving}: {reason}" for reason in refused]


def test_the_watcher_swaps_builds_while_requests_keep_succeeding(dataset, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    with TestClient(create_app(copy, settings=Settings(watch_seconds=0.05))) as client:
        before = client.get("/health").json()["dataset"]["manifest_sha256"]
        assert client.get("/objects/random_001/poses/0/q").headers["x-toppledb-build"] == before
        rebuilt(copy, "2031-01-01T00:00:00+00:00")
        statuses = []

        def swapped():
            statuses.append(client.get("/objects/random_001/poses/0/q").status_code)
            return client.get("/health").json()["reloads"] == 1

        wait_for(swapped, "the watcher to load the rebuilt dataset")
        health = client.get("/health").json()
        assert health["dataset"]["manifest_sha256"] != before and health["dataset"]["created"].startswith("2031")
        assert set(statuses) == {200}
        # Each answer names the build it came from: a controller sees the swap without polling /health.
        assert client.get("/objects/random_001/poses/0/q").headers["x-toppledb-build"] == health["dataset"]["manifest_sha256"]
        # A request naming the build its action indices came from is refused once that build is replaced.
        stale = client.get("/objects/random_001/poses/0/actions/0", headers={"x-toppledb-build": before})
        assert stale.status_code == 412 and stale.json()["build"] == health["dataset"]["manifest_sha256"]
        assert 'toppledb_dataset_reloads_total 1.0' in client.get("/metrics").text
        assert "reload_error" not in health  # left out while there is none: older clients' models forbid it
        # A broken rebuild: still served, and /health and /metrics say why the new one is not.
        (copy / "manifest.json").write_text("[]")
        broken = wait_for(lambda: client.get("/health").json().get("reload_error"), "the watcher to try the broken build")
        assert "schema version None" in broken
        assert client.get("/health").json()["dataset"]["manifest_sha256"] == health["dataset"]["manifest_sha256"]
        assert 'toppledb_dataset_reload_failures_total 1.0' in client.get("/metrics").text
        assert client.get("/objects/random_001/poses/0/q").status_code == 200


def _swapping(live, real):
    """``real``, with the served store swapped for another build while it runs (and back after)."""
    def swapped(*args, **kwargs):
        served, live.store = live.store, SimpleNamespace(manifest_sha256="f" * 64)
        try:
            return real(*args, **kwargs)
        finally:
            live.store = served
    return swapped


@pytest.mark.parametrize("staged", [False, True], ids=["create_app", "staged"])
def test_the_build_header_names_the_build_a_request_took_even_if_a_swap_comes_during_it(dataset, tables, monkeypatch,
                                                                                           staged):
    """The header is what ``get_store`` or the fast /plan path took when the request arrived, not the store
    served when the answer is sent: on the fast path, on a route that plans in an executor (/heaps/plan), on
    FastAPI's app and on the staged server that answers before FastAPI is built."""
    from service import fastplan, planning
    from service.routers import heaps
    from tests.test_service import planar_transform, stored_transform
    from tests.test_service_client import pushing
    from tests.test_service_staged import staged_app

    if staged:
        app = staged_app(dataset)
        live = app.runtime.live
    else:
        app = create_app(dataset, settings=Settings())
        live = app.state.live
    with TestClient(app) as client:
        build = client.get("/health").json()["dataset"]["manifest_sha256"]
        object_id, pose = pushing(tables)
        observed = planar_transform(0.4, 0.1, 0.2) @ stored_transform(tables, object_id, pose)
        monkeypatch.setattr(fastplan, "plan", _swapping(live, planning.plan))
        monkeypatch.setattr(heaps, "plan_heap", _swapping(live, heaps.plan_heap))
        answers = [client.post("/plan", json=plan_item(object_id, pose=observed)),
                   client.post("/heaps/plan", json={"objects": [{"object_id": object_id,
                                                                   "pose": stored_transform(tables, object_id, pose).tolist()}]})]
        assert [a.status_code for a in answers] == [200, 200]
        assert all(a.headers.get_list("x-toppledb-build") == [build] for a in answers)


# --- the runtime: /health's answer, swaps, the watcher, a worker's life ------------------------


def runtime_of(directory: Path, **settings) -> Runtime:
    runtime = Runtime.open(Settings.from_env(dataset=directory, **settings))
    runtime.lane = SimpleNamespace(closed=0)
    runtime.lane.close = lambda: setattr(runtime.lane, "closed", runtime.lane.closed + 1)
    return runtime


def served(runtime: Runtime) -> list[str]:
    """The ``toppledb_dataset_info`` series /metrics shows (one per build: the gauge is cleared on a swap)."""
    return [line for line in runtime.metrics.render().decode().splitlines() if line.startswith("toppledb_dataset_info{")]


def test_runtime_health_reports_the_store_it_is_given_and_reload_error_only_while_one_fails(dataset, tmp_path):
    from schema.version import CODE_VERSION
    from service.guard import BUILD_SCOPE_KEY

    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    runtime = runtime_of(copy)
    other = Store.load(dataset)
    other.load_seconds = 1.23456
    health = runtime.health(other)
    assert (health.status, health.schema_version, health.service_version) == ("ok", other.schema_version, CODE_VERSION)
    assert health.dataset.path == str(dataset) and health.dataset.manifest_sha256 == other.manifest_sha256
    assert (health.dataset.created, health.dataset.code_version, health.dataset.parameters_sha256, health.dataset.loaded_at) == (
        other.manifest.created, other.code_version, other.parameters_sha256, other.loaded_at)
    assert health.counts.model_dump() == other.counts and health.load_seconds == 1.235
    assert (health.reloads, health.reload_error) == (0, None)
    scope: dict = {}
    body = json.loads(runtime.health_json(scope))
    assert "reload_error" not in body and body["dataset"]["path"] == str(copy) and body["reloads"] == 0
    assert scope[BUILD_SCOPE_KEY] == runtime.live.store.manifest_sha256 == body["dataset"]["manifest_sha256"]
    runtime.live.reloads, runtime.live.reload_error = 3, "manifest.json is not JSON"
    body = json.loads(runtime.health_json({}))
    assert (body["reloads"], body["reload_error"]) == (3, "manifest.json is not JSON")


def test_runtime_reload_swaps_only_a_new_build_unless_forced_and_says_so_to_metrics_and_callbacks(dataset, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    runtime = runtime_of(copy)
    swaps = []
    runtime.on_swap.append(lambda: swaps.append(runtime.live.store.manifest.created))
    runtime.on_swap.append(lambda: swaps.append("second"))
    first = served(runtime)
    created = runtime.live.store.manifest.created
    assert len(first) == 1 and runtime.live.store.manifest_sha256 in first[0] and f'created="{created}"' in first[0]
    assert not asyncio.run(runtime.reload()) and swaps == [] and served(runtime) == first
    rebuilt(copy, "2033-01-01T00:00:00+00:00")
    assert asyncio.run(runtime.reload()) and swaps == ["2033-01-01T00:00:00+00:00", "second"]
    now = served(runtime)
    assert len(now) == 1 and runtime.live.store.manifest_sha256 in now[0] and 'created="2033-01-01T00:00:00+00:00"' in now[0]
    assert "toppledb_dataset_reloads_total 1.0" in runtime.metrics.render().decode()
    assert asyncio.run(runtime.reload(force=True)) and len(swaps) == 4  # SIGHUP: the same build again
    assert "toppledb_dataset_reloads_total 2.0" in runtime.metrics.render().decode()


def test_the_watcher_keeps_watching_after_a_failed_check(dataset, tmp_path, caplog):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    runtime = runtime_of(copy, watch_seconds=0.02)
    checks, real = [], runtime.live.changed

    def changed():  # the first check fails; the watcher logs it and checks again
        checks.append(True)
        if len(checks) == 1:
            raise OSError("the disk went away")
        return real()

    runtime.live.changed = changed

    async def watch():
        task = asyncio.create_task(runtime._watch())
        await asyncio.sleep(0.5)
        task.cancel()

    rebuilt(copy, "2034-01-01T00:00:00+00:00")
    with caplog.at_level(logging.ERROR, logger="service"):
        asyncio.run(watch())
    assert len(checks) >= 3 and runtime.live.store.manifest.created.startswith("2034") and runtime.live.reloads == 1
    assert [r.getMessage() for r in caplog.records] == ["dataset watcher: reload failed"]
    assert "the disk went away" in caplog.text


def test_runtime_solves_every_objects_budgets_in_a_daemon_thread_of_its_own(dataset):
    runtime = runtime_of(dataset)
    assert all(obj._budgets is None for obj in runtime.live.store.objects.values())
    store, release = runtime.live.store, threading.Event()
    store.solve_budgets = lambda: release.wait(30) and Store.solve_budgets(store)  # held until the thread is seen
    runtime.solve_budgets()
    solver = [thread for thread in threading.enumerate() if thread.name == "budgets"]
    assert len(solver) == 1 and solver[0].daemon  # a worker's exit does not wait for it
    release.set()
    solver[0].join(30)
    assert all(obj._budgets is not None for obj in runtime.live.store.objects.values())


@pytest.mark.parametrize("watch_seconds", [0.0, 0.02])
def test_a_workers_life_reloads_a_build_swapped_before_it_watches_only_when_asked_and_answers_sighup(
        dataset, tmp_path, watch_seconds):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    runtime = runtime_of(copy, watch_seconds=watch_seconds)
    rebuilt(copy, "2035-01-01T00:00:00+00:00")  # swapped in by the other workers before this one was forked
    seen = {}

    async def life():
        async with runtime.serving():
            seen["start"] = runtime.live.store.manifest.created, runtime.live.reloads, served(runtime)
            rebuilt(copy, "2036-01-01T00:00:00+00:00")
            await asyncio.sleep(0.3)
            seen["watched"] = runtime.live.store.manifest.created
            os.kill(os.getpid(), signal.SIGHUP)
            await asyncio.sleep(0.3)
            seen["hup"] = runtime.live.reloads
            assert runtime.lane.closed == 0
        seen["handler"] = signal.getsignal(signal.SIGHUP)
        rebuilt(copy, "2037-01-01T00:00:00+00:00")
        await asyncio.sleep(0.3)  # the watcher stopped with the worker
        seen["after"] = runtime.live.store.manifest.created

    def before(signum, frame):  # the disposition the worker starts with, whatever this process inherited (nohup: SIG_IGN)
        raise AssertionError("SIGHUP reached the disposition the worker started with")

    inherited = signal.signal(signal.SIGHUP, before)
    try:
        asyncio.run(life())
    finally:
        signal.signal(signal.SIGHUP, inherited)
    created, reloads, metrics = seen["start"]
    assert created.startswith("2035") and reloads == 1 and len(metrics) == 1 and 'created="2035' in metrics[0]
    assert seen["watched"].startswith("2036" if watch_seconds else "2035")
    assert seen["hup"] == (3 if watch_seconds else 2)  # a SIGHUP reloads even the same build
    assert seen["after"].startswith("2036") and runtime.lane.closed == 1
    assert seen["handler"] is before  # given back as it was (asyncio alone leaves SIG_DFL)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start(args: list[str], env: dict | None = None) -> tuple[subprocess.Popen, str]:
    port = free_port()
    process = subprocess.Popen(
        [*args, "--port", str(port)], cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        env={**os.environ, "PYTHONUNBUFFERED": "1", **(env or {})}, start_new_session=True,
    )
    url = f"http://127.0.0.1:{port}"

    def up():
        assert process.poll() is None, process.stderr.read().decode()
        try:
            return httpx.get(f"{url}/health", timeout=1).status_code == 200
        except httpx.TransportError:
            return False

    try:
        wait_for(up, "the server to answer /health")
    except BaseException:
        stop(process)
        raise
    return process, url


@contextlib.contextmanager
def two_worker_server(dataset, *extra: str):
    """A ``--workers 2`` server on ``dataset`` (no watcher), both workers forked: a namespace with
    ``process``, ``url``, ``workers``; after the block it is stopped and ``out``, ``err`` hold its output."""
    process, url = start([sys.executable, "-m", "service", "--dataset", str(dataset), "--workers", "2", "--watch-seconds", "0", *extra])
    server = SimpleNamespace(process=process, url=url, workers=None, out="", err="")
    try:
        server.workers = wait_for(lambda: len(w := psutil.Process(process.pid).children()) == 2 and w, "two workers")
        yield server
    finally:
        server.out, server.err = stop(process)


def stop(process: subprocess.Popen) -> tuple[str, str]:
    """SIGINT the server; then SIGKILL its whole process group (workers too) if it lingers."""
    process.send_signal(signal.SIGINT)
    try:
        out, err = process.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(process.pid, signal.SIGKILL)  # the server and its workers
        out, err = process.communicate()
    return out.decode(), err.decode()


@pytest.mark.parametrize("option, value", [
    ("--workers", "0"), ("--workers", "-2"), ("--port", "70000"), ("--port", "0"), ("--limit-concurrency", "0"),
    # uvicorn counts the connection it serves: a limit of 1 answers every request 503.
    ("--limit-concurrency", "1"),
    ("--request-timeout", "0"), ("--request-timeout", "nan"), ("--request-timeout", "inf"), ("--timeout-keep-alive", "-1"),
    ("--watch-seconds", "-1"), ("--watch-seconds", "inf"), ("--workers", "two"),
])
def test_options_that_would_start_a_service_that_cannot_serve_are_refused(option, value, capsys):
    """Each of these used to start a service that exits at once, listens elsewhere, refuses or
    drops every request; they are usage errors (exit 2) naming the option."""
    with pytest.raises(SystemExit) as refused:
        build_parser().parse_args([option, value])
    assert refused.value.code == 2
    assert f"argument {option}: " in capsys.readouterr().err
    sane = {"--workers": "2", "--port": "65535", "--limit-concurrency": "2", "--request-timeout": "0.5",
            "--timeout-keep-alive": "0", "--watch-seconds": "0"}[option]
    assert build_parser().parse_args([option, sane]) is not None


def test_the_usage_names_the_command_typed(capsys):
    from pipeline.cli import main as toppledb

    with pytest.raises(SystemExit) as shown:
        toppledb(["serve", "--help"])
    assert shown.value.code == 0 and capsys.readouterr().out.startswith("usage: toppledb serve [-h]")
    assert build_parser().format_usage().startswith("usage: python -m service [-h]")


def test_a_port_in_use_is_one_line_and_exit_2_before_the_dataset_is_loaded(dataset):
    """It used to load the dataset, say "loaded", start, then log uvicorn's [Errno 98] and exit 3."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        run = subprocess.run([sys.executable, "-m", "pipeline", "serve", "--dataset", str(dataset), "--port", str(port)],
                             cwd=ROOT, capture_output=True, text=True, timeout=60, check=False)
    assert run.returncode == 2
    assert run.stderr == f"error: cannot listen on 127.0.0.1:{port}: address already in use; choose another --port\n"


def test_the_port_check_binds_what_the_server_will_bind(monkeypatch):
    """A family the machine cannot open (IPv6 disabled while the host resolves to ::1 too) is
    skipped, as asyncio skips it; several workers share one socket of the host's written family,
    so only that address is checked; a port in use is refused either way."""
    from service.server import listen_problem

    real_socket = socket.socket
    resolved = [(socket.AF_INET6, socket.SOCK_STREAM, 6, "", ("::1", 0, 0, 0)),
                (socket.AF_INET, socket.SOCK_STREAM, 6, "", ("127.0.0.1", 0))]
    asked = []

    def getaddrinfo(host, port, family=0, *args):
        asked.append(family)
        return [(f, k, p, c, (a[0], port, *a[2:])) for f, k, p, c, a in resolved if family in (0, f)]

    def no_ipv6(family=socket.AF_INET, *args, **kwargs):
        if family == socket.AF_INET6:
            raise OSError(97, "Address family not supported by protocol")
        return real_socket(family, *args, **kwargs)

    monkeypatch.setattr(socket, "getaddrinfo", getaddrinfo)
    monkeypatch.setattr(socket, "socket", no_ipv6)
    with real_socket() as probe:
        probe.bind(("127.0.0.1", 0))
        free = probe.getsockname()[1]
    assert listen_problem("localhost", free) is None
    assert listen_problem("localhost", free, workers=2) is None and asked[-1] == socket.AF_INET
    with real_socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        for workers in (1, 2):
            assert listen_problem("localhost", port, workers) == (
                f"cannot listen on localhost:{port}: address already in use; choose another --port")


def test_default_host_is_localhost_and_the_server_answers(dataset):
    assert DEFAULT_HOST == "127.0.0.1" and build_parser().parse_args([]).host == "127.0.0.1"
    process, url = start([sys.executable, "-m", "service", "--dataset", str(dataset), "--log-level", "warning"])
    try:
        health = httpx.get(f"{url}/health", timeout=1)
        assert health.status_code == 200 and health.json()["counts"]["objects"] == 3
        listening = {c.laddr.ip for c in psutil.Process(process.pid).net_connections() if c.status == psutil.CONN_LISTEN}
        assert listening == {"127.0.0.1"}
    finally:
        _, err = stop(process)
    assert process.returncode == 0 and "Traceback" not in err, "Ctrl-C is a stop, not a crash"


def test_server_closes_unfinished_requests_reloads_on_sighup_logs_no_access_lines_and_leaves_no_child(dataset, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    process, url = start(
        [sys.executable, "-m", "service", "--dataset", str(copy), "--request-timeout", "1", "--watch-seconds", "0"]
    )
    try:
        host, port = url.removeprefix("http://").split(":")
        silent, partial = socket.create_connection((host, int(port))), socket.create_connection((host, int(port)))
        partial.sendall(b"GET /health HTTP/1.1\r\nHost: x\r\n")  # headers never finish
        for sock in (silent, partial):
            sock.settimeout(DEADLINE)
            assert sock.recv(1024) == b"", "the server must close the connection"
            sock.close()
        for _ in range(20):
            assert httpx.get(f"{url}/objects").status_code == 200
        rebuilt(copy, "2032-01-01T00:00:00+00:00")
        process.send_signal(signal.SIGHUP)
        wait_for(lambda: httpx.get(f"{url}/health").json()["reloads"] == 1, "SIGHUP to reload")
        assert httpx.get(f"{url}/health").json()["dataset"]["created"].startswith("2032")
        item = {"object_id": "random_001", "pose": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}
        assert httpx.post(f"{url}/batch/plan", json={"items": [item]}).status_code == 200  # forks the batch process
        children = psutil.Process(process.pid).children(recursive=True)
        assert children, "the batch lane runs in a child process"
    finally:
        process.kill()  # a crash, not a shutdown: the batch process must still go
        process.wait()
        _, alive = psutil.wait_procs(children, timeout=DEADLINE)
        for leftover in alive:  # (it would also hold the server's output pipes open)
            leftover.kill()
        out, err = (stream.decode() for stream in process.communicate())
    assert not alive, "the batch process must not outlive its server"
    assert "GET /objects" not in out + err, "no access log line per request by default"


@pytest.mark.slow
def test_two_forked_workers_serve_and_a_dead_one_is_replaced(dataset):
    # python -m service --workers 2 loads the dataset once and forks the workers from it.
    with two_worker_server(dataset, "--request-timeout", "3") as server:
        process, url, workers = server.process, server.url, server.workers
        assert httpx.get(f"{url}/health").json()["counts"]["objects"] == 3
        pids = set()
        for _ in range(40):  # a new connection each time: the kernel spreads them over the workers
            with httpx.Client() as client:
                assert client.get(f"{url}/objects/random_001").status_code == 200
                metrics = client.get(f"{url}/metrics").text
            pids |= {line.split('pid="')[1].split('"')[0] for line in metrics.splitlines() if line.startswith("toppledb_dataset_info{")}
        assert pids <= {str(w.pid) for w in workers} and pids, "each worker reports its own pid"
        workers[0].kill()
        wait_for(lambda: len(c := psutil.Process(process.pid).children()) == 2 and workers[0].pid not in {w.pid for w in c},
                 "a replacement worker")
        assert wait_for(lambda: httpx.get(f"{url}/health").status_code == 200, "an answer after the replacement")
    assert psutil.pid_exists(workers[1].pid) is False or psutil.Process(workers[1].pid).status() == psutil.STATUS_ZOMBIE


def test_batch_lanes_agree_and_the_process_lane_follows_a_swap(dataset):
    from schema.vocabulary import NO_OP
    from service.lane import Lane

    item = None
    answers = {}
    for kind in ("process", "thread"):
        app = create_app(dataset, settings=Settings(watch_seconds=0))
        app.state.lane = Lane(kind)
        store = app.state.live.store
        if item is None:
            obj = next(o for o in store.objects.values() if (o.policy_action["value_iteration"] != NO_OP).any())
            pose = int((obj.policy_action["value_iteration"] != NO_OP).argmax())
            item = {"object_id": obj.object_id, "pose": obj.transforms[pose].tolist()}
        with TestClient(app) as client:
            answers[kind] = client.post("/batch/plan", json={"items": [item]}).json()
            assert answers[kind]["results"][0]["result"] == client.post("/plan", json=item).json()
            # A swapped store (here: one value changed) is what the next batch answers from.
            fresh = Store.load(dataset)
            changed = fresh.objects[item["object_id"]]
            changed.v_s = changed.v_s.copy()
            changed.v_s[:] = 0.125
            app.state.live.store = fresh
            after = client.post("/batch/plan", json={"items": [item]}).json()["results"][0]["result"]
            assert after["v_s"] == 0.125
    assert answers["process"] == answers["thread"]


def test_a_running_server_picks_up_an_added_symmetric_object_and_plans_for_it_at_any_roll(dataset, tmp_path):
    """`toppledb add` on a served dataset: the server swaps the build in without a restart;
    the can's turned copies of one pose are one pose (merged by symmetry), and an observation
    at any roll about its axis matches it, with the push placed on the can as observed."""
    import numpy as np
    import trimesh

    from pipeline.cli import main as toppledb

    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    can = trimesh.creation.cylinder(radius=0.03, height=0.1, sections=16)
    can.export(tmp_path / "can.stl")
    process, url = start([sys.executable, "-m", "service", "--dataset", str(copy), "--watch-seconds", "0.1"])
    try:
        assert httpx.get(f"{url}/objects/can").status_code == 404
        assert toppledb(["add", str(copy), str(tmp_path / "can.stl"), "--id", "can", "--mass", "0.2", "--no-progress"]) == 0
        detail = wait_for(lambda: (r := httpx.get(f"{url}/objects/can")).status_code == 200 and r.json(),
                          "the server to serve the added object")
        assert detail["n_poses"] == 2, "16 sides and 2 ends: one side pose and one end pose"
        side = np.array(httpx.get(f"{url}/objects/can/poses/0").json()["transform"])
        for facets in (0, 3, 7):
            roll = trimesh.transformations.rotation_matrix(facets * 2 * np.pi / 16, [0, 0, 1])  # about the can's axis
            observed = trimesh.transformations.rotation_matrix(0.7, [0, 0, 1]) @ side @ roll
            observed[:2, 3] = [0.3, -0.1]
            body = httpx.post(f"{url}/plan", json={"object_id": "can", "pose": observed.tolist(), "policy": "max_height"}).json()
            assert body["match"]["pose"] == 0 and body["match"]["angle_error"] < 1e-6, body
            assert abs(body["match"]["z_offset"]) < 1e-9
            point = np.linalg.inv(observed) @ [*body["push"]["point"], 1.0]  # back into the can's own frame
            assert abs(can.nearest.signed_distance([point[:3]])[0]) < 1e-5, "the push lies on the observed can"
        health = httpx.get(f"{url}/health").json()
        assert health["reloads"] == 1 and health["counts"]["objects"] == 4
    finally:
        stop(process)


def test_a_response_written_in_two_parts_leaves_in_one_send_and_a_close_sends_what_is_held():
    import asyncio

    from service.server import CoalescingTransport

    class Recording:
        def __init__(self):
            self.sent, self.closed = [], False

        def write(self, data):
            assert not self.closed, "written after close"
            self.sent.append(bytes(data))

        def is_closing(self):
            return self.closed

        def close(self):
            self.closed = True

        def get_extra_info(self, name, default=None):
            return f"extra:{name}"

    async def scenario():
        raw = Recording()
        transport = CoalescingTransport(raw, asyncio.get_running_loop())
        transport.write(b"HTTP/1.1 200 OK\r\ncontent-length: 2\r\n\r\n")
        transport.write(b"{}")
        assert raw.sent == [], "held until the loop's next turn"
        await asyncio.sleep(0)
        assert raw.sent == [b"HTTP/1.1 200 OK\r\ncontent-length: 2\r\n\r\n{}"]
        transport.write(b"last")
        transport.close()  # before the next turn: the held bytes go first
        await asyncio.sleep(0)
        assert raw.sent[1:] == [b"last"] and raw.closed
        assert transport.get_extra_info("socket") == "extra:socket"

    asyncio.run(scenario())


@pytest.mark.slow
def test_a_stop_during_a_workers_restart_pause_starts_no_new_worker(dataset):
    # A worker dies; while the server waits RESTART_PAUSE before replacing it, a SIGTERM arrives:
    # the server must stop (not fork a worker that nobody will signal, and wait for it forever).
    with two_worker_server(dataset) as server:
        process, workers = server.process, server.workers
        workers[0].kill()
        wait_for(lambda: workers[0].pid not in {c.pid for c in psutil.Process(process.pid).children()}, "the dead worker reaped")
        process.send_signal(signal.SIGTERM)  # within the restart pause
        process.wait(timeout=DEADLINE)  # it stops (it used to fork a replacement after the pause and wait for it)


@pytest.mark.slow
def test_a_replacement_worker_serves_the_build_the_others_reloaded(dataset, tmp_path):
    # The workers reload a rebuilt dataset on SIGHUP; the server process itself keeps the build it
    # loaded at start.  A worker forked later to replace a dead one must not serve that old build.
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)

    def serving(url: str) -> dict[str, str]:
        """pid -> created of the worker that answers a new connection."""
        with httpx.Client() as client:
            lines = client.get(f"{url}/metrics").text.splitlines()
        info = next(line for line in lines if line.startswith("toppledb_dataset_info{"))
        return {info.split('pid="')[1].split('"')[0]: info.split('created="')[1].split('"')[0]}

    with two_worker_server(copy) as server:
        process, url, workers = server.process, server.url, server.workers
        rebuilt(copy, "2033-01-01T00:00:00+00:00")
        process.send_signal(signal.SIGHUP)
        seen: dict[str, str] = {}
        wait_for(lambda: seen.update(serving(url)) or (len(seen) == 2 and all(c.startswith("2033") for c in seen.values())),
                 "both workers to reload")
        workers[0].kill()
        old = {w.pid for w in workers}
        replacement = wait_for(lambda: [w for w in psutil.Process(process.pid).children() if w.pid not in old],
                               "a replacement worker")[0]
        seen.clear()
        created = wait_for(lambda: seen.update(serving(url)) or seen.get(str(replacement.pid)), "an answer from the replacement")
        assert created.startswith("2033"), f"the replacement serves the build of {created}"


@pytest.mark.slow
def test_a_sighup_while_a_worker_starts_does_not_kill_it(dataset):
    # SIGHUP means "reload" to a worker once it serves; one that arrives while a replacement
    # worker is still starting up must not terminate it (SIGHUP's default action).
    with two_worker_server(dataset) as server:
        server.workers[0].kill()
        deadline = time.monotonic() + 3.0  # the restart pause, then the replacement's start-up
        while time.monotonic() < deadline:
            server.process.send_signal(signal.SIGHUP)
            time.sleep(0.005)
        time.sleep(0.5)
    assert server.err.count("starting another") == 1, server.err[-2000:]


def _raw_exchange(url: str, request: bytes, idle: int = 0) -> bytes:
    """Send ``request`` on a fresh TCP connection (after opening ``idle`` connections that send
    nothing) and return everything the server answers before it closes."""
    import socket

    host, port = url.removeprefix("http://").split(":")
    held = [socket.create_connection((host, int(port)), timeout=5) for _ in range(idle)]
    time.sleep(0.2)  # let the server accept them before the request that counts
    try:
        with socket.create_connection((host, int(port)), timeout=5) as conn:
            conn.sendall(request)
            chunks = []
            while chunk := conn.recv(65536):
                chunks.append(chunk)
            return b"".join(chunks)
    finally:
        for conn in held:
            conn.close()


def test_uvicorn_s_own_refusals_are_json_too(dataset):
    """Bytes that are no HTTP request get a 400, and a request over the connection limit a 503
    (with Retry-After), each with a JSON detail as every other error (docs/SERVICE.md)."""
    process, url = start([sys.executable, "-m", "service", "--dataset", str(dataset), "--log-level", "warning",
                          "--limit-concurrency", "2"])
    try:
        garbage = _raw_exchange(url, b"NOT AN HTTP REQUEST\r\n\r\n")
        head, _, body = garbage.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 400") and b"content-type: application/json" in head.lower()
        assert "detail" in json.loads(body)
        busy = _raw_exchange(url, b"GET /health HTTP/1.1\r\nhost: x\r\n\r\n", idle=2)
        head, _, body = busy.partition(b"\r\n\r\n")
        assert head.startswith(b"HTTP/1.1 503") and b"retry-after: 1" in head.lower()
        assert "connection limit" in json.loads(body)["detail"]
    finally:
        stop(process)
