# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""The service's answers as a robot controller relies on them: decisions, off-table poses,
pushes on a tilted object's surface, forces against the finger's limit, ROS poses, and the
guard's 401/413/415/422 (the tiny dataset of tests/test_service.py)."""

from __future__ import annotations

import copy
import datetime
import hashlib
import json
import math
import re
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
from fastapi.testclient import TestClient

from schema.api import FINGER_FORCE_LIMIT, HEIGHT_TOLERANCE, RosPose
from schema.vocabulary import NO_OP
from service import create_app
from service.settings import Settings
from service.store import Store
from tests.test_service import (  # noqa: F401 (fixtures)
    OBJECTS,
    client,
    dataset,
    planar_transform,
    rotation_about,
    stored_transform,
    tables,
    tilted,
    xyz,
)
from tests.test_service_fastplan import call

JSON = {"content-type": "application/json"}
TOKEN = "s3cret-token-for-tests"


def pushing_poses(tables, policy: str = "value_iteration") -> list[tuple[str, int, dict]]:
    return [(o, p, r) for (o, p), r in sorted(tables["poses"].items()) if r[f"{policy}_action"] != NO_OP]


def observe(tables, object_id: str, pose: int, lift: float = 0.0, tilt: float = 0.0) -> np.ndarray:
    """Object -> world: the stable pose at yaw 0.7, (0.3, -0.2), raised by ``lift`` m and
    tilted by ``tilt`` rad about a horizontal axis through the support point."""
    observed = planar_transform(0.7, 0.3, -0.2) @ stored_transform(tables, object_id, pose)
    support = np.eye(4)
    support[:3, 3] = [0.3, -0.2, 0.0]
    observed = support @ rotation_about([1.0, 2.0, 0.0], tilt) @ np.linalg.inv(support) @ observed
    observed[2, 3] += lift
    return observed


def post_plan(client, object_id, observed, policy="value_iteration"):
    return client.post("/plan", json={"object_id": object_id, "pose": observed.tolist(), "policy": policy})


def edited(dataset, tmp_path, edit):
    """A copy of the dataset whose manifest.json ``edit`` (a function of the parsed JSON) has changed."""
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    edit(manifest)
    (copy / "manifest.json").write_text(json.dumps(manifest))
    return copy


# --- off the table -------------------------------------------------------------------


@pytest.mark.parametrize("lift", [0.02, -0.02, 1000.0])
def test_an_object_off_the_table_is_409_with_its_height(client, tables, lift):
    object_id, pose, _ = pushing_poses(tables)[0]
    response = post_plan(client, object_id, observe(tables, object_id, pose, lift=lift))
    assert response.status_code == 409, response.text
    body = response.json()
    assert body["reason"] == "off_table" and body["pose"] == pose and body["height_tolerance"] == HEIGHT_TOLERANCE
    assert body["z_offset"] == pytest.approx(lift, abs=1e-9)
    assert ("above" if lift > 0 else "below") in body["detail"] and "not resting on the table" in body["detail"]


def test_within_the_height_tolerance_the_push_follows_the_observed_height(client, tables):
    object_id, pose, _ = pushing_poses(tables)[0]
    lift = 0.8 * HEIGHT_TOLERANCE
    low, high = (post_plan(client, object_id, observe(tables, object_id, pose, lift=h)).json() for h in (0.0, lift))
    assert high["match"]["z_offset"] == pytest.approx(lift, abs=1e-12)
    np.testing.assert_allclose(np.subtract(high["push"]["point"], low["push"]["point"]), [0, 0, lift], atol=1e-9)


def test_a_409_for_no_stable_pose_says_so(client, tables):
    observed, _ = tilted(tables, "random_001", 0, math.radians(30))
    body = post_plan(client, "random_001", observed).json()
    assert body["reason"] == "no_stable_pose" and body["object_id"] == "random_001"


# --- pushes placed through the observed pose -----------------------------------------


def test_a_tilted_observation_gets_the_push_on_its_surface(client, tables):
    tilt = math.radians(6.0)
    checked = 0
    for object_id, pose, _row in pushing_poses(tables):
        observed = observe(tables, object_id, pose, tilt=tilt)
        response = post_plan(client, object_id, observed)
        if response.status_code != 200 or response.json()["match"]["pose"] != pose:
            continue  # the tilt brought it nearer another pose, or lifted the support point off the table
        body = response.json()
        pose_to_world = observed @ np.linalg.inv(stored_transform(tables, object_id, pose))
        np.testing.assert_allclose(body["match"]["pose_to_world"], pose_to_world, atol=1e-12)
        action = tables["actions"][(object_id, pose, body["action"])]
        # The stored contact, carried by the object as observed: on its surface, not beside it.
        on_surface = (pose_to_world @ [*xyz(action, "point"), 1.0])[:3]
        np.testing.assert_allclose(body["push"]["point"], on_surface, atol=1e-6)
        np.testing.assert_allclose(body["push"]["normal"], pose_to_world[:3, :3] @ xyz(action, "normal"), atol=1e-6)
        planar_only = (np.asarray(body["match"]["planar"]) @ [*xyz(action, "point"), 1.0])[:3]
        if np.linalg.norm(xyz(action, "point")[:2]) > 0.005 or xyz(action, "point")[2] > 0.005:
            assert np.linalg.norm(planar_only - on_surface) > 1e-4, "the tilt must move the contact"
        checked += 1
    assert checked >= 2


