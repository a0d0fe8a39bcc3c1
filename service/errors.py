"""Errors of the service and how they become JSON responses.

Every error body is ``{"detail": "<one message>"}`` (``schema.api.ErrorBody``), so a
client needs one code path: 401 a missing or wrong bearer token, 404 unknown ids, 409 an
observed pose that is no stable pose or not on the table (``reason`` says which), 412 a request
naming a build other than the one that serves it (``OtherBuild``), 413 a body over the limit, 415 a
body that is not JSON, 422 malformed input (with ``errors``, one entry per problem), 500 a bug (its
traceback logged, at most ``TRACEBACKS_PER_MINUTE`` a minute).

Framework-free, so the planning code and the early control path (``service.staged``) import
it without FastAPI; ``service.handlers`` turns these errors into FastAPI's responses.
"""

from __future__ import annotations

import sys
import threading
import time


class ServiceError(Exception):
    """A request the dataset cannot answer; ``extra`` fields join ``detail`` in the body."""

    status_code = 400
    reason: str | None = None
    """Machine-readable cause, in the body as ``reason`` when set (409 has two causes)."""

    def __init__(self, detail: str, **extra):
        super().__init__(detail)
        self.detail = detail
        self.extra = extra

    def body(self) -> dict:
        reason = {} if self.reason is None else {"reason": self.reason}
        return {"detail": self.detail, **reason, **self.extra}


class NotFound(ServiceError):
    """Unknown object, pose or action id."""

    status_code = 404


class NoStablePose(ServiceError):
    """An observed orientation within tolerance of no stable pose of the object."""

    status_code = 409
    reason = "no_stable_pose"


class OffTable(ServiceError):
    """An observed pose whose support point is too far above or below the table z = 0."""

    status_code = 409
    reason = "off_table"


class OtherBuild(ServiceError):
    """A request that names, in ``x-toppledb-build``, a build other than the one that would answer it.

    Action indices (a /plan's ``failed_actions``, a transition's ``action``) name one build's candidates,
    so a controller that recorded them under one build sends its name, and after a rebuild is refused
    (HTTP's "precondition failed") rather than answered about other pushes under the same numbers."""

    status_code = 412

    def __init__(self, requested: str, served: str):
        # A header may be kilobytes of anything: the body echoes a bounded, printable part of it.
        shown = requested.encode("ascii", "backslashreplace").decode()[:80]
        super().__init__(f"this request names build '{shown}' in x-toppledb-build, but build {served} answers it: "
                         "action indices name one build's candidates; clear them and ask again", build=served,
                         requested=shown)


class UnknownFrame(ServiceError):
    """A ROS pose given in a frame other than the service's table frame: malformed input."""

    status_code = 422

    def body(self) -> dict:
        return {"detail": f"body.ros_pose.frame_id: {self.detail}",
                "errors": [{"loc": ["body", "ros_pose", "frame_id"], "msg": self.detail, "type": "unknown_frame"}]}


class UnknownAction(ServiceError):
    """A failed action the matched pose does not have: malformed input (the pose is known only
    once the observation is matched, so pydantic cannot check it)."""

    status_code = 422

    def __init__(self, detail: str, index: int):
        super().__init__(detail)
        self.index = index

    def body(self) -> dict:
        return {"detail": f"body.failed_actions.{self.index}: {self.detail}",
                "errors": [{"loc": ["body", "failed_actions", self.index], "msg": self.detail, "type": "unknown_action"}]}


TRACEBACKS_PER_MINUTE = 10
"""Most tracebacks logged a minute: a bug hit by every request must not fill the disk."""


class RateLimit:
    """At most ``per_minute`` events a minute (fixed window); counts the rest."""

    def __init__(self, per_minute: int):
        self.per_minute = per_minute
        self.window = 0.0
        self.used = 0
        self.suppressed = 0
        self._lock = threading.Lock()

    def allow(self) -> tuple[bool, int]:
        """(allowed, events suppressed since the last allowed one)."""
        with self._lock:
            now = time.monotonic()
            if now - self.window >= 60.0:
                self.window, self.used = now, 0
            if self.used < self.per_minute:
                self.used += 1
                suppressed, self.suppressed = self.suppressed, 0
                return True, suppressed
            self.suppressed += 1
            return False, 0


tracebacks = RateLimit(TRACEBACKS_PER_MINUTE)


def validation_body(errors: list[dict]) -> dict:
    """The 422 body for pydantic/FastAPI error dicts: a one-line ``detail`` and ``errors``."""
    # FastAPI's default body is a list under "detail"; ours keeps "detail" a message
    # and drops "input"/"ctx", which may echo huge bodies or hold non-JSON objects.
    errors = [
        {"loc": list(e.get("loc", ())), "msg": _message(e), "type": str(e.get("type", ""))}
        for e in errors
    ]
    detail = "; ".join(f"{_location(e['loc'])}: {e['msg']}" for e in errors[:10])
    if len(errors) > 10:
        detail += f"; ... {len(errors) - 10} more"
    return {"detail": detail or "malformed request", "errors": errors}


NOT_GIVEN = object()
"""An error dict's ``input`` when it has none (``None`` is an input: JSON null)."""


def _message(error: dict) -> str:
    """An error's message; a JSON decode error says why and where (the parser's words are in ``ctx``,
    which the body leaves out), so a client can find the broken character, and a null says it was one
    (``input`` is left out too)."""
    message = str(error.get("msg", "")).removeprefix("Value error, ")
    if error.get("type") == "json_invalid" and message == "JSON decode error":
        reason = (error.get("ctx") or {}).get("error")
        loc = tuple(error.get("loc", ()))
        if isinstance(reason, str) and reason:
            message += f": {reason}"
        if len(loc) > 1 and isinstance(loc[1], int):
            message += f" at character {loc[1]}"
    elif error.get("input", NOT_GIVEN) is None and error.get("type") != "missing":
        # Serialisers that write an unset optional as null (a dict's None, std::optional) meet this first;
        # the same words fit a required field, an array's entry and a whole body.
        message += ", got null (null is never read as absent: send a value, or leave an optional field out)"
    return message


def undecodable_body(cause: BaseException | None) -> str:
    """The 422's message for a JSON body the parser gave up on without a position (no
    ``JSONDecodeError``): bytes that are not UTF-8, thousands of nested brackets, or an integer
    longer than Python converts (``sys.get_int_max_str_digits``, 4,300 digits by default)."""
    if isinstance(cause, UnicodeDecodeError):
        return "JSON decode error: not UTF-8 text"
    if isinstance(cause, RecursionError):
        return "JSON decode error: nested too deeply"
    if isinstance(cause, ValueError) and "integer string conversion" in str(cause):
        return f"JSON decode error: a number of more than {sys.get_int_max_str_digits()} digits"
    return "JSON decode error (not UTF-8 text, or nested too deeply)"


def _location(loc) -> str:
    return ".".join(str(part) for part in loc)
