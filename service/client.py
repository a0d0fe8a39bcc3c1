"""A typed Python client of the service, for robot code: timeouts, retries, typed answers.

    from service.client import Client

    with Client("http://127.0.0.1:8000", token=None, timeout=0.5) as toppledb:
        answer = toppledb.plan("bunny", pose=observed_4x4)              # or ros_pose={...}
        if answer.decision == "push" and answer.push.within_force_limit:
            execute(answer.push.start, answer.push.end)
        elif answer.decision == "grasp":
            grasp(answer.grasp.point, answer.grasp.axis)

Every answer is the ``schema.api`` model of the route (``PlanResponse``, ``Health``, ...).
Errors are exceptions carrying the service's ``detail``: ``NotFound`` (404),
``NoStablePose`` and ``OffTable`` (409, by ``reason``), ``OtherBuild`` (412: failed actions
recorded under a build the service no longer serves), ``InvalidRequest`` (422, also a
pose with NaN or infinite entries, refused before sending), ``Unreachable`` (no answer
after every retry), and ``ServiceError`` (their base) for anything else.  Every request is read-only, hence safe to repeat:
connection errors, timeouts and 503s are retried ``retries`` times with exponential
backoff; a 4xx never is.  Needs httpx: ``pip install "toppledb[client]"`` brings it and
nothing of the server, which the client does not import."""

from __future__ import annotations

import operator
import re
import time
from typing import Any, Self, TypeVar
from urllib.parse import quote

import httpx
import numpy as np
from pydantic import BaseModel, ValidationError

from schema.api import (
    ActionDetail,
    Health,
    ObjectDetail,
    ObjectList,
    PlanResponse,
    PlanResults,
    PoseDetail,
    QValues,
    RosPose,
    TransitionResults,
)
from schema.layout import OBJECT_ID_PATTERN

from .errors import validation_body

DEFAULT_TIMEOUT = 1.0
"""s, per attempt (connect, read, write each); a controller at 50 Hz wants well under its period."""
DEFAULT_RETRIES = 2
DEFAULT_BACKOFF = 0.05
"""s, wait before the first retry; doubles after each."""
RETRY_STATUSES = frozenset({502, 503, 504})

Model = TypeVar("Model", bound=BaseModel)


class ServiceError(RuntimeError):
    """A non-2xx answer: ``status``, the service's ``detail`` and the whole JSON ``body``."""

    def __init__(self, status: int, detail: str, body: dict | None = None):
        super().__init__(f"{status}: {detail}")
        self.status, self.detail, self.body = status, detail, body or {}


class NotFound(ServiceError):
    """404: unknown object, pose or action."""


class NoStablePose(ServiceError):
    """409 no_stable_pose: the observed orientation is no stable pose (``body['nearest_pose']``, ``angle_error``)."""


class OffTable(ServiceError):
    """409 off_table: the object is not on the table (``body['z_offset']``, ``height_tolerance``)."""


class OtherBuild(ServiceError):
    """412: the request's failed actions were recorded under another build than the one now served
    (``body['build']``, also the client's ``build`` now): clear them and ask again."""


class InvalidRequest(ServiceError):
    """422 (or 413, 415): the request is malformed; ``body['errors']`` lists the problems."""


class Unauthorized(ServiceError):
    """401: missing or wrong bearer token."""


class Unreachable(ServiceError):
    """No answer after every retry (refused, reset, timed out): ``status`` 0, the transport's
    error as ``__cause__``."""


def _error(response: httpx.Response) -> ServiceError:
    try:
        body = response.json()
    except ValueError:
        body = {"detail": response.text[:200]}
    detail = str(body.get("detail", "")) if isinstance(body, dict) else str(body)
    fields = body if isinstance(body, dict) else {}  # JSON that is no object (a proxy's list or string): no fields
    status = response.status_code
    kind = {401: Unauthorized, 404: NotFound, 412: OtherBuild, 413: InvalidRequest, 415: InvalidRequest,
            422: InvalidRequest}.get(status, ServiceError)
    if status == 409:
        kind = OffTable if fields.get("reason") == "off_table" else NoStablePose
    return kind(status, detail, fields)


