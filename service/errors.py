"""Errors of the service and how they become JSON responses.

Every error body is ``{"detail": "<one message>"}`` (``schema.api.ErrorBody``), so a
client needs one code path: 404 unknown ids, 409 an observed pose that is no stable
pose, 422 malformed input (with ``errors``, one entry per problem), 500 a bug.
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

log = logging.getLogger("service")


class ServiceError(Exception):
    """A request the dataset cannot answer; ``extra`` fields join ``detail`` in the body."""

    status_code = 400

    def __init__(self, detail: str, **extra):
        super().__init__(detail)
        self.detail = detail
        self.extra = extra

    def body(self) -> dict:
        return {"detail": self.detail, **self.extra}


class NotFound(ServiceError):
    """Unknown object, pose or action id."""

    status_code = 404


class NoStablePose(ServiceError):
    """An observed orientation within tolerance of no stable pose of the object."""

    status_code = 409


def _location(loc) -> str:
    return ".".join(str(part) for part in loc)


async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
    return JSONResponse(exc.body(), status_code=exc.status_code)


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    # FastAPI's default body is a list under "detail"; ours keeps "detail" a message
    # and drops "input"/"ctx", which may echo huge bodies or hold non-JSON objects.
    errors = [
        {"loc": list(e.get("loc", ())), "msg": str(e.get("msg", "")).removeprefix("Value error, "), "type": str(e.get("type", ""))}
        for e in exc.errors()
    ]
    detail = "; ".join(f"{_location(e['loc'])}: {e['msg']}" for e in errors[:10])
    if len(errors) > 10:
        detail += f"; ... {len(errors) - 10} more"
    return JSONResponse({"detail": detail or "malformed request", "errors": errors}, status_code=422)


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    return JSONResponse({"detail": str(exc.detail)}, status_code=exc.status_code, headers=getattr(exc, "headers", None))


async def _unexpected_error(request: Request, exc: Exception) -> JSONResponse:
    log.exception("unhandled error on %s %s", request.method, request.url.path)
    return JSONResponse({"detail": "internal error (logged by the service)"}, status_code=500)


def install(app: FastAPI) -> None:
    """Register the JSON error handlers on ``app``."""
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected_error)
