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

import importlib.util
import logging
import os

from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from .settings import ENV_PREFIX, Settings

DEFAULT_LIMIT_CONCURRENCY = 256
DEFAULT_KEEP_ALIVE = 5
DEFAULT_REQUEST_TIMEOUT = 10.0
REQUEST_TIMEOUT_ENV = "TOPPLEDB_REQUEST_TIMEOUT"
WORKER_STARTUP_TIMEOUT = 300
"""s a uvicorn worker may take to load the dataset and answer its first health check."""

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

    # A class attribute read from the environment: uvicorn's workers are spawned processes
    # that import this module afresh and receive the class by reference.
    request_timeout = float(os.environ.get(REQUEST_TIMEOUT_ENV, DEFAULT_REQUEST_TIMEOUT))

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

    def _cancel_request_timer(self) -> None:
        timer = getattr(self, "_request_timer", None)
        if timer is not None:
            timer.cancel()
            self._request_timer = None

    def _request_timed_out(self) -> None:
        self._request_timer = None
        if not self.transport.is_closing():
            self.transport.close()


def export_settings(settings: Settings) -> None:
    """Put the settings into ``TOPPLEDB_*`` variables, so that workers started by uvicorn
    (``service.app:create_app`` as a factory) read the same ones."""
    for name, value in settings.__dict__.items():
        if value is not None:
            os.environ[ENV_PREFIX + name.upper()] = str(value)


def run(
    settings: Settings,
    host: str,
    port: int,
    workers: int = 1,
    log_level: str = "info",
    access_log: bool = False,
    limit_concurrency: int = DEFAULT_LIMIT_CONCURRENCY,
    timeout_keep_alive: int = DEFAULT_KEEP_ALIVE,
    request_timeout: float = DEFAULT_REQUEST_TIMEOUT,
    app=None,
) -> None:
    """Serve until interrupted.  ``app`` (already loaded) is used with one worker; several
    workers each load the dataset through the factory."""
    import uvicorn

    from .lane import tune_interpreter

    tune_interpreter()
    os.environ[REQUEST_TIMEOUT_ENV] = str(request_timeout)  # for spawned workers
    GuardedHttpToolsProtocol.request_timeout = request_timeout
    has_httptools = importlib.util.find_spec("httptools") is not None
    options = {
        "host": host, "port": port, "log_level": log_level, "access_log": access_log, "limit_concurrency": limit_concurrency,
        "timeout_keep_alive": timeout_keep_alive, "loop": "uvloop" if importlib.util.find_spec("uvloop") else "asyncio",
        "http": GuardedHttpToolsProtocol if has_httptools else "h11",
        "h11_max_incomplete_event_size": 16 * 1024, "server_header": False,
    }
    if not has_httptools:
        log.warning("httptools is not installed: h11 parser, no request timeout for incomplete requests")
    if workers > 1:
        export_settings(settings)
        # A worker answers uvicorn's health check only once it has loaded the dataset (seconds for
        # the full one on a busy machine); uvicorn's 5 s default would kill and restart it forever.
        uvicorn.run("service.app:create_app", factory=True, workers=workers, timeout_worker_healthcheck=WORKER_STARTUP_TIMEOUT,
                    **options)
    else:
        uvicorn.run(app, **options)