# --- values, decisions, forces ---------------------------------------------------------


def test_force_is_reported_against_the_finger_limit(dataset, tables):
    object_id, pose, row = pushing_poses(tables)[0]
    action = tables["actions"][(object_id, pose, row["value_iteration_action"])]
    force = action["mean_force"]
    observed = observe(tables, object_id, pose)
    for limit, settings in [(FINGER_FORCE_LIMIT, Settings()), (force / 2, Settings(finger_force_limit=force / 2))]:
        with TestClient(create_app(dataset, settings=settings)) as c:
            push = post_plan(c, object_id, observed).json()["push"]
        assert push["required_force"] == pytest.approx(force, rel=1e-6) and push["finger_force_limit"] == limit
        assert push["within_force_limit"] == (force <= limit)
    assert force / 2 < force, "the halved limit must be exceeded"


def test_a_manifest_finger_force_limit_is_used(dataset, tables, tmp_path):
    copy = tmp_path / "dataset"
    shutil.copytree(dataset, copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["parameters"]["topple"]["max_finger_force"] = 0.001
    (copy / "manifest.json").write_text(json.dumps(manifest))
    object_id, pose, _ = pushing_poses(tables)[0]
    with TestClient(create_app(copy, settings=Settings())) as c:
        push = post_plan(c, object_id, observe(tables, object_id, pose)).json()["push"]
        body = post_plan(c, object_id, observe(tables, object_id, pose)).json()
    assert push["finger_force_limit"] == 0.001 and push["within_force_limit"] is False
    assert "more than the finger's limit" in body["reason"]


def test_a_build_that_recorded_no_finger_force_limit_is_held_to_the_default(dataset, tables, tmp_path):
    copy = edited(dataset, tmp_path, lambda manifest: manifest["parameters"]["topple"].pop("max_finger_force"))
    object_id, pose, _ = pushing_poses(tables)[0]
    with TestClient(create_app(copy, settings=Settings())) as c:
        push = post_plan(c, object_id, observe(tables, object_id, pose)).json()["push"]
    assert push["finger_force_limit"] == FINGER_FORCE_LIMIT


def test_no_push_and_no_grasp_says_so(dataset, tables):
    object_id, pose, _ = pushing_poses(tables)[0]
    app = create_app(dataset)
    obj = app.state.live.store.objects[object_id]
    obj.policy_action["value_iteration"] = obj.policy_action["value_iteration"].copy()
    obj.v_s, obj.grasp_point = obj.v_s.copy(), obj.grasp_point.copy()
    obj.policy_action["value_iteration"][pose] = NO_OP  # a pose where the policy does not push ...
    obj.v_s[pose] = 0.0  # ... and there is no grasp
    obj.grasp_point[pose] = np.nan
    with TestClient(app) as c:
        body = post_plan(c, object_id, observe(tables, object_id, pose)).json()
    assert body["decision"] == "no_grasp" and body["grasp"] is None and body["v_s"] == 0.0
    assert "no suction grasp" in body["reason"] and body["push"] is None


# --- ROS poses ---------------------------------------------------------------------------


def quaternion(rotation: np.ndarray) -> list[float]:
    """x, y, z, w of a rotation matrix (Shepperd, w > 0 branch suffices for these tests)."""
    w = math.sqrt(max(0.0, 1 + np.trace(rotation))) / 2
    if w < 1e-3:
        pytest.skip("rotation near a half turn")
    return [(rotation[2, 1] - rotation[1, 2]) / (4 * w), (rotation[0, 2] - rotation[2, 0]) / (4 * w),
            (rotation[1, 0] - rotation[0, 1]) / (4 * w), w]


def ros_pose(observed: np.ndarray, frame_id: str = "world") -> dict:
    x, y, z, w = quaternion(observed[:3, :3])
    return {"position": dict(zip("xyz", observed[:3, 3])), "orientation": {"x": x, "y": y, "z": z, "w": w}, "frame_id": frame_id}


def test_a_ros_pose_plans_like_its_matrix(client, tables):
    for object_id, pose, _ in pushing_poses(tables)[:4]:
        observed = observe(tables, object_id, pose)
        given = ros_pose(observed)
        np.testing.assert_allclose(RosPose.model_validate(given).matrix(), observed, atol=1e-12)
        by_matrix = post_plan(client, object_id, observed).json()
        by_ros = client.post("/plan", json={"object_id": object_id, "ros_pose": given}).json()
        assert by_ros["action"] == by_matrix["action"] and by_ros["match"]["pose"] == pose
        np.testing.assert_allclose(by_ros["push"]["point"], by_matrix["push"]["point"], atol=1e-9)


@pytest.mark.parametrize(
    "change,message",
    [
        ({"frame_id": "camera_link"}, "frame_id is 'camera_link', but this service plans in 'world'"),
        ({"orientation": {"x": 0, "y": 0, "z": 0, "w": 2}}, "not unit: |q| = 2"),
        ({"orientation": {"x": 0, "y": 0, "z": 0}}, "body.ros_pose.orientation.w: Field required"),
        ({"position": {"x": 0, "y": 0, "z": "NaN"}}, "body.ros_pose.position.z"),
    ],
)
def test_malformed_ros_poses_are_422(client, tables, change, message):
    object_id, pose, _ = pushing_poses(tables)[0]
    given = {**ros_pose(observe(tables, object_id, pose)), **change}
    response = client.post("/plan", json={"object_id": object_id, "ros_pose": given})
    assert response.status_code == 422 and message in response.json()["detail"], response.text


W_FIRST = ("If the quaternion came from a library that orders it w, x, y, z (Eigen's Quaterniond constructor, transforms3d, "
           "pyquaternion): read so, it is pose {pose}, {angle} deg away and on the table; geometry_msgs orders it x, y, z, w")


def sent_w_first(given: dict) -> dict:
    x, y, z, w = (given["orientation"][k] for k in "xyzw")
    return {**given, "orientation": {"x": w, "y": x, "z": y, "w": z}}


def test_a_quaternion_sent_w_first_is_named_in_the_refusal(client, tables):
    """Eigen's constructor, transforms3d and pyquaternion order a quaternion w, x, y, z; geometry_msgs x, y, z, w.
    Sent in the wrong order it reads as another rotation: refused (409: no stable pose, or one off the table),
    the refusal names the pose it would be, also when the object is observed a little tilted."""
    refused = 0
    for object_id, pose, _ in pushing_poses(tables):
        for yaw in np.linspace(0.0, 2 * math.pi, 7, endpoint=False):
            for tilt, angle in ((0.0, "0.0"), (math.radians(1.5), "1.5")):  # 1.5 deg: within the hint's 2.5
                observed = planar_transform(yaw, 0.0, 0.0) @ observe(tables, object_id, pose, tilt=tilt)
                if np.trace(observed[:3, :3]) < -0.9:  # near a half turn, where ``quaternion`` would skip the test
                    continue
                response = client.post("/plan", json={"object_id": object_id, "ros_pose": sent_w_first(ros_pose(observed))})
                if response.status_code != 409:  # the wrong reading happens to rest on another pose: nothing to tell
                    assert response.status_code == 200, response.text
                    continue
                refused += 1
                detail = response.json()["detail"]
                assert detail.endswith(" " + W_FIRST.format(pose=pose, angle=angle)), detail
    assert refused >= 10  # the wrong order is refused for most orientations


def test_a_tilted_object_sent_in_order_is_rarely_taken_for_one_sent_w_first(client, tables):
    """A correctly ordered quaternion of a tilted object, read w first, lands anywhere within the pose
    tolerance: the hint names only readings within a quarter of it (2.5 deg), so few refusals carry it."""
    rng = np.random.default_rng(71)
    refused, hinted = 0, 0
    for object_id, pose, _ in pushing_poses(tables):
        for _ in range(40):
            axis = rng.normal(size=3)
            observed = observe(tables, object_id, pose)
            observed[:3, :3] = rotation_about(axis, float(np.linalg.norm(rng.normal(0.0, 0.5, 3))))[:3, :3] @ observed[:3, :3]
            if np.trace(observed[:3, :3]) < -0.9:
                continue
            response = client.post("/plan", json={"object_id": object_id, "ros_pose": ros_pose(observed)})
            if response.status_code != 409:
                continue
            refused += 1
            detail = response.json()["detail"]
            hint = re.search(r"read so, it is pose \d+, ([0-9.]+) deg away", detail)
            hinted += hint is not None
            assert hint is None or float(hint.group(1)) <= 2.5, detail
    assert refused >= 50 and hinted <= 0.05 * refused, (refused, hinted)


def test_both_pose_forms_at_once_are_422(client, tables):
    object_id, pose, _ = pushing_poses(tables)[0]
    observed = observe(tables, object_id, pose)
    response = client.post("/plan", json={"object_id": object_id, "pose": observed.tolist(), "ros_pose": ros_pose(observed)})
    assert response.status_code == 422 and "exactly one of pose" in response.json()["detail"]


# --- the guard: content type, body size, malformed JSON, token -------------------------------


@pytest.mark.parametrize("path", ["/plan", "/batch/plan", "/batch/transitions"])
def test_wrong_content_type_is_415_and_malformed_json_422(client, path):
    for content_type in ("text/plain", "application/x-www-form-urlencoded", None):
        headers = {} if content_type is None else {"content-type": content_type}
        response = client.post(path, content=b'{"items": []}', headers=headers)
        assert response.status_code == 415 and "application/json" in response.json()["detail"], response.text
    for broken in (b"{not json", b'{"items": [1,', b"\xff\xfe", b"\x80", b'{"items": "\xe9"}'):
        response = client.post(path, content=broken, headers=JSON)
        assert response.status_code == 422 and "JSON decode error" in response.json()["detail"], (broken, response.text)
    response = client.post(path, content=b"", headers=JSON)
    assert response.status_code == 422 and response.json()["detail"] == "body: Field required"
    deep = b'{"items": ' + b"[" * 5000 + b"]" * 5000 + b"}"  # ASCII, past the decoder's recursion limit
    response = client.post(path, content=deep, headers=JSON)
    assert response.status_code == 422 and response.json()["detail"] == "body: JSON decode error: nested too deeply", response.text
    # The parser gives no position for these two; the message says what it found instead.
    response = client.post(path, content=b'{"items": "\xe9"}', headers=JSON)
    assert response.status_code == 422 and response.json()["detail"] == "body: JSON decode error: not UTF-8 text", response.text
    huge = b'{"items": ' + b"7" * 5000 + b"}"  # valid JSON, but past Python's 4,300 digits of an int
    response = client.post(path, content=huge, headers=JSON)
    assert response.status_code == 422, response.text
    assert response.json()["detail"] == "body: JSON decode error: a number of more than 4300 digits", response.text


@pytest.mark.parametrize("method", ["PUT", "PATCH", "DELETE"])
def test_a_method_no_route_takes_is_405_with_or_without_a_body(client, method):
    for path in ("/plan", "/health", "/objects"):
        for headers, body in (({}, None), (JSON, b"{}"), ({"content-type": "text/plain"}, b"x")):
            response = client.request(method, path, content=body, headers=headers)
            assert response.status_code == 405, (method, path, headers, response.text)
    if method != "DELETE":  # a declared body over the limit is refused before anything reads it
        huge = client.request(method, "/plan", headers={"content-length": str(10**10)}, content=b"")
        assert huge.status_code == 413 and huge.headers["connection"] == "close"


@pytest.mark.parametrize("path", ["/plan", "/batch/plan", "/heaps/plan"])
def test_a_body_in_utf16_or_utf32_is_422_as_docs_service_says(client, path):
    # Python's JSON decoder reads UTF-16 and UTF-32 by their byte pattern; JSON on the wire is UTF-8.
    for encoding in ("utf-16", "utf-16-le", "utf-16-be", "utf-32", "utf-32-le"):
        response = client.post(path, content='{"items": []}'.encode(encoding), headers=JSON)
        assert response.status_code == 422, (encoding, response.text)
        assert "UTF-16 or UTF-32; send UTF-8" in response.json()["detail"]


def test_two_content_types_are_415_even_if_one_is_json(client):
    for pair in ([("content-type", "text/plain"), ("content-type", "application/json")],
                 [("content-type", "application/json"), ("content-type", "application/json")]):
        response = client.post("/plan", content=b"{}", headers=pair)
        assert response.status_code == 415 and "application/json" in response.json()["detail"], response.text


def test_a_post_no_route_takes_is_404_or_405_whatever_its_content_type(client):
    # Not a 415 asking for JSON that no route there would take (schemathesis flagged it).
    for headers in ({}, {"content-type": "text/plain"}, JSON):
        for path, status in (("/objects", 405), ("/health", 405), ("/objects/random_000/poses/0", 405), ("/nowhere", 404)):
            response = client.post(path, content=b"{}", headers=headers)
            assert response.status_code == status, (path, headers, response.text)


def test_behind_a_root_path_the_guard_still_checks_the_post_routes(dataset):
    # uvicorn --root-path puts the prefix in the ASGI path; the guard must match the routes without it.
    with TestClient(create_app(dataset), root_path="/api") as prefixed:
        response = prefixed.post("/api/plan", content=b'{"object_id": "x"}', headers={"content-type": "text/plain"})
        assert response.status_code == 415, response.text
        padded = b'{"object_id": "x", "pose": [' + b" " * (70 * 1024) + b"]}"
        assert prefixed.post("/api/plan", content=padded, headers=JSON).status_code == 413
        assert prefixed.post("/api/objects", content=b"{}", headers={"content-type": "text/plain"}).status_code == 405


def test_the_guard_reads_the_body_of_every_post_route_and_only_those(client):
    from service.guard import POST_PATHS

    paths = client.get("/openapi.json").json()["paths"]
    assert POST_PATHS == {path for path, operations in paths.items() if "post" in operations}


def test_single_requests_have_a_small_body_limit_batches_a_large_one(client):
    from service.guard import SINGLE_BODY_BYTES

    padded = b'{"object_id": "x", "pose": [' + b" " * SINGLE_BODY_BYTES + b"]}"
    response = client.post("/plan", content=padded, headers=JSON)
    assert response.status_code == 413 and f"at most {SINGLE_BODY_BYTES}" in response.json()["detail"]
    batch = b'{"items": [' + b" " * SINGLE_BODY_BYTES + b"]}"
    assert client.post("/batch/plan", content=batch, headers=JSON).status_code == 200


@pytest.mark.parametrize("path", ["/plan", "/batch/plan"])
def test_oversized_bodies_are_413_before_parsing(dataset, path):
    with TestClient(create_app(dataset, settings=Settings(max_body_bytes=4096))) as c:
        big = b'{"items": [' + b"1," * 4000 + b"1]}"
        response = c.post(path, content=big, headers=JSON)
        assert response.status_code == 413 and "at most 4096" in response.json()["detail"]

        def chunks():  # no content-length: counted while read
            yield big[:3000]
            yield big[3000:]

        response = c.post(path, content=chunks(), headers=JSON)
        assert response.status_code == 413 and "over 4096 bytes" in response.json()["detail"]


def test_a_bearer_token_guards_everything_but_health(dataset):
    with TestClient(create_app(dataset, settings=Settings(token=TOKEN))) as c:
        assert c.get("/health").status_code == 200
        for path in ("/objects", "/metrics", "/openapi.json", "/docs"):
            missing = c.get(path)
            assert missing.status_code == 401 and missing.headers["www-authenticate"] == "Bearer"
            assert c.get(path, headers={"authorization": "Bearer wrong-token-of-some-length"}).status_code == 401
            assert c.get(path, headers={"authorization": f"Bearer {TOKEN}"}).status_code == 200
            # RFC 7235: the scheme's name is case-insensitive; the token and the scheme are not optional.
            assert c.get(path, headers={"authorization": f"bearer {TOKEN}"}).status_code == 200
            for wrong in (f"Basic {TOKEN}", TOKEN, f"Bearer{TOKEN}", f"Bearer {TOKEN}x", "Bearer "):
                assert c.get(path, headers={"authorization": wrong}).status_code == 401, wrong
        assert c.post("/plan", json={}).status_code == 401  # before the body is looked at
        schema = c.get("/openapi.json", headers={"authorization": f"Bearer {TOKEN}"}).json()
        assert "401" in schema["paths"]["/plan"]["post"]["responses"] and "401" not in schema["paths"]["/health"]["get"]["responses"]
    with pytest.raises(ValueError, match="at least 16 characters"):
        Settings(token="short").check()
    for bad in (-1.0, float("inf"), float("nan")):  # TOPPLEDB_WATCH_SECONDS as --watch-seconds
        with pytest.raises(ValueError, match="watch_seconds"):
            Settings(watch_seconds=bad).check()


# --- operations: health, metrics, docs, examples -------------------------------------------


def test_health_names_the_build(client, dataset, tables):
    body = client.get("/health").json()
    identity = body["dataset"]
    assert identity["manifest_sha256"] == hashlib.sha256((dataset / "manifest.json").read_bytes()).hexdigest()
    assert identity["created"] == tables["manifest"]["created"]
    parameters = copy.deepcopy(tables["manifest"]["parameters"])
    assert tables["manifest"]["parameter_files"], "the default model names its boosted map's file"
    for name, digest in tables["manifest"]["parameter_files"].items():  # the file's content, not its name
        section, key = name.split(".")
        parameters[section][key] = f"sha256:{digest}"
    canonical = json.dumps(parameters, sort_keys=True, separators=(",", ":")).encode()
    assert identity["parameters_sha256"] == hashlib.sha256(canonical).hexdigest()
    code = tables["manifest"]["code_version"]
    assert identity["code_version"] == code["package"] + (f"+g{code['git_commit'][:12]}" if code["git_commit"] else "")
    assert datetime.datetime.fromisoformat(identity["loaded_at"]).utcoffset() == datetime.timedelta(0)


@pytest.mark.parametrize("commit,version", [(None, "0.1.0"), ("0123456789abcdef0123", "0.1.0+g0123456789ab")])
def test_the_code_version_names_the_builds_commit_when_it_had_one(dataset, tmp_path, commit, version):
    copy = edited(dataset, tmp_path, lambda manifest: manifest["code_version"].update(package="0.1.0", git_commit=commit))
    assert Store.load(copy).code_version == version


def test_an_object_whose_build_failed_is_404_saying_so(dataset, tmp_path):
    failure = {"object_id": "random_009", "path": "random_urdfs/009/009.obj", "reason": "mesh is not watertight", "kind": "mesh"}
    copy = edited(dataset, tmp_path, lambda manifest: manifest["failures"].append(failure))
    with TestClient(create_app(copy)) as c:
        response = c.get("/objects/random_009/poses/0")
        listing = c.get("/objects").json()
    assert listing["count"] == 3 and [o["object_id"] for o in listing["objects"]] == OBJECTS, "a failed object is not listed"
    assert response.status_code == 404
    assert response.json()["detail"] == "object 'random_009' is not in the dataset: its build failed (mesh is not watertight)"


def test_metrics_count_requests_per_route_in_prometheus_format(client):
    def count(text: str, route: str, status: str) -> float:
        match = re.search(rf'toppledb_requests_total\{{method="GET",route="{re.escape(route)}",status="{status}"\}} (\S+)', text)
        return float(match.group(1)) if match else 0.0

    before = client.get("/metrics").text
    for _ in range(3):
        client.get("/objects/nothing-here")
    after = client.get("/metrics")
    assert after.headers["content-type"].startswith("text/plain")
    assert count(after.text, "/objects/{object_id}", "404") - count(before, "/objects/{object_id}", "404") == 3
    assert 'toppledb_request_seconds_bucket{le="0.001",method="GET",route="/objects/{object_id}"}' in after.text


def test_docs_and_redoc_load_nothing_from_the_internet(client):
    for page in ("/docs", "/redoc"):
        html = client.get(page).text
        assert re.findall(r"https?://", html) == [], page
        for asset in re.findall(r'(?:src|href)="([^"]+)"', html):
            if asset.startswith("/"):
                assert client.get(asset).status_code == 200, asset


def test_openapi_examples_come_from_the_served_dataset(client, tables):
    schema = client.get("/openapi.json").json()
    example = schema["components"]["schemas"]["PlanRequest"]["examples"][0]
    assert example["object_id"] in {o for o, _ in tables["poses"]}
    response = client.post("/plan", json=example)
    assert response.status_code == 200 and response.json()["decision"] == "push"
    batch = schema["components"]["schemas"]["PlanBatch"]["examples"][0]
    assert client.post("/batch/plan", json=batch).json()["results"][0]["result"] == response.json()
    transitions = schema["components"]["schemas"]["TransitionBatch"]["examples"][0]
    assert client.post("/batch/transitions", json=transitions).json()["results"][0]["error"] is None
    # The first pose value iteration pushes from, of the first object with one (corpus order is the ids' order
    # here): the plan and the lookup agree.
    assert OBJECTS == sorted(OBJECTS)
    first = pushing_poses(tables)[0][:2]
    assert (example["object_id"], response.json()["match"]["pose"]) == first
    assert (transitions["items"][0]["object_id"], transitions["items"][0]["pose"]) == first


def test_without_a_pushing_pose_the_examples_are_the_first_objects_first_pose(dataset):
    store = Store.load(dataset)
    for obj in store.objects.values():
        obj.policy_action = {**obj.policy_action, "value_iteration": np.full(obj.n_poses, NO_OP)}
    object_id, pose, transform = store.example_object()
    first = next(iter(store.objects.values()))
    assert (object_id, pose) == (first.object_id, 0)
    np.testing.assert_array_equal(transform, first.transforms[0])


def test_a_client_that_leaves_before_its_body_arrives_is_not_counted_as_a_server_error():
    """The guard sends nothing when the connection drops mid-body (or the request timeout closes
    it); /metrics counts such a request as 499, not as the 500 an alert on server errors watches."""
    from service.guard import CLIENT_CLOSED, Guard
    from service.metrics import Metrics

    async def app(scope, receive, send):  # never reached: the body never arrived
        raise AssertionError("the route must not run")

    metrics = Metrics()
    guard = Guard(app, metrics, token=None, max_body_bytes=4096)
    scope = {"type": "http", "method": "POST", "path": "/plan", "headers": [(b"content-type", b"application/json"),
                                                                           (b"content-length", b"50")]}
    sent = call(guard, scope, {"type": "http.request", "body": b"{}", "more_body": True})  # then the client leaves
    text = metrics.render().decode()
    assert not sent
    assert f'status="{CLIENT_CLOSED}"' in text and 'status="500"' not in text


def test_an_object_lifted_by_exactly_the_height_tolerance_rests_on_the_table(client, tables):
    # Its height comes out of a matrix product, a few ulps either side of the lift; the edge is inside.
    codes, crossed = {}, 0
    for object_id, pose, _ in pushing_poses(tables)[:12]:
        for lift in (HEIGHT_TOLERANCE, -HEIGHT_TOLERANCE):
            response = post_plan(client, object_id, observe(tables, object_id, pose, lift=lift))
            codes[object_id, pose, lift] = response.status_code
            crossed += abs(response.json()["match"]["z_offset"]) > HEIGHT_TOLERANCE if response.status_code == 200 else 1
        for beyond in (HEIGHT_TOLERANCE + 1e-6, -HEIGHT_TOLERANCE - 1e-6):
            off = post_plan(client, object_id, observe(tables, object_id, pose, lift=beyond))
            assert off.status_code == 409 and off.json()["reason"] == "off_table", "a micrometre further is off"
            words = f"is observed 5.0010 mm {'above' if beyond > 0 else 'below'} the table"
            assert words in off.json()["detail"] and "tolerance 5.0 mm" in off.json()["detail"], "not '5.0 mm', as the tolerance"
    assert set(codes.values()) == {200}, {k: v for k, v in codes.items() if v != 200}
    assert crossed > 0, "some observation rounds past the edge, or this would not test it"


def test_the_edge_of_the_table_is_inside_and_a_nan_height_is_not():
    from schema.api import HEIGHT_ROUNDING, rests_on_table

    assert rests_on_table(0.005, 0.005) and rests_on_table(-0.005, 0.005) and rests_on_table(0.0, 0.0)
    assert rests_on_table(0.005 + HEIGHT_ROUNDING / 2, 0.005), "a few ulps past the edge"
    assert not rests_on_table(0.005 + 2 * HEIGHT_ROUNDING, 0.005) and not rests_on_table(-0.005 - 2e-9, 0.005)
    assert not rests_on_table(float("nan"), 0.005) and not rests_on_table(float("inf"), 0.005)
    from schema.api import height_in_mm

    assert height_in_mm(0.25, 0.1) == "250.0" and height_in_mm(-0.0125, 0.005) == "12.5"
    assert height_in_mm(0.005001, 0.005) == "5.0010" and height_in_mm(-0.00504, 0.005) == "5.0400", "not the tolerance's 5.0"
    assert height_in_mm(0.0051, 0.005) == "5.1"
    assert height_in_mm(1e308, 0.005) == "1e+311" and height_in_mm(-2.5e6, 0.005) == "2.5e+9", "not inf mm"


# --- the guard alone: its refusals' words, what it hands on, what it counts ------------------


def through_guard(path="/plan", method="POST", headers=(), messages=(), token=None, max_body_bytes=4096, root_path=None,
                  app=None, metrics=None):
    """One request through a ``Guard`` in front of ``app``, by default one that records what reached it and
    answers 200 ``{}``. Returns (the messages sent, what reached the default app: its scope and the first two
    messages it received (None after a disconnect), or None, the metrics)."""
    from service.guard import Guard, json_messages
    from service.metrics import Metrics

    reached = []

    async def recorder(scope, receive, send):
        first = await receive()
        reached.append((scope, first, None if first["type"] == "http.disconnect" else await receive()))
        for message in json_messages(200, {}):
            await send(message)

    app = app or recorder
    metrics = metrics or Metrics()
    scope = {"type": "http", "method": method, "path": path, "headers": list(headers)}
    if root_path is not None:
        scope["root_path"] = root_path
    sent = call(Guard(app, metrics, token=token, max_body_bytes=max_body_bytes), scope, *messages)
    return sent, (reached[0] if reached else None), metrics


def refusal(sent) -> tuple[int, dict, dict]:
    """The status, headers and JSON body of the error the guard sent (``sent``, two ASGI messages)."""
    start, body = sent
    assert start["type"] == "http.response.start" and body["type"] == "http.response.body"
    headers = dict(start["headers"])
    assert headers[b"content-type"] == b"application/json" and int(headers[b"content-length"]) == len(body["body"])
    return start["status"], headers, json.loads(body["body"])


BODY = {"type": "http.request", "body": b"{}", "more_body": False}
JSON_TYPE = (b"content-type", b"application/json")


def test_the_guards_401_says_whether_the_token_was_missing_or_wrong():
    hint = "send 'Authorization: Bearer <token>'"
    for given, why in ((None, "missing bearer token"), (b"Bearer " + b"x" * 22, "wrong bearer token"),
                       (TOKEN.encode(), "wrong bearer token"), (b"", "missing bearer token")):
        headers = [JSON_TYPE] + ([] if given is None else [(b"authorization", given)])
        sent, reached, _ = through_guard(headers=headers, messages=[BODY], token=TOKEN)
        status, sent_headers, body = refusal(sent)
        assert (status, body) == (401, {"detail": f"{why}: {hint}"}) and reached is None
        assert sent_headers[b"www-authenticate"] == b"Bearer"
    # The token's own surrounding spaces are not part of it; /health, also behind a root path, needs none.
    sent, reached, _ = through_guard(headers=[JSON_TYPE, (b"authorization", b"BEARER  " + TOKEN.encode() + b" ")],
                                     messages=[BODY], token=TOKEN)
    assert sent[0]["status"] == 200 and reached is not None
    for path, root in (("/health", None), ("/api/health", "/api")):
        sent, reached, _ = through_guard(path, "GET", token=TOKEN, root_path=root)
        assert sent[0]["status"] == 200 and reached is not None


def test_the_guards_413_names_the_declared_length_and_the_limit():
    for path, limit, maximum in (("/plan", 4096, 4096), ("/plan", 64 * 1024, 10**6), ("/batch/plan", 10**6, 10**6)):
        for declared, shown in ((str(limit + 1).encode(), str(limit + 1)), (b"12x", "12x"), (b"-1", "-1"),
                                (b"9" * 30, "9" * 20)):
            sent, reached, _ = through_guard(path, headers=[JSON_TYPE, (b"content-length", declared)], messages=[BODY],
                                             max_body_bytes=maximum)
            status, headers, body = refusal(sent)
            assert (status, body) == (413, {"detail": f"request body of {shown} bytes; at most {limit}"}), (path, declared)
            assert headers[b"connection"] == b"close" and reached is None
        # Exactly the limit is within it.
        sent, reached, _ = through_guard(path, headers=[JSON_TYPE, (b"content-length", str(limit).encode())],
                                         messages=[BODY], max_body_bytes=maximum)
        assert sent[0]["status"] == 200 and reached is not None


def test_a_chunked_body_is_handed_on_whole_and_refused_only_past_the_limit():
    half = b" " * 2048
    chunks = [{"type": "http.request", "body": half, "more_body": True},
              {"type": "http.request", "body": half, "more_body": True},
              {"type": "http.request", "body": b"", "more_body": False}]
    sent, reached, _ = through_guard(headers=[JSON_TYPE], messages=chunks)
    assert sent[0]["status"] == 200
    _, first, second = reached
    # One message with the whole body, then what the client sends next (here it leaves).
    assert first == {"type": "http.request", "body": half * 2, "more_body": False}
    assert second == {"type": "http.disconnect"}
    over = [*chunks[:2], {"type": "http.request", "body": b" ", "more_body": False}]
    sent, reached, _ = through_guard(headers=[JSON_TYPE], messages=over)
    status, headers, body = refusal(sent)
    assert (status, body) == (413, {"detail": "request body over 4096 bytes"}) and headers[b"connection"] == b"close"
    assert reached is None
    # A last message without "more_body" ends the body, and one without "body" adds none (ASGI's defaults).
    sent, reached, _ = through_guard(headers=[JSON_TYPE], messages=[{"type": "http.request", "body": b"{}"}])
    assert sent[0]["status"] == 200 and reached[1]["body"] == b"{}"
    sent, reached, _ = through_guard(headers=[JSON_TYPE], messages=[{"type": "http.request", "body": b"{", "more_body": True},
                                                                    {"type": "http.request"}])
    assert sent[0]["status"] == 200 and reached[1] == {"type": "http.request", "body": b"{", "more_body": False}


def test_the_guards_415_shows_the_content_types_given():
    hint = "send the body as application/json"
    for types, shown in (([], "none"), ([b"text/plain"], "text/plain"),
                         ([b"text/plain", b"application/json"], "text/plain, application/json"),
                         ([b"text/" + b"x" * 100], "text/" + "x" * 55)):
        sent, reached, _ = through_guard(headers=[(b"content-type", t) for t in types], messages=[BODY])
        assert refusal(sent)[::2] == (415, {"detail": f"content-type {shown!r}: {hint}"}) and reached is None


def test_json_media_types_and_what_the_guard_calls_utf16():
    from service.guard import is_json, not_utf8

    for media in (b"application/json", b"Application/JSON", b"application/json; charset=utf-8", b" application/json ",
                  b"application/problem+json", b"application/vnd.toppledb+JSON;v=1", b"application/json; charset=utf-8; v=1"):
        assert is_json(media), media
    for media in (b"text/json", b"application/jsonx", b"application/json-seq", b"text/x+json", b"application/xml",
                  b"", b"json"):
        assert not is_json(media), media
    for body in ('{"a": 1}'.encode("utf-16-le"), '{"a": 1}'.encode("utf-16-be"), b"\xff\xfe", b"\xfe\xff", b"\xff\xfe{}",
                 b"{\x00", b"  \x00{", b"\x00"):
        assert not_utf8(body), body
    # Only the first two bytes are a byte-order mark; only the first four could hold UTF-16's or UTF-32's NUL.
    for body in (b"", b"{}", b'{"a": "\xc3\xa9"}', b'    {"a": "\\u0000"}', b"\xef\xbb\xbf{}", b"{\xff\xfe}", b'{"a"\x00}'):
        assert not not_utf8(body), body


def test_a_utf16_body_is_a_located_json_decode_error():
    body = {"type": "http.request", "body": '{"a": 1}'.encode("utf-16"), "more_body": False}
    sent, reached, _ = through_guard(headers=[JSON_TYPE], messages=[body])
    status, _, answer = refusal(sent)
    message = "JSON decode error: the body is UTF-16 or UTF-32; send UTF-8"
    assert (status, answer) == (422, {"detail": f"body: {message}", "errors": [{"loc": ["body"], "msg": message,
                                                                                  "type": "json_invalid"}]})
    assert reached is None


def test_route_paths_behind_a_root_path():
    from service.guard import route_path

    for path, root, route in (("/plan", None, "/plan"), ("/plan", "", "/plan"), ("/api/plan", "/api", "/plan"),
                              ("/api", "/api", "/"), ("/plan", "/api", "/plan"), ("/api/health", "", "/api/health")):
        scope = {"path": path} if root is None else {"path": path, "root_path": root}
        assert route_path(scope) == route, (path, root)


def test_what_the_guard_hands_on_unread():
    # Methods without a body, a PUT within the limit and a POST to a path without a body route reach the app
    # with their messages as sent; a lifespan scope passes through untouched.
    for method, path in (("GET", "/objects"), ("PUT", "/plan"), ("POST", "/objects"), ("POST", "/nowhere"),
                         ("DELETE", "/plan")):
        sent, reached, _ = through_guard(path, method, headers=[(b"content-type", b"text/plain")], messages=[BODY])
        scope, first, second = reached
        assert sent[0]["status"] == 200 and scope["method"] == method and (first, second) == (BODY, {"type": "http.disconnect"})
    from service.guard import Guard
    from service.metrics import Metrics

    seen = []

    async def app(scope, receive, send):
        seen.append((scope, await receive()))

    lifespan = {"type": "lifespan"}
    assert call(Guard(app, Metrics(), token=TOKEN, max_body_bytes=1), lifespan, {"type": "lifespan.startup"}) == []
    assert seen == [(lifespan, {"type": "lifespan.startup"})]


def test_head_is_answered_as_get_only_on_health_and_counted_as_head():
    for path, root, method in (("/health", None, "GET"), ("/api/health", "/api", "GET"), ("/objects", None, "HEAD"),
                               ("/health/x", None, "HEAD")):
        _, (scope, _, _), metrics = through_guard(path, "HEAD", root_path=root)
        assert scope["method"] == method, path
        text = metrics.render().decode()
        assert 'toppledb_requests_total{method="HEAD",route="unmatched",status="200"} 1.0' in text
        # The time from the request to the end of its answer: well under a second here.
        seconds = float(re.search(r'toppledb_request_seconds_sum\{method="HEAD",route="unmatched"\} (\S+)', text).group(1))
        assert 0 < seconds < 1


def test_the_build_header_joins_the_apps_own_headers_and_an_exception_is_counted_as_500():
    from service.guard import BUILD_HEADER, BUILD_SCOPE_KEY, requested_build
    from service.metrics import Metrics

    async def app(scope, receive, send):
        scope[BUILD_SCOPE_KEY] = "ab" * 32
        await send({"type": "http.response.start", "status": 200, "headers": [(b"x-own", b"1")]})
        await send({"type": "http.response.body", "body": b""})

    sent, _, _ = through_guard("/x", "GET", app=app)
    assert sent[0]["headers"] == [(b"x-own", b"1"), (BUILD_HEADER, b"ab" * 32)]

    async def bare(scope, receive, send):  # a start message without headers
        scope[BUILD_SCOPE_KEY] = "cd" * 32
        await send({"type": "http.response.start", "status": 204})

    sent, _, _ = through_guard("/x", "GET", app=bare)
    assert sent == [{"type": "http.response.start", "status": 204, "headers": [(BUILD_HEADER, b"cd" * 32)]}]

    async def broken(scope, receive, send):
        scope["route"] = SimpleNamespace(path="/objects/{object_id}")
        raise RuntimeError("a bug")

    metrics = Metrics()
    with pytest.raises(RuntimeError, match="a bug"):
        through_guard("/objects/a", "GET", app=broken, metrics=metrics)
    assert 'toppledb_requests_total{method="GET",route="/objects/{object_id}",status="500"} 1.0' in metrics.render().decode()
    # The build a request names: its first such header, read as FastAPI reads it (latin-1).
    scope = {"headers": [(b"accept", b"*/*"), (BUILD_HEADER, b"caf\xe9"), (BUILD_HEADER, b"second")]}
    assert requested_build(scope) == "caf\u00e9" and requested_build({"headers": [(b"accept", b"*/*")]}) is None
