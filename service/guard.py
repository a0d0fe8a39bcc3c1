"""The ASGI layer in front of the routes: metrics, bearer token, body limits, content type.

Pure ASGI (no BaseHTTPMiddleware): it costs a few microseconds a request and answers
401/413/415 before FastAPI reads or parses anything, so an oversized or non-JSON body
never reaches the JSON parser on the event loop.  Order, outermost first:

1. metrics: every response counted and timed per route (``service.metrics``), and stamped with
   ``BUILD_HEADER`` when a build answered it (``answered_from``);
2. token: ``Authorization: Bearer <token>`` on every path except /health, when set (401);
3. body: a POST to a route that takes one (``POST_PATHS``) must say ``content-type:
   application/json`` (415); any body must be at most ``max_body_bytes`` for /batch/* and
   ``SINGLE_BODY_BYTES`` for the others (413, from content-length before reading, or while
   reading a chunked body); a POST route's body is read here once and handed on.
"""

from __future__ import annotations

import hmac
import time
from typing import TYPE_CHECKING

import orjson

from .errors import OtherBuild, validation_body
from .metrics import Metrics

if TYPE_CHECKING:  # the store imports numpy and pyarrow, which the guard need not load
    from .store import Store

OPEN_PATHS = frozenset({"/health"})
"""Paths answered without the bearer token (liveness probes carry no secrets)."""
HEAD_PATHS = frozenset({"/health"})
"""Paths a HEAD request is answered on, as its GET with the body left out: uptime monitors and load
balancers probe liveness with HEAD (RFC 9110 9.3.2), and the routes are GET only."""

BODY_METHODS = frozenset({"POST", "PUT", "PATCH"})
"""Methods that carry a body: a declared length over the limit is 413 whatever the method."""
READ_METHODS = frozenset({"POST"})
"""Methods whose body the guard checks and reads: the API's only one.  A PUT or PATCH within the
limit goes on unread to the router, which answers 405 (not a 415 about a body no route takes)."""

POST_PATHS = frozenset({"/plan", "/batch/plan", "/batch/transitions", "/heaps/plan"})
"""The routes that take a body (the API's POST routes). A POST elsewhere goes on unread to the router,
which answers 404 (no such path) or 405 (a GET route), not a 415 about a body no route takes."""

SINGLE_BODY_BYTES = 64 * 1024
"""Largest body of a request that is not a batch (a /plan body is under 2 kB): such bodies are
parsed on the event loop, so they stay small; only /batch/* bodies may reach max_body_bytes."""
BATCH_PREFIX = "/batch/"


def error_messages(status: int, detail: str, headers: list[tuple[bytes, bytes]] = ()) -> tuple[dict, dict]:
    """The two ASGI messages (start, body) of a JSON error ``{"detail": detail}`` with ``status``."""
    return json_messages(status, {"detail": detail}, headers)


def json_messages(status: int, content: dict, headers: list[tuple[bytes, bytes]] = ()) -> tuple[dict, dict]:
    """The two ASGI messages (start, body) of the JSON body ``content`` with ``status``."""
    body = orjson.dumps(content)
    start = {
        "type": "http.response.start",
        "status": status,
        "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()), *headers],
    }
    return start, {"type": "http.response.body", "body": body}


def replay(message: dict, receive):
    """A ``receive`` that first hands back ``message`` (a body already read), then defers to
    ``receive`` (disconnects)."""
    delivered = False

    async def replayed():
        nonlocal delivered
        if not delivered:
            delivered = True
            return message
        return await receive()

    return replayed


def is_json(content_type: bytes) -> bool:
    """application/json or application/<x>+json, parameters (charset) allowed."""
    media = content_type.split(b";", 1)[0].strip().lower()
    return media == b"application/json" or (media.startswith(b"application/") and media.endswith(b"+json"))


def route_path(scope) -> str:
    """The request's path as the routes name it: behind a proxy that mounts the API under a prefix
    (uvicorn's ``--root-path``), the ASGI ``path`` starts with ``root_path``, which the router strips."""
    path, root = scope["path"], scope.get("root_path", "")
    return (path[len(root):] or "/") if root and path.startswith(root) else path


def not_utf8(body: bytes) -> bool:
    """A JSON text in UTF-16 or UTF-32, which Python's JSON decoder would read by its byte pattern
    (RFC 7159 allowed them) though JSON on the wire is UTF-8 (RFC 8259): a byte-order mark, or a NUL in
    the first four bytes, which UTF-8 JSON never has (its first character is ASCII)."""
    return body[:2] in (b"\xff\xfe", b"\xfe\xff") or b"\x00" in body[:4]


CLIENT_CLOSED = 499
"""The status /metrics counts for a request that ended without a response because the client
went away (nginx's "client closed request"); nothing is sent."""