class Client:
    """Synchronous client.  ``timeout`` (s, per attempt) configures the ``httpx.Client`` made
    here; a client passed as ``http`` keeps its own timeouts and headers, the token going with each
    request instead (tests pass FastAPI's TestClient).

    ``build``: the manifest SHA-256 of the dataset build the last answer that named one came from (its
    ``x-toppledb-build`` header; None until one did: a service older than stop 68 names none, and one
    older than stop 72 names its build on ``/health`` in the body only).

    ``plan_build``: the build of the last ``plan`` or ``plan_batch`` answer (a 2xx).
    ``plan_builds``: per object id, the build of the last plan answer that served that object a push,
    whose action indices are that build's. Only those answers set them, not a refusal nor another
    route's answer, so ``plan`` sends an object's ``failed_actions`` with its entry (or the ``build=``
    given), and a rebuild since is ``OtherBuild`` however often the call is repeated, also when other
    objects were planned under the new build in between (docs/SERVICE.md, "Python client")."""

    def __init__(
        self,
        base_url: str = "http://127.0.0.1:8000",
        token: str | None = None,
        timeout: float = DEFAULT_TIMEOUT,
        retries: int = DEFAULT_RETRIES,
        backoff: float = DEFAULT_BACKOFF,
        http: httpx.Client | None = None,
    ):
        # Sent with each request rather than set on ``http``: a client passed in may be shared (its connection
        # pool) with other Clients holding other tokens, or with code of the caller's own.
        self.headers = {"authorization": f"Bearer {token}"} if token else {}
        self.http = http or httpx.Client(base_url=base_url, timeout=timeout)
        self.timeout, self.retries, self.backoff = timeout, retries, backoff
        self.build: str | None = None
        self.plan_build: str | None = None
        self.plan_builds: dict[str, str | None] = {}

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self.http.close()

    # --- routes -------------------------------------------------------------------

    def health(self) -> Health:
        return self._call("GET", "/health", Health)

    def objects(self) -> ObjectList:
        return self._call("GET", "/objects", ObjectList)

    def object(self, object_id: str) -> ObjectDetail:
        return self._call("GET", _object_path(object_id), ObjectDetail)

    def pose(self, object_id: str, pose: int) -> PoseDetail:
        return self._call("GET", f"{_object_path(object_id)}/poses/{_integer(pose, 'pose')}", PoseDetail)

    def action(self, object_id: str, pose: int, action: int, build: str | None = None) -> ActionDetail:
        """One candidate push; ``build``: the build ``action`` was taken from (another one is ``OtherBuild``)."""
        path = f"{_object_path(object_id)}/poses/{_integer(pose, 'pose')}/actions/{_integer(action, 'action')}"
        return self._call("GET", path, ActionDetail, requested=_build_name(build))

    def q_values(self, object_id: str, pose: int, top: int = 10, by: str = "q") -> QValues:
        return self._call("GET", f"{_object_path(object_id)}/poses/{_integer(pose, 'pose')}/q", QValues, params={"top": top, "by": by})

    def plan(
        self,
        object_id: str,
        pose: Any = None,
        ros_pose: RosPose | dict | None = None,
        policy: str = "value_iteration",
        pushes_left: int | None = None,
        failed_actions: list[int] | None = None,
        build: str | None = None,
    ) -> PlanResponse:
        """The decision for one observed object: ``pose`` a 4x4 object -> world matrix (array or
        nested lists) or ``ros_pose`` (position, orientation x, y, z, w, frame_id); with
        ``pushes_left``, value iteration's push for that budget; with ``failed_actions`` (the
        actions of earlier answers that left the object in this pose), a push that has not failed.

        build : the build ``failed_actions`` were recorded under (default ``plan_builds[object_id]``, that of
            the last answer that served this object a push); another build raises ``OtherBuild``. Sent only
            with ``failed_actions``, the only indices a plan takes."""
        item = plan_item(object_id, pose, ros_pose, policy, pushes_left, failed_actions)
        return self._plan("/plan", PlanResponse, item, [item], build)

    def plan_batch(self, items: list[dict], build: str | None = None) -> PlanResults:
        """Up to 1000 items of ``plan_item(...)``; per-item errors are in ``results[i].error``.
        ``build`` as ``plan``'s, for the whole batch when an item has ``failed_actions``; items whose
        objects' failed actions were recorded under different builds cannot all be current, and raise
        ``OtherBuild`` before anything is sent."""
        return self._plan("/batch/plan", PlanResults, {"items": items}, items, build)

    def transitions(self, items: list[tuple[str, int, int]], build: str | None = None) -> TransitionResults:
        """(object_id, pose, action) triples, up to 1000; ``build``: the build the actions were taken from.
        Indices are integers (numpy's too); 2.0, "1" and True raise TypeError, as ``pose`` and ``action`` do."""
        body = {"items": [{"object_id": o, "pose": _integer(p, f"items[{i}] pose"), "action": _integer(a, f"items[{i}] action")}
                          for i, (o, p, a) in enumerate(items)]}
        return self._call("POST", "/batch/transitions", TransitionResults, json=body, requested=_build_name(build))

    # --- transport ----------------------------------------------------------------

    def _recorded_under(self, items: list[dict], build: str | None) -> str | None:
        """The build to name for plan ``items``: with failed actions, ``build``, else the build of the answers
        that last served those items' objects a push (none known, as after a restart: no build named, and any
        build answers)."""
        failed = [item["object_id"] for item in items if item.get("failed_actions")]
        if not failed:
            return None
        if build is not None:
            return _build_name(build)
        recorded = {o: self.plan_builds[o] for o in failed if self.plan_builds.get(o) is not None}
        builds = sorted(set(recorded.values()))
        if len(builds) > 1:
            # One header names the build of every item's indices; of two builds at most one is served.
            raise OtherBuild(412, f"failed actions recorded under {len(builds)} builds in one batch "
                                  f"({', '.join(f'{o}: {b[:12]}' for o, b in recorded.items())}): at most one is "
                                  "served; clear the older ones or plan them in separate calls",
                             {"build": self.build, "requested": ", ".join(builds), "recorded": recorded})
        return builds[0] if builds else None

    def _plan(self, path: str, model: type[Model], body: dict, items: list[dict], build: str | None) -> Model:
        """A plan or a batch of ``items``, naming the build their failed actions were recorded under; then the
        build that answered is noted, per object for each item it served a push (those indices are its)."""
        answer = self._call("POST", path, model, json=body, requested=self._recorded_under(items, build))
        self.plan_build = self.build
        answers = [r.result for r in answer.results] if isinstance(answer, PlanResults) else [answer]
        for item, served in zip(items, answers, strict=True):
            if served is not None and served.action is not None:
                self.plan_builds[item["object_id"]] = self.build
        return answer

    def _call(self, method: str, path: str, model: type[Model], requested: str | None = None, **kwargs) -> Model:
        """``method path`` answered as ``model``, retried as the module says; ``requested``: the build the
        request's action indices were recorded under, sent as ``x-toppledb-build``."""
        kwargs["headers"] = self.headers if requested is None else {**self.headers, "x-toppledb-build": requested}
        wait = self.backoff
        for attempt in range(self.retries + 1):
            last = attempt == self.retries
            try:
                response = self.http.request(method, path, **kwargs)
            except httpx.TransportError as err:  # connect/read/write errors and timeouts
                if last:
                    raise Unreachable(0, f"{method} {path}: no answer after {attempt + 1} tries "
                                         f"({type(err).__name__}: {err})") from err
            else:
                answered = response.headers.get("x-toppledb-build")
                self.build = answered or self.build
                if response.status_code < 300:
                    if requested is not None and answered is not None and answered != requested:
                        # A stop-68 service stamps answers with their build but does not check the request's.
                        raise OtherBuild(412, f"answered by build {answered}, not {requested} that the action indices "
                                              "were recorded under: clear them and ask again",
                                         {"build": answered, "requested": requested})
                    return model.model_validate_json(response.content)
                if response.status_code not in RETRY_STATUSES or last:
                    raise _error(response)
            time.sleep(wait)
            wait *= 2
        raise AssertionError("unreachable")


