"""Running the app under uvicorn with the limits a shared robot network needs.

- ``limit_concurrency`` (default 256): beyond that many open connections or running
  requests, uvicorn answers 503 at once instead of queueing without bound (the process
  keeps file descriptors to spare under the usual 1,024 limit).
- ``timeout_keep_alive`` (default 5 s): idle keep-alive connections are closed.
- one send per response (``CoalescingTransport``): uvicorn's separate writes of the headers and
  the body leave as one TCP segment.
- ``request_timeout`` (default 10 s, ``GuardedHttpToolsProtocol``): a connection must deliver a
  whole request (headers and body) within this time of its first byte, or of being opened;
  uvicorn itself never closes a connection whose headers do not finish (slowloris).
- no access log by default (``--access-log`` turns it on): a line per request costs CPU on
  the control path and fills disks under load; /metrics counts requests instead.
- uvloop and httptools when installed (the ``service`` extra installs both).
"""

from __future__ import annotations

import contextlib
import importlib.util
import logging
import os

import orjson
from uvicorn.protocols.http import httptools_impl
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

DEFAULT_LIMIT_CONCURRENCY = 256
DEFAULT_KEEP_ALIVE = 5
DEFAULT_REQUEST_TIMEOUT = 10.0

log = logging.getLogger("service")


class CoalescingTransport:
    """A transport that sends the writes of one event-loop turn as one.

    uvicorn writes a response's status line and headers, then its body: two sends, two TCP
    segments, two wake-ups of the client, and the loopback TCP work of each, which on a
    2-core machine was most of a /plan request's cost.  Held until the loop's next turn
    (``call_soon``) they leave as one; a close sends what is held first.  Everything else
    is the real transport's.
    """

    def __init__(self, transport, loop):
        self._transport = transport
        self._loop = loop
        self._held: list[bytes] = []

    def write(self, data: bytes) -> None:
        if not self._held:
            self._loop.call_soon(self._flush)
        self._held.append(bytes(data))

    def _flush(self) -> None:
        if self._held:
            data = b"".join(self._held)
            self._held.clear()
            if not self._transport.is_closing():
                self._transport.write(data)

    def writelines(self, chunks) -> None:
        for chunk in chunks:
            self.write(chunk)

    def write_eof(self) -> None:
        self._flush()
        self._transport.write_eof()

    def close(self) -> None:
        self._flush()
        self._transport.close()

    def __getattr__(self, name):
        return getattr(self._transport, name)


class GuardedHttpToolsProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol plus a request timeout: from a connection's opening (or
    the first byte of a request) to the request's last byte at most ``request_timeout`` s;
    else the connection is closed."""

    # A class attribute: uvicorn receives the class, not an instance; ``run`` sets it before
    # forking the workers, which inherit it.
    request_timeout = DEFAULT_REQUEST_TIMEOUT

    def connection_made(self, transport) -> None:
        super().connection_made(CoalescingTransport(transport, self.loop))
        self._request_timer = self.loop.call_later(self.request_timeout, self._request_timed_out)

    def on_message_begin(self) -> None:
        super().on_message_begin()
        if getattr(self, "_request_timer", None) is None:
            self._request_timer = self.loop.call_later(self.request_timeout, self._request_timed_out)

    def on_message_complete(self) -> None:
        self._cancel_request_timer()
        super().on_message_complete()

    def connection_lost(self, exc) -> None:
        self._cancel_request_timer()
        super().connection_lost(exc)

    def send_400_response(self, msg: str) -> None:
        """uvicorn's answer to bytes that are no HTTP request, as JSON like every other error."""
        body = orjson.dumps({"detail": msg})
        self.transport.write(b"".join([
            b"HTTP/1.1 400 Bad Request\r\n", *(name + b": " + value + b"\r\n" for name, value in self.server_state.default_headers),
            b"content-type: application/json\r\ncontent-length: ", str(len(body)).encode(), b"\r\nconnection: close\r\n\r\n", body,
        ]))
        self.transport.close()

    def _cancel_request_timer(self) -> None:
        timer = getattr(self, "_request_timer", None)
        if timer is not None:
            timer.cancel()
            self._request_timer = None

    def _request_timed_out(self) -> None:
        self._request_timer = None
        if not self.transport.is_closing():
            self.transport.close()


BUSY_BODY = orjson.dumps({"detail": "the service is at its connection limit (--limit-concurrency); retry shortly"})


async def json_service_unavailable(scope, receive, send) -> None:
    """uvicorn's 503 beyond ``limit_concurrency``, as JSON like every other error."""
    await send({"type": "http.response.start", "status": 503, "headers": [
        (b"content-type", b"application/json"), (b"content-length", str(len(BUSY_BODY)).encode()),
        (b"connection", b"close"), (b"retry-after", b"1")]})
    await send({"type": "http.response.body", "body": BUSY_BODY, "more_body": False})


