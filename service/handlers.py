"""FastAPI's exception handlers: every error becomes the JSON body ``service.errors`` defines."""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.exceptions import HTTPException as StarletteHTTPException

from .errors import ServiceError, tracebacks, undecodable_body, validation_body

log = logging.getLogger("service")


async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
    return JSONResponse(exc.body(), status_code=exc.status_code)


async def _validation_error(request: Request, exc: RequestValidationError) -> JSONResponse:
    return JSONResponse(validation_body(list(exc.errors())), status_code=422)


FASTAPI_PARSE_ERROR = "There was an error parsing the body"
"""FastAPI's 400 for a JSON body it cannot decode (not UTF-8, nested past Python's recursion limit, or an
integer past its digits limit); served as the 422 every other malformed JSON gets, saying which."""


async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
    if exc.status_code == 400 and exc.detail == FASTAPI_PARSE_ERROR:
        return JSONResponse(validation_body([{"loc": ("body",), "msg": undecodable_body(exc.__cause__), "type": "json_invalid"}]),
                            status_code=422)
    return JSONResponse({"detail": str(exc.detail)}, status_code=exc.status_code, headers=getattr(exc, "headers", None))


async def _unexpected_error(request: Request, exc: Exception) -> JSONResponse:
    allowed, suppressed = tracebacks.allow()
    if allowed:
        more = f" ({suppressed} more since the last one logged)" if suppressed else ""
        log.error("unhandled error on %s %s%s", request.method, request.url.path, more, exc_info=exc)
    return JSONResponse({"detail": "internal error (logged by the service)"}, status_code=500)


def install(app: FastAPI) -> None:
    """Register the JSON error handlers on ``app``."""
    app.add_exception_handler(ServiceError, _service_error)
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.add_exception_handler(Exception, _unexpected_error)