def _build_name(build: str | None) -> str | None:
    """``build`` as sent in ``x-toppledb-build``: a manifest SHA-256 (64 hex digits), as answers name it."""
    if build is not None and not re.fullmatch(r"[0-9a-f]{64}", build):
        raise ValueError(f"build must be a manifest SHA-256 (64 lowercase hex digits) as x-toppledb-build names it, "
                         f"got {build[:80]!r}")
    return build


def _object_path(object_id: str) -> str:
    """``/objects/<id>`` with the id escaped whole, so that "bunny?x=1" asks for an object of that id (none
    has one: a 404), not bunny with a query.  A "/" or a dot segment would still reach another route (the
    server decodes the path before routing), and no object id holds them (``schema.layout.OBJECT_ID_PATTERN``)."""
    if "/" in object_id or object_id in (".", ".."):
        raise ValueError(f"{object_id[:80]!r} is no object id: ids match {OBJECT_ID_PATTERN.pattern}")
    return f"/objects/{quote(object_id, safe='')}"


def _integer(value: Any, name: str) -> int:
    """``value`` as an int when it is one (numpy's too), else TypeError: 2.7, "3" and True are
    refused here as the service refuses them (422), not rounded or read into another request."""
    if not isinstance(value, (bool, np.bool_)):
        try:
            return operator.index(value)
        except TypeError:
            pass
    raise TypeError(f"{name} must be an integer, got {value!r}")


def plan_item(object_id: str, pose: Any = None, ros_pose: RosPose | dict | None = None, policy: str = "value_iteration",
              pushes_left: int | None = None, failed_actions: list[int] | None = None) -> dict:
    """One /plan body (also one /batch/plan item) from a matrix or a ROS pose."""
    if (pose is None) == (ros_pose is None):
        raise ValueError("give exactly one of pose (4x4) and ros_pose")
    item: dict = {"object_id": object_id, "policy": policy}
    if pushes_left is not None:
        item["pushes_left"] = _integer(pushes_left, "pushes_left")
    if failed_actions:
        item["failed_actions"] = [_integer(a, "failed_actions") for a in failed_actions]
    if pose is not None:
        matrix = np.asarray(pose, dtype=float)
        if not np.isfinite(matrix).all():
            # JSON has no NaN or infinity: refused here as the service would refuse it (422).
            raise InvalidRequest(422, "pose: every entry must be a finite number")
        item["pose"] = matrix.tolist()
    else:
        try:
            # A failed TF lookup often gives NaN, which JSON cannot carry: refused here as the service would (422).
            # A RosPose is checked again: its fields may have been assigned since it was made.
            checked = RosPose.model_validate(ros_pose.model_dump() if isinstance(ros_pose, RosPose) else ros_pose)
        except ValidationError as err:
            body = validation_body([{**e, "loc": ("ros_pose", *e["loc"])} for e in err.errors()])  # the service's 422 body
            raise InvalidRequest(422, body["detail"], body) from None
        item["ros_pose"] = checked.model_dump()
    return item