def listen_problem(host: str, port: int, workers: int = 1) -> str | None:
    """Why the service could not listen on ``host:port``, as one line for the user, or None.

    Checked before the dataset is loaded, so a port already in use is said at once and in a
    line, not after the load as uvicorn's ``[Errno 98]`` log and exit 3.  The addresses are
    bound as the server will bind them, then released: one worker's asyncio server binds every
    address the host resolves to (``SO_REUSEADDR``, IPv6 only on IPv6) and skips a family the
    machine cannot open a socket of; several workers share the one socket uvicorn binds (IPv6
    only for a host written with ':').  A server that takes the port in between still fails as
    uvicorn says."""
    import errno
    import socket

    where = f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
    wanted = socket.AF_UNSPEC if workers <= 1 else (socket.AF_INET6 if ":" in host else socket.AF_INET)
    try:
        addresses = socket.getaddrinfo(host or None, port, wanted, socket.SOCK_STREAM, 0, socket.AI_PASSIVE)
    except socket.gaierror as err:
        return f"cannot listen on {where}: {str(err.strerror).lower()}; check --host"
    if workers > 1:
        addresses = addresses[:1]
    for family, kind, proto, _, address in dict.fromkeys(addresses):
        try:
            opened = socket.socket(family, kind, proto)
        except OSError:
            continue  # a family this machine cannot open (IPv6 disabled): asyncio skips it too
        try:
            with opened as sock:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if family == socket.AF_INET6 and hasattr(socket, "IPPROTO_IPV6"):
                    sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                sock.bind(address)
        except OSError as err:
            reason = (err.strerror or str(err)).lower()
            todo = {errno.EADDRINUSE: "choose another --port", errno.EACCES: "choose a --port above 1023",
                    errno.EADDRNOTAVAIL: "choose another --host (an address of this machine)"}.get(err.errno, "check --host and --port")
            return f"cannot listen on {where}: {reason}; {todo}"
    return None


def run(
    app,
    host: str,
    port: int,
    workers: int = 1,
    log_level: str = "info",
    access_log: bool = False,
    limit_concurrency: int = DEFAULT_LIMIT_CONCURRENCY,
    timeout_keep_alive: int = DEFAULT_KEEP_ALIVE,
    request_timeout: float = DEFAULT_REQUEST_TIMEOUT,
) -> None:
    """Serve ``app`` (an ASGI app whose dataset is already mapped: ``service.staged.StagedApp``
    for ``python -m service``, or ``service.app.create_app``'s) until interrupted, in
    ``workers`` processes forked from this one (``serve_forked``)."""
    import uvicorn

    from .lane import tune_interpreter

    tune_interpreter()
    GuardedHttpToolsProtocol.request_timeout = request_timeout
    # uvicorn's protocol answers its concurrency limit with the module's text/plain app; the
    # service's errors are JSON (docs/SERVICE.md), so the module is given this one.
    httptools_impl.service_unavailable = json_service_unavailable
    has_httptools = importlib.util.find_spec("httptools") is not None
    if not has_httptools:
        log.warning("httptools is not installed: h11 parser, no request timeout for incomplete requests")
    config = uvicorn.Config(
        app, host=host, port=port, log_level=log_level, access_log=access_log, limit_concurrency=limit_concurrency,
        timeout_keep_alive=timeout_keep_alive, loop="uvloop" if importlib.util.find_spec("uvloop") else "asyncio",
        http=GuardedHttpToolsProtocol if has_httptools else "h11", h11_max_incomplete_event_size=16 * 1024,
        server_header=False,
    )
    if workers == 1:
        uvicorn.Server(config).run()
    else:
        serve_forked(config, workers)


RESTART_PAUSE = 1.0
"""s between restarts of a worker that died: a worker that dies at once must not spin."""


def serve_forked(config, workers: int) -> None:
    """Pre-fork: bind the socket here, then fork ``workers`` processes that each serve the
    already loaded app on it.

    The dataset is mapped and the code imported once, before the fork, so every worker starts
    at once (uvicorn's own ``--workers`` spawns fresh interpreters that import and load again:
    seconds each) and shares those pages.  The kernel spreads connections over the workers
    accepting on the one socket.  SIGINT and SIGTERM stop the workers, SIGHUP reaches each
    (each reloads its dataset); a worker that dies otherwise is replaced (starting from this
    process's load, it swaps in a rebuild the others have at once: ``Runtime.serving``, both apps' lifespan).
    """
    import signal
    import time

    import uvicorn

    sock = config.bind_socket()
    children: set[int] = set()
    stopping = False

    def fork_worker() -> None:
        pid = os.fork()
        if pid == 0:  # the worker
            for signum in (signal.SIGINT, signal.SIGTERM):
                signal.signal(signum, signal.SIG_DFL)  # uvicorn installs its own when it starts serving
            # Until the app's lifespan installs its reload handler (a rebuild in between is swapped in
            # there too), a SIGHUP must not end the worker as its default action would.
            signal.signal(signal.SIGHUP, signal.SIG_IGN)
            code = 1
            try:
                uvicorn.Server(config).run(sockets=[sock])
                code = 0
            finally:
                os._exit(code)
        children.add(pid)

    def forward(signum, frame) -> None:
        nonlocal stopping
        stopping = stopping or signum in (signal.SIGINT, signal.SIGTERM)
        # A terminal's Ctrl-C reaches the workers too; a second SIGINT would make uvicorn skip its
        # graceful shutdown, a SIGTERM does not.
        forwarded = signal.SIGTERM if signum == signal.SIGINT else signum
        for pid in list(children):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, forwarded)

    for _ in range(workers):
        fork_worker()
    for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(signum, forward)
    log.info("serving on %s:%d with %d forked workers %s", config.host, config.port, workers, sorted(children))
    while children:
        try:
            pid, status = os.wait()
        except ChildProcessError:
            break
        if pid not in children:
            continue  # not a worker (a batch lane child is its worker's)
        children.discard(pid)
        if not stopping:
            log.warning("worker %d exited (status %d); starting another", pid, status)
            time.sleep(RESTART_PAUSE)
            if not stopping:  # a SIGINT or SIGTERM during the pause: no worker left to signal it later
                fork_worker()
    sock.close()
