# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""service.client: typed answers equal to the service's JSON, errors as exceptions by status
and reason, retries only where repeating is safe and useful."""

from __future__ import annotations

import math

import httpx
import numpy as np
import pytest
from fastapi.testclient import TestClient

from schema.api import PlanResponse, RosPose
from schema.vocabulary import NO_OP
from service import create_app
from service.client import (
    Client,
    InvalidRequest,
    NoStablePose,
    NotFound,
    OffTable,
    OtherBuild,
    ServiceError,
    Unauthorized,
    Unreachable,
    plan_item,
)
from service.settings import Settings
from tests.test_service import JSON, client, dataset, planar_transform, stored_transform, tables, tilted  # noqa: F401

TOKEN = "client-test-token-0123"


@pytest.fixture(scope="module")
def typed(dataset):
    with TestClient(create_app(dataset, settings=Settings(token=TOKEN))) as http:
        yield Client(token=TOKEN, http=http, retries=0)


def pushing(tables) -> tuple[str, int]:
    return next((o, p) for (o, p), r in sorted(tables["poses"].items()) if r["value_iteration_action"] != NO_OP)


def _with_new_fields(value):
    """An answer as a newer service might send it: every object given a field this code does not know."""
    if isinstance(value, dict):
        return {**{k: _with_new_fields(v) for k, v in value.items()}, "added_by_a_newer_service": {"n": 1}}
    if isinstance(value, list):
        return [_with_new_fields(v) for v in value]
    return value


def test_a_client_reads_an_answer_from_a_newer_service_that_added_fields(client, tables):
    """Answers are open for extension: a field the client's models do not know is ignored at every depth,
    and the fields it knows read as before. Requests stay closed: a misspelt field is a 422."""
    object_id, pose = pushing(tables)
    observed = planar_transform(0.4, 0.1, 0.2) @ stored_transform(tables, object_id, pose)
    item = plan_item(object_id, pose=observed)
    answers = {"/plan": client.post("/plan", json=item), "/health": client.get("/health"),
               "/batch/plan": client.post("/batch/plan", json={"items": [item, {**item, "object_id": "nope"}]})}
    gets = {"objects": "/objects", "object": f"/objects/{object_id}",
            "pose": f"/objects/{object_id}/poses/{pose}", "action": f"/objects/{object_id}/poses/{pose}/actions/0",
            "q_values": f"/objects/{object_id}/poses/{pose}/q"}
    answers.update({path: client.get(path) for path in gets.values()})

    def handler(request):
        return httpx.Response(200, json=_with_new_fields(answers[request.url.path].json()))

    newer = Client(http=httpx.Client(transport=httpx.MockTransport(handler), base_url="http://x"), retries=0)
    plan = newer.plan(object_id, pose=observed)
    assert plan.model_dump(mode="json") == answers["/plan"].json()
    assert newer.health().model_dump(mode="json", exclude_none=True) == answers["/health"].json()
    batch = newer.plan_batch([item, {**item, "object_id": "nope"}])
    dumped = batch.model_dump(mode="json")
    assert dumped["results"][1]["error"].pop("reason") is None, "left out of the answer, None when read"
    assert dumped == answers["/batch/plan"].json() and batch.results[1].error.status == 404
    # The routes' answers too, the pose's maps keyed by policy and by status among them: a new key is dropped.
    read = {"objects": newer.objects(), "object": newer.object(object_id),
            "pose": newer.pose(object_id, pose), "action": newer.action(object_id, pose, 0), "q_values": newer.q_values(object_id, pose)}
    for name, typed_answer in read.items():
        assert typed_answer.model_dump(mode="json") == answers[gets[name]].json(), name
    misspelt = client.post("/plan", json={**item, "polciy": "value_iteration"})
    assert misspelt.status_code == 422 and "polciy" in misspelt.json()["detail"]


def test_every_answer_from_the_dataset_names_its_build(client, dataset, tables):
    """``x-toppledb-build``: the manifest SHA-256 of the build an answer came from, on the fast /plan path
    and the routes alike, errors included; not where no build was consulted (a refused token)."""
    build = client.get("/health").json()["dataset"]["manifest_sha256"]
    object_id, pose = pushing(tables)
    observed = planar_transform(0.4, 0.1, 0.2) @ stored_transform(tables, object_id, pose)
    item = plan_item(object_id, pose=observed)
    answers = [client.post("/plan", json=item), client.get("/objects"), client.get(f"/objects/{object_id}/poses/{pose}/q"),
               client.post("/batch/plan", json={"items": [item]}), client.get("/objects/nope"),
               client.post("/plan", json={**item, "object_id": "nope"})]
    assert [a.status_code for a in answers] == [200, 200, 200, 200, 404, 404]
    assert all(a.headers["x-toppledb-build"] == build for a in answers)
    typed = Client(http=client, retries=0)
    assert typed.build is None
    typed.plan(object_id, pose=observed)
    assert typed.build == build, "the typed client keeps the build of its last answer"
    with TestClient(create_app(dataset, settings=Settings(token=TOKEN))) as guarded:
        refused = guarded.get("/objects")
        assert refused.status_code == 401 and "x-toppledb-build" not in refused.headers


OTHER_BUILD = "f" * 64


@pytest.mark.parametrize("staged", [False, True], ids=["create_app", "staged"])
def test_a_request_naming_another_build_is_refused_with_412_on_every_route_that_reads_the_dataset(
        dataset, tables, monkeypatch, staged):
    """``x-toppledb-build`` on a request: the build its action indices were recorded under. The build it
    names answers as if it were not there; another is a 412 naming both, on the fast /plan path and the
    FastAPI route byte for byte, on the GET, batch and heap routes; /health does not read the dataset."""
    from service import fastplan
    from tests.test_service_staged import staged_app

    app = staged_app(dataset) if staged else create_app(dataset, settings=Settings())
    object_id, pose = pushing(tables)
    observed = planar_transform(0.4, 0.1, 0.2) @ stored_transform(tables, object_id, pose)
    with TestClient(app) as client:
        build = client.get("/health").json()["dataset"]["manifest_sha256"]
        first = client.post("/plan", json=plan_item(object_id, pose=observed)).json()["action"]
        item = plan_item(object_id, pose=observed, failed_actions=[first])
        plain = client.post("/plan", json=item)
        assert plain.status_code == 200
        cases = [(build, 200), (OTHER_BUILD, 412), ("not a build \u00e9", 412), ((build, OTHER_BUILD), 200), ((OTHER_BUILD, build), 412)]
        for named, status in cases:
            # Bytes: a header value need not be ASCII. Given twice, the first counts, on both paths as FastAPI reads it.
            header = [("x-toppledb-build", value.encode()) for value in ((named,) if isinstance(named, str) else named)]
            named = named if isinstance(named, str) else named[0]
            fast = client.post("/plan", json=item, headers=header)
            with monkeypatch.context() as patch:
                patch.setattr(fastplan, "PATH", "/not-the-fast-path")
                routed = client.post("/plan", json=item, headers=header)
            assert fast.status_code == routed.status_code == status and fast.content == routed.content
            assert fast.headers["x-toppledb-build"] == routed.headers["x-toppledb-build"] == build
            if status == 200:
                assert fast.content == plain.content, "the build it names answers as if the header were not there"
            else:
                body = fast.json()
                assert body["build"] == build and named.startswith(body["requested"][:5]) and build in body["detail"]
        other = {"x-toppledb-build": OTHER_BUILD}
        routes = [client.get(f"/objects/{object_id}/poses/{pose}/actions/{first}", headers=other),
                  client.get("/objects", headers=other),
                  client.post("/batch/plan", json={"items": [item]}, headers=other),
                  client.post("/batch/transitions", json={"items": [{"object_id": object_id, "pose": pose, "action": first}]},
                              headers=other),
                  client.post("/heaps/plan", json={"objects": [{"object_id": object_id, "pose": observed.tolist()}]},
                              headers=other)]
        assert [r.status_code for r in routes] == [412] * len(routes)
        assert all(r.json()["build"] == build and r.headers["x-toppledb-build"] == build for r in routes)
        assert client.get("/health", headers=other).status_code == 200
        long = client.get("/objects", headers={"x-toppledb-build": "f" * 200}).json()["requested"]
        assert long == "f" * 80, "the refusal echoes at most 80 characters of what it was sent"
        assert 'route="/plan",status="412"' in client.get("/metrics").text


def recording_client(client, sent: list, stamps: list | None = None) -> Client:
    """A ``Client`` whose requests the service (``client``) answers, each request's ``x-toppledb-build`` noted in
    ``sent``; ``stamps``: builds the first answers claim instead of their own, as if served before a rebuild."""
    stamps = list(stamps or [])

    def recording(request):
        sent.append(request.headers.get("x-toppledb-build"))
        real = client.request(request.method, request.url.path, content=request.content, headers=dict(request.headers))
        return httpx.Response(real.status_code, content=real.content,
                              headers={"x-toppledb-build": stamps.pop(0) if stamps else real.headers["x-toppledb-build"]})

    return Client(http=httpx.Client(transport=httpx.MockTransport(recording), base_url="http://x"), retries=0)


def test_the_client_names_the_build_of_its_failed_actions_and_raises_other_build(client, tables):
    """``plan`` sends ``x-toppledb-build`` only with failed actions: the build given, else that of its last plan
    answer (``plan_build``), which neither a refusal nor another route's answer changes, so a repeated call stays
    refused. A 412 is ``OtherBuild``. A stop-68 service, which stamps answers but does not check requests, is
    caught by the client itself; a service that names no build is not taken for another one."""
    object_id, pose = pushing(tables)
    observed = planar_transform(0.4, 0.1, 0.2) @ stored_transform(tables, object_id, pose)
    sent: list[str | None] = []
    served = client.get("/health").json()["dataset"]["manifest_sha256"]
    typed = recording_client(client, sent)
    first = typed.plan(object_id, pose=observed)
    after = typed.plan(object_id, pose=observed, failed_actions=[first.action])
    assert sent == [None, served] and after.action != first.action and typed.plan_build == served
    assert typed.plan_builds == {object_id: served}
    with pytest.raises(OtherBuild) as refused:
        typed.plan(object_id, pose=observed, failed_actions=[first.action], build=OTHER_BUILD)
    assert refused.value.status == 412 and refused.value.body["build"] == served and sent[-1] == OTHER_BUILD
    assert "but build" in refused.value.detail, "the service's own refusal"
    typed.plan_builds[object_id] = OTHER_BUILD  # as if the push that failed came from a build since replaced
    for _ in range(2):  # repeated, and after another route's answer from the new build: still refused
        with pytest.raises(OtherBuild):
            typed.plan_batch([plan_item(object_id, pose=observed, failed_actions=[first.action])])
        assert sent[-1] == OTHER_BUILD and typed.build == served and typed.plan_builds[object_id] == OTHER_BUILD
        typed.objects()
    typed.plan_batch([plan_item(object_id, pose=observed)])
    assert sent[-1] is None and typed.plan_builds[object_id] == served, "asked afresh: the new build's indices from here on"
    with pytest.raises(OtherBuild):  # a build given outranks plan_builds, in a batch too
        typed.plan_batch([plan_item(object_id, pose=observed, failed_actions=[first.action])], build=OTHER_BUILD)
    assert sent[-1] == OTHER_BUILD and typed.plan_builds[object_id] == served
    for lookup in (lambda: typed.action(object_id, pose, first.action, build=OTHER_BUILD),
                   lambda: typed.transitions([(object_id, pose, first.action)], build=OTHER_BUILD)):
        with pytest.raises(OtherBuild):
            lookup()
    assert typed.action(object_id, pose, first.action, build=served).action == first.action
    for malformed in ("\u00e9", "abc", "g" * 64, "F" * 64, served + "0"):  # not 64 lowercase hex digits
        with pytest.raises(ValueError, match="64 lowercase hex"):
            typed.plan(object_id, pose=observed, failed_actions=[first.action], build=malformed)

    def older(stamp):  # a service from before stop 69: answers whatever build the request names
        return Client(http=httpx.Client(transport=httpx.MockTransport(
            lambda r: httpx.Response(200, content=client.post("/plan", content=r.content, headers=JSON).content,
                                     headers=stamp)), base_url="http://x"), retries=0)

    with pytest.raises(OtherBuild, match="answered by build .*: clear them and ask again$") as caught:
        older({"x-toppledb-build": served}).plan(object_id, pose=observed, failed_actions=[first.action], build=OTHER_BUILD)
    assert caught.value.status == 412 and caught.value.body == {"build": served, "requested": OTHER_BUILD}
    unnamed = older({}).plan(object_id, pose=observed, failed_actions=[first.action], build=OTHER_BUILD)
    assert unnamed.action == after.action, "a service naming no build (before stop 68) cannot be checked"


def test_the_client_names_each_objects_own_build_when_a_swap_falls_between_two_objects_plans(client, tables):
    """A controller planning two objects in turn across a rebuild: the failed push of the first object carries
    the build that served it, not the build that answered the second object since, so the new build refuses
    it (with the last plan answer's build, ``plan_build``, the new build would read the old indices). A batch
    whose failed actions were recorded under two builds is refused before it is sent; an answer that served no
    push, or an item refused, records nothing."""
    pushes = [(o, p) for (o, p), r in sorted(tables["poses"].items()) if r["value_iteration_action"] != NO_OP]
    (first_id, first_pose), (second_id, second_pose) = pushes[0], next(q for q in pushes if q[0] != pushes[0][0])
    observed = {o: planar_transform(0.4, 0.1, 0.2) @ stored_transform(tables, o, p)
                for o, p in ((first_id, first_pose), (second_id, second_pose))}
    served = client.get("/health").json()["dataset"]["manifest_sha256"]
    sent: list[str | None] = []
    typed = recording_client(client, sent, stamps=[OTHER_BUILD])  # the first answer from a build replaced before the second
    failed = typed.plan(first_id, pose=observed[first_id]).action
    other = typed.plan(second_id, pose=observed[second_id]).action
    assert typed.plan_builds == {first_id: OTHER_BUILD, second_id: served} and typed.plan_build == served
    with pytest.raises(OtherBuild) as refused:
        typed.plan(first_id, pose=observed[first_id], failed_actions=[failed])
    assert sent[-1] == OTHER_BUILD and refused.value.body["build"] == served, "the service's own 412"
    calls = len(sent)
    both = [plan_item(first_id, pose=observed[first_id], failed_actions=[failed]),
            plan_item(second_id, pose=observed[second_id], failed_actions=[other])]
    with pytest.raises(OtherBuild, match="2 builds") as mixed:
        typed.plan_batch(both)
    assert len(sent) == calls and mixed.value.body["recorded"] == {first_id: OTHER_BUILD, second_id: served}
    assert mixed.value.body["requested"] == ", ".join(sorted((OTHER_BUILD, served))), "a string, as the service's 412"
    answer = typed.plan_batch(both, build=served)  # the caller's word outranks the records
    assert sent[-1] == served and all(r.result is not None for r in answer.results)
    assert typed.plan_builds == {first_id: served, second_id: served}
    typed.plan_builds[first_id] = OTHER_BUILD
    refused_item = plan_item("no-such-object", pose=observed[first_id])
    typed.plan_batch([refused_item, plan_item(second_id, pose=observed[second_id])])
    assert typed.plan_builds == {first_id: OTHER_BUILD, second_id: served}, "an item refused records nothing"
    stranger = plan_item(second_id, pose=observed[second_id], failed_actions=[other])
    typed.plan_builds.clear()
    typed.plan_batch([stranger])
    assert sent[-1] is None, "failed actions of an object no answer served: no build is named"
    typed.plan_builds[first_id] = served  # one object known, the other not (a client started since): the known build
    typed.plan_batch([both[0], stranger])
    assert sent[-1] == served


def test_typed_answers_equal_the_json(typed, client, tables):
    object_id, pose = pushing(tables)
    observed = planar_transform(0.4, 0.1, 0.2) @ stored_transform(tables, object_id, pose)
    answer = typed.plan(object_id, pose=observed)
    assert isinstance(answer, PlanResponse) and answer.decision == "push" and answer.match.pose == pose
    assert answer.model_dump(mode="json") == client.post("/plan", json=plan_item(object_id, pose=observed)).json()
    assert typed.health().counts.objects == 3 and typed.objects().count == 3
    assert typed.pose(object_id, pose).pose == pose and typed.object(object_id).object_id == object_id
    assert typed.action(object_id, pose, answer.action).status == "ok"
    assert typed.q_values(object_id, pose, top=3).top[0].action == answer.action
    batch = typed.plan_batch([plan_item(object_id, pose=observed), plan_item("mug", pose=np.eye(4))])
    assert batch.results[0].result == answer and batch.results[1].error.status == 404
    assert typed.transitions([(object_id, pose, answer.action)]).results[0].result.action == answer.action
    budget = typed.plan(object_id, pose=observed, pushes_left=2)
    assert budget.pushes_left == 2
    assert budget.model_dump(mode="json") == client.post("/plan", json=plan_item(object_id, pose=observed, pushes_left=2)).json()
    if answer.action is not None:
        after = typed.plan(object_id, pose=observed, failed_actions=[answer.action])
        assert after.ruled_out >= 1 and after.action != answer.action
        assert after.model_dump(mode="json") == client.post(
            "/plan", json=plan_item(object_id, pose=observed, failed_actions=[answer.action])).json()


def test_errors_are_exceptions_by_status_and_reason(typed, tables):
    object_id, pose = pushing(tables)
    lifted = planar_transform(0.0, 0.0, 0.0) @ stored_transform(tables, object_id, pose)
    lifted[2, 3] += 0.5
    with pytest.raises(OffTable) as off:
        typed.plan(object_id, pose=lifted)
    assert off.value.status == 409 and off.value.body["z_offset"] == pytest.approx(0.5)
    with pytest.raises(NoStablePose):
        typed.plan("random_001", pose=tilted(tables, "random_001", 0, math.radians(30))[0])
    with pytest.raises(NotFound, match="unknown object 'mug'"):
        typed.plan("mug", pose=np.eye(4))
    with pytest.raises(InvalidRequest, match="not a rotation"):
        typed.plan(object_id, pose=np.diag([2.0, 1, 1, 1]))
    with pytest.raises(ValueError, match="exactly one"):
        plan_item(object_id)
    for budget in (2.7, "3", True, np.True_):  # the service takes integers only; the client sends what it was given
        with pytest.raises(TypeError):
            plan_item(object_id, pose=np.eye(4), pushes_left=budget)
    assert plan_item(object_id, pose=np.eye(4), pushes_left=np.int64(2))["pushes_left"] == 2
    # An id is one path segment, escaped: never a query, nor a path to another route.
    for odd in (f"{object_id}?x=1", "a b#c", "%2e%2e", "-"):
        with pytest.raises(NotFound):
            typed.object(odd)
    for path in (f"{object_id}/poses", "../health", "..", "."):  # would reach another route: no id is one
        with pytest.raises(ValueError, match="is no object id"):
            typed.object(path)
    with pytest.raises(NotFound, match="unknown object 'a b#c'"):
        typed.pose("a b#c", 0)
    assert typed.pose(object_id, np.int64(pose)).pose == pose
    for index in (float(pose), "1", True):  # as the plan's integers: refused, not formatted into the path
        with pytest.raises(TypeError):
            typed.pose(object_id, index)
        with pytest.raises(TypeError):
            typed.action(object_id, pose, index)
        with pytest.raises(TypeError, match=r"items\[1\] action must be an integer"):  # int() would truncate 1.7 to push 1
            typed.transitions([(object_id, pose, 0), (object_id, pose, index)])
        with pytest.raises(TypeError, match=r"items\[0\] pose must be an integer"):
            typed.transitions([(object_id, index, 0)])
    assert typed.transitions([(object_id, np.int64(pose), np.int64(0))]).results[0].result.pose == pose
    with pytest.raises(Unauthorized):
        Client(http=typed.http, retries=0, token="another-token-of-length").objects()
    # The shared http client is not rewritten: the first Client's token still goes with its requests, and a Client
    # given no token sends none of its own.
    assert typed.objects().objects
    with pytest.raises(Unauthorized):
        Client(http=typed.http, retries=0).objects()
    assert "authorization" not in typed.http.headers


def test_retries_transport_errors_and_503_but_never_4xx(dataset):
    app = create_app(dataset)
    calls: list[str] = []
    script = iter(["connect", "503", "pass"] + ["404"] * 10)

    with TestClient(app) as real:

        def handler(request: httpx.Request) -> httpx.Response:
            step = next(script)
            calls.append(step)
            if step == "connect":
                raise httpx.ConnectError("refused", request=request)
            if step == "503":
                return httpx.Response(503, json={"detail": "busy"})
            if step == "404":
                return httpx.Response(404, json={"detail": "unknown object 'x'"})
            return httpx.Response(200, content=real.get(request.url.path).content)

        flaky = Client(http=httpx.Client(transport=httpx.MockTransport(handler), base_url="http://x"), retries=2, backoff=0.0)
        assert flaky.health().status == "ok" and calls == ["connect", "503", "pass"]
        refused = Client(http=httpx.Client(transport=httpx.MockTransport(
            lambda r: (_ for _ in ()).throw(httpx.ConnectError("refused", request=r))), base_url="http://x"),
            retries=1, backoff=0.0)
        with pytest.raises(Unreachable, match="GET /health: no answer after 2 tries") as gone:
            refused.health()
        assert isinstance(gone.value, ServiceError) and gone.value.status == 0
        assert isinstance(gone.value.__cause__, httpx.ConnectError)
        with pytest.raises(InvalidRequest, match="finite"):
            refused.plan("x", pose=np.full((4, 4), np.nan))
        # A ROS pose with NaN (a failed TF lookup) is refused the same way, before anything is sent.
        nan_ros = {"position": {"x": float("nan"), "y": 0.0, "z": 0.0},
                   "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}, "frame_id": "world"}
        with pytest.raises(InvalidRequest, match=r"ros_pose\.position\.x: .*finite") as bad:
            refused.plan("x", ros_pose=nan_ros)
        assert bad.value.status == 422 and bad.value.body["errors"][0]["loc"] == ["ros_pose", "position", "x"]  # as the service's
        reused = RosPose.model_validate({**nan_ros, "position": {"x": 0.0, "y": 0.0, "z": 0.0}})
        reused.position.x = float("inf")  # a message refreshed in place from TF
        with pytest.raises(InvalidRequest, match=r"ros_pose\.position\.x"):
            refused.plan("x", ros_pose=reused)
        with pytest.raises(NotFound):
            flaky.health()
        assert calls[3:] == ["404"], "a 404 is an answer, not a failure to retry"
        with pytest.raises(ServiceError):
            Client(http=httpx.Client(transport=httpx.MockTransport(lambda r: httpx.Response(503, json={"detail": "busy"})),
                                     base_url="http://x"), retries=1, backoff=0.0).health()


def answering(status: int, **response) -> Client:
    """A client of a server (a proxy, a load balancer) that answers every request with ``status`` and ``response``."""
    return Client(http=httpx.Client(transport=httpx.MockTransport(lambda r: httpx.Response(status, **response)),
                                    base_url="http://x"), retries=0)


def test_a_409_whose_json_is_no_object_is_a_service_error_not_an_attribute_error():
    """A 409 is read by its ``reason``; JSON that is no object has none, and is the 409's default exception
    with what it said as ``detail`` (it raised AttributeError, looking up ``reason`` in a list)."""
    for said, detail in ((b'["conflict"]', "['conflict']"), (b'"conflict"', "conflict"), (b"null", "None")):
        with pytest.raises(NoStablePose) as refused:
            answering(409, content=said).health()
        assert refused.value.status == 409 and refused.value.detail == detail and refused.value.body == {}
    with pytest.raises(OffTable):
        answering(409, json={"detail": "lifted", "reason": "off_table"}).health()


def test_an_answer_not_from_the_service_is_the_exception_of_its_status():
    """A proxy in front of the service answers in its own words: a page that is not JSON (``detail`` its first
    200 characters), JSON without ``detail`` (an empty one) or JSON that is no object (said as ``detail``, no
    fields). 413 and 415 are malformed requests, as 422; a status the client does not know is a ``ServiceError``."""
    page = "<html><body>" + "504 Gateway Time-out " * 20 + "</body></html>"
    with pytest.raises(ServiceError) as html:
        answering(504, text=page).health()
    assert type(html.value) is ServiceError and html.value.status == 504
    assert html.value.detail == page[:200] and html.value.body == {"detail": page[:200]}
    with pytest.raises(ServiceError) as bare:
        answering(500, json={"error": "upstream"}).health()
    assert bare.value.detail == "" and bare.value.body == {"error": "upstream"}
    with pytest.raises(NotFound) as listed:
        answering(404, json=["no", "route"]).health()
    assert listed.value.detail == "['no', 'route']" and listed.value.body == {}
    for status in (413, 415, 422):
        with pytest.raises(InvalidRequest) as malformed:
            answering(status, json={"detail": "too large"}).health()
        assert malformed.value.status == status and malformed.value.detail == "too large"
    for status in (414, 416):
        with pytest.raises(ServiceError) as other:
            answering(status, json={"detail": "odd"}).health()
        assert type(other.value) is ServiceError


def test_q_values_asks_for_the_ranking_and_length_given(client, tables):
    """``top`` and ``by`` reach the service; the defaults are the route's (ten actions by Q)."""
    typed = Client(http=client, retries=0)
    object_id, pose = pushing(tables)
    path = f"/objects/{object_id}/poses/{pose}/q"
    default = client.get(path).json()
    assert len(default["top"]) == 10 and default["by"] == "q", "the pose has more than ten ranked actions"
    assert typed.q_values(object_id, pose).model_dump(mode="json") == default
    ranked = typed.q_values(object_id, pose, top=3, by="p_topple")
    assert ranked.by == "p_topple" and len(ranked.top) == 3
    assert ranked.model_dump(mode="json") == client.get(path, params={"top": 3, "by": "p_topple"}).json()
    with pytest.raises(TypeError, match=r"^pose must be an integer, got 1\.0$"):
        typed.q_values(object_id, 1.0)


@pytest.mark.parametrize("status,tries", [(500, 1), (501, 1), (502, 3), (503, 3), (504, 3), (429, 1)])
def test_only_a_gateways_or_an_overloaded_services_answer_is_retried(status, tries):
    """502, 503 and 504 say the service was not reached or could not take the request now (docs/SERVICE.md,
    "Python client"); a 500 is a bug the same request meets again, and is answered at once."""
    asked = []

    def answer(request):
        asked.append(request.url.path)
        return httpx.Response(status, json={"detail": "no"})

    flaky = Client(http=httpx.Client(transport=httpx.MockTransport(answer), base_url="http://x"), retries=2, backoff=0.0)
    with pytest.raises(ServiceError) as refused:
        flaky.objects()
    assert refused.value.status == status and asked == ["/objects"] * tries


def _models_within(model) -> set:
    """``model`` and every pydantic model its fields hold, at any depth (lists, maps, unions)."""
    import typing

    from pydantic import BaseModel

    found, stack = set(), [model]
    while stack:
        current = stack.pop()
        if current in found:
            continue
        found.add(current)
        for field in current.model_fields.values():
            annotations = [field.annotation]
            while annotations:
                annotation = annotations.pop()
                if isinstance(annotation, type) and issubclass(annotation, BaseModel):
                    stack.append(annotation)
                annotations.extend(typing.get_args(annotation))
    return found


def test_requests_refuse_unknown_fields_at_every_depth_and_answers_ignore_them():
    """Every model a request body holds forbids extra fields (a misspelt field is a 422); every other API
    model is an answer's and ignores them (docs/SERVICE.md, "Versions")."""
    from pydantic import BaseModel

    from schema import api

    bodies = [api.PlanRequest, api.PlanBatch, api.TransitionBatch, api.HeapPlanRequest]
    requests = set().union(*map(_models_within, bodies))
    assert {api.RosPose, api.Point, api.Quaternion, api.HeapBin, api.HeapObject, api.TransitionQuery} <= requests
    models = {m for m in vars(api).values() if isinstance(m, type) and issubclass(m, BaseModel) and m.__module__ == api.__name__}
    answers = models - requests - {api.Model, api.Answer}
    assert all(m.model_config.get("extra") == "forbid" for m in requests), sorted(m.__name__ for m in requests)
    assert answers and all(m.model_config.get("extra") == "ignore" for m in answers), sorted(
        m.__name__ for m in answers if m.model_config.get("extra") != "ignore")
    assert not requests & set().union(*(_models_within(m) for m in answers)), "no answer holds a request's model"