BUILD_SCOPE_KEY = "toppledb.build"
"""ASGI scope key of the manifest SHA-256 of the build a request is answered from (set by ``answered_from``);
the guard sends it back as ``BUILD_HEADER``."""
BUILD_HEADER = b"x-toppledb-build"
"""Response header naming the build an answer came from, so that a controller sees a dataset swap in the
answer itself: action indices, ``failed_actions`` among them, name one build's candidates.  On a request,
the build the request's action indices were recorded under: another build refuses it (412, ``OtherBuild``)."""


def requested_build(scope: dict) -> str | None:
    """The build a request names in ``BUILD_HEADER`` (the first such header, as FastAPI reads it), or None."""
    return next((value.decode("latin-1") for name, value in scope["headers"] if name == BUILD_HEADER), None)


def answered_from(scope: dict, store: Store, requested: str | None) -> Store:
    """``store``, noted in the request's ``scope`` as the build it is answered from.

    requested : the build the request names (``requested_build``), or None
    Raises ``OtherBuild`` when the request names another build; the refusal names ``store`` too.
    """
    scope[BUILD_SCOPE_KEY] = store.manifest_sha256
    if requested is not None and requested != store.manifest_sha256:
        raise OtherBuild(requested, store.manifest_sha256)
    return store


class Guard:
    """ASGI middleware: see the module docstring."""

    def __init__(self, app, metrics: Metrics, token: str | None, max_body_bytes: int):
        self.app = app
        self.metrics = metrics
        self.token = None if token is None else token.encode()
        self.max_body_bytes = max_body_bytes

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        started = time.perf_counter()
        status = None  # the response's, once one starts
        method = scope["method"]
        if method == "HEAD" and route_path(scope) in HEAD_PATHS:
            # Answered as the GET, headers and all (content-length included); the server, which knows the request
            # was a HEAD, sends no body.
            scope = {**scope, "method": "GET"}

        async def send_counted(message):
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
                build = scope.get(BUILD_SCOPE_KEY)
                if build is not None:  # the build the answer came from (dependencies.BUILD_HEADER)
                    message = {**message, "headers": [*message.get("headers", ()), (BUILD_HEADER, build.encode())]}
            await send(message)

        try:
            await self._guarded(scope, receive, send_counted)
            if status is None:
                # Returned without a response: the client left (or the request timeout closed the
                # connection) before its body arrived.  Not a server error; 499 as nginx logs it.
                status = CLIENT_CLOSED
        finally:
            route = scope.get("route")
            # No status after an exception: the server sends 500.
            self.metrics.observe(method, getattr(route, "path", None), 500 if status is None else status,
                                 time.perf_counter() - started)

    async def _guarded(self, scope, receive, send):
        headers = dict(scope["headers"])
        path = route_path(scope)
        if self.token is not None and path not in OPEN_PATHS:
            given = headers.get(b"authorization", b"")
            scheme, _, credentials = given.partition(b" ")
            # The scheme's name is case-insensitive (RFC 7235); the token is compared in constant time.
            if not (scheme.lower() == b"bearer" and hmac.compare_digest(credentials.strip(), self.token)):
                why = "missing bearer token" if not given else "wrong bearer token"
                await self._reply(send, 401, f"{why}: send 'Authorization: Bearer <token>'", [(b"www-authenticate", b"Bearer")])
                return
        if scope["method"] not in BODY_METHODS:
            await self.app(scope, receive, send)
            return
        limit = self.max_body_bytes if path.startswith(BATCH_PREFIX) else min(self.max_body_bytes, SINGLE_BODY_BYTES)
        length = headers.get(b"content-length")
        if length is not None and (not length.isdigit() or int(length) > limit):
            # connection: close, so the server does not go on reading (and discarding) the rest.
            await self._reply(send, 413, f"request body of {length.decode('latin-1')[:20]} bytes; at most {limit}",
                              [(b"connection", b"close")])
            return
        if scope["method"] not in READ_METHODS or path not in POST_PATHS:
            await self.app(scope, receive, send)
            return
        # Every Content-Type header, not the last one only: the framework reads the first, so two that
        # disagree would have the guard pass a body the route then reads as another type.
        types = [value for name, value in scope["headers"] if name == b"content-type"]
        if len(types) != 1 or not is_json(types[0]):
            given = b", ".join(types).decode("latin-1")[:60] or "none"
            await self._reply(send, 415, f"content-type {given!r}: send the body as application/json")
            return
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > limit:
                await self._reply(send, 413, f"request body over {limit} bytes", [(b"connection", b"close")])
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        if not_utf8(body):
            for message in json_messages(422, validation_body([{"loc": ("body",), "type": "json_invalid",
                                                                "msg": "JSON decode error: the body is UTF-16 or UTF-32; send UTF-8"}])):
                await send(message)
            return
        whole = {"type": "http.request", "body": body, "more_body": False}
        await self.app(scope, replay(whole, receive), send)

    @staticmethod
    async def _reply(send, status: int, detail: str, headers=()) -> None:
        start, body = error_messages(status, detail, list(headers))
        await send(start)
        await send(body)
