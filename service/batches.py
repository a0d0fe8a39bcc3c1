"""Batch bodies, handled whole in the batch lane (``service.lane``): parse, validate,
answer each item, serialise.  Returns JSON bytes, or raises ``BatchInvalid`` with the
same error dicts FastAPI would give, so a malformed batch is the same 422 as elsewhere.
"""

from __future__ import annotations

import json
from collections.abc import Callable

from fastapi.exceptions import RequestValidationError
from pydantic import BaseModel, ValidationError

from .errors import NOT_GIVEN, ServiceError, undecodable_body


class BatchInvalid(Exception):
    """A malformed batch: ``errors`` as FastAPI's validation errors (type, loc, msg, and input only
    when it is null: plain values, so that it crosses a process boundary)."""

    def __init__(self, errors: list[dict]):
        super().__init__(errors)
        self.errors = errors


def _located(error: dict) -> dict:
    """A pydantic error of a batch body as FastAPI's would be: located under ``body``, its input dropped
    unread but for a null, which ``errors.validation_body`` says it was."""
    located = {"type": error["type"], "loc": ("body", *error["loc"]), "msg": error["msg"]}
    if error.get("input", NOT_GIVEN) is None:
        located["input"] = None
    return located


def answer(body: bytes, request_model: type[BaseModel], item: Callable, results_model: type[BaseModel], result_model) -> bytes:
    """``results_model(results=[...])`` as JSON bytes, one result per item of the body.

    item(request_item) -> the result, or raises ServiceError (becomes that item's error).
    """
    if not body:  # as FastAPI says it; whitespace alone is JSON that ends too soon, for FastAPI too
        raise BatchInvalid([{"type": "missing", "loc": ("body",), "msg": "Field required"}])
    try:
        # The standard library parser, as FastAPI uses: it reads NaN and Infinity, which
        # validation then refuses with a message naming the field (orjson would not say where).
        data = json.loads(body)
    except json.JSONDecodeError as err:
        raise BatchInvalid([{"type": "json_invalid", "loc": ("body", err.pos), "msg": "JSON decode error",
                            "ctx": {"error": err.msg}}]) from None
    except (ValueError, RecursionError) as err:  # no position: not UTF-8, nested a thousand deep, a huge integer
        raise BatchInvalid([{"type": "json_invalid", "loc": ("body",), "msg": undecodable_body(err)}]) from None
    try:
        parsed = request_model.model_validate(data)
    except ValidationError as err:
        raise BatchInvalid([_located(e) for e in err.errors(include_url=False)]) from None
    results, reasonless = [], {}
    for i, request in enumerate(parsed.items):
        try:
            results.append(result_model(result=item(request)))
        except ServiceError as err:
            results.append(result_model(error={"status": err.status_code, "detail": err.detail, "reason": err.reason}))
            if err.reason is None:
                reasonless[i] = {"error": {"reason"}}
    # ``reason`` is left out of an error that has none, as /health leaves out ``reload_error``: answers of the
    # service before it had the key are read by clients whose models forbid keys they do not know.
    return results_model(results=results).model_dump_json(exclude={"results": reasonless} if reasonless else None).encode()


def answer_kind(kind: str, body: bytes, store, settings) -> bytes:
    """The answer to a ``plan`` or ``transitions`` batch body (what the lane runs)."""
    from functools import partial

    from schema.api import PlanBatch, PlanResult, PlanResults, TransitionBatch, TransitionResult, TransitionResults

    from .planning import plan
    from .routers.objects import action_detail

    if kind == "plan":
        return answer(body, PlanBatch, partial(plan, store, settings=settings), PlanResults, PlanResult)

    def transition(item):
        return action_detail(store.object(item.object_id), item.pose, item.action)

    return answer(body, TransitionBatch, transition, TransitionResults, TransitionResult)


async def run(lane, kind: str, body: bytes, store, settings) -> bytes:
    """``answer_kind`` in the lane; a malformed batch raises RequestValidationError (422)."""
    try:
        return await lane.run(kind, body, store, settings)
    except BatchInvalid as err:
        raise RequestValidationError(err.errors) from None


def request_body(model: type[BaseModel]) -> dict:
    """openapi_extra documenting a body FastAPI does not parse itself."""
    return {"requestBody": {"required": True, "content": {"application/json": {"schema": {"$ref": f"#/components/schemas/{model.__name__}"}}}}}
