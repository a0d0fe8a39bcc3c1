# ruff: noqa: F811  (pytest fixtures imported from tests/test_service.py)
"""POST /heaps/plan on the tiny dataset of tests/test_service.py: the served push is the one
``clutter.policies.plan_push`` plans from the dataset's hulls, it keeps the planner's
invariants in the world frame, the ROS form gives the same answer, and the error contract
holds (404 unknown object, 409 outside the bin or below the floor, 422 malformed, never 500)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from clutter import footprints as fp
from clutter.policies import POLICIES, PushConfig, plan_push
from clutter.state import Bin, HeapState
from schema.api import BIN_TOLERANCE, MAX_SEED, HeapBin, HeapPolicy, RosPose
from tests.test_service import (  # noqa: F401 (fixtures)
    JSON,
    assert_malformed,
    client,
    dataset,
    planar_transform,
    stored_transform,
    tables,
)


@pytest.fixture(scope="module")
def store(client):
    return client.app.state.live.store


def resting(tables, object_id: str, x: float, y: float, yaw: float = 0.0) -> np.ndarray:
    """Object -> world: the object's most probable stable pose, at (x, y) with ``yaw``."""
    pose = max((p for (o, p) in tables["poses"] if o == object_id), key=lambda p: tables["poses"][(object_id, p)]["probability"])
    return planar_transform(yaw, x, y) @ stored_transform(tables, object_id, pose)


def half_width(store, object_id: str, pose: np.ndarray) -> float:
    """m, half the footprint's extent along world x at ``pose``."""
    poly = fp.footprint(store.objects[object_id].hull_vertices, pose)
    return float(poly[:, 0].max() - poly[:, 0].min()) / 2


def side_by_side(store, tables, ids=("random_000", "random_001"), y: float = 0.0, gap: float = 0.002) -> list[dict]:
    """Two objects touching-close along world x, centred on the bin."""
    a, b = (resting(tables, i, 0.0, y) for i in ids)
    wa, wb = half_width(store, ids[0], a), half_width(store, ids[1], b)
    a[0, 3] -= wa + gap / 2
    b[0, 3] += wb + gap / 2
    # Centre each footprint (not its stable pose's origin) at the intended x.
    for obj_id, pose, sign, w in ((ids[0], a, -1, wa), (ids[1], b, 1, wb)):
        poly = fp.footprint(store.objects[obj_id].hull_vertices, pose)
        pose[0, 3] += sign * (gap / 2 + w) - (poly[:, 0].max() + poly[:, 0].min()) / 2
    return [{"object_id": i, "pose": p.tolist()} for i, p in zip(ids, (a, b))]


def library_push(store, objects: list[dict], policy: str, seed: int = 0, bin: Bin = Bin()):  # noqa: B008
    ids = tuple(o["object_id"] for o in objects)
    state = HeapState(bin, ids, np.array([o["pose"] for o in objects], dtype=float))
    return plan_push(policy, state, [store.objects[i].hull_vertices for i in ids],
                     np.array([store.objects[i].center_mass for i in ids]), rng=np.random.default_rng(seed))


def post(client, objects, policy="boundary_shear", **extra):
    return client.post("/heaps/plan", json={"objects": objects, "policy": policy, **extra})


# --- answers ---------------------------------------------------------------------------


def test_the_policy_names_and_bin_defaults_are_the_libraries():
    assert HeapPolicy.__args__ == POLICIES
    assert HeapBin().model_dump() == {k: getattr(Bin(), k) for k in ("length", "width", "height", "wall")}


@pytest.mark.parametrize("policy", POLICIES)
def test_the_served_push_is_the_planners(client, store, tables, policy):
    objects = side_by_side(store, tables) + [{"object_id": "random_002", "pose": resting(tables, "random_002", 0.12, 0.1, 0.5).tolist()}]
    response = post(client, objects, policy, seed=7)
    assert response.status_code == 200, response.text
    body = response.json()
    expected = library_push(store, objects, policy, seed=7)
    assert body["policy"] == policy and body["frame_id"] == "world" and body["found"] == (expected is not None)
    if expected is None:
        assert body["push"] is None and "no collision-free push" in body["reason"]
        return
    push = body["push"]
    assert push["target"] == expected.target and push["object_id"] == objects[expected.target]["object_id"]
    np.testing.assert_allclose(push["start"], expected.start, atol=1e-12)
    np.testing.assert_allclose(push["end"], expected.end, atol=1e-12)
    assert push["length"] == pytest.approx(expected.length)
    np.testing.assert_allclose(np.array(push["direction"]) * push["length"], np.subtract(push["end"], push["start"]), atol=1e-12)
    assert f"objects[{push['target']}]" in body["reason"]
    # In the world: inside the bin a finger radius from the walls, starting clear of every object.
    config = PushConfig()
    for point in (push["start"], push["end"]):
        assert np.all(np.abs(point[:2]) <= Bin().half_extents - config.finger_radius + 1e-9)
    polygons = fp.pad_polygons([fp.footprint(store.objects[o["object_id"]].hull_vertices, np.array(o["pose"])) for o in objects])
    assert fp.point_polygon_distance(np.array(push["start"][:2])[None], polygons).min() >= config.finger_radius - 1e-9
    assert body["finger_radius"] == config.finger_radius and body["push_length"] == config.push_length


def test_boundary_shear_pushes_along_the_boundary_of_two_objects_side_by_side(client, store, tables):
    body = post(client, side_by_side(store, tables, y=-0.08)).json()
    assert body["found"], body["reason"]
    # The line between the two centres of mass runs along x (the footprints are centred on one line,
    # the centres of mass nearly so): the push runs across it, towards the bin's middle.
    assert abs(body["push"]["direction"][1]) > 0.95 and body["push"]["direction"][1] > 0


def test_quasi_random_follows_the_seed(client, store, tables):
    objects = side_by_side(store, tables)
    answers = [post(client, objects, "quasi_random", seed=s).json()["push"] for s in (3, 3, 4, 5, 6)]
    assert answers[0] == answers[1]
    assert len({json.dumps(a) for a in answers}) >= 3
    assert post(client, objects, "quasi_random", seed=MAX_SEED).status_code == 200, "the largest seed is served"


def quaternion(rotation: np.ndarray) -> dict:
    """x, y, z, w of a rotation matrix (3, 3)."""
    return dict(zip("xyzw", Rotation.from_matrix(rotation).as_quat().tolist()))


def test_a_ros_pose_gives_the_same_push_as_its_matrix(client, store, tables):
    objects = side_by_side(store, tables)
    matrix = np.array(objects[1]["pose"])
    ros = {"position": dict(zip("xyz", matrix[:3, 3])), "orientation": quaternion(matrix[:3, :3]), "frame_id": "world"}
    np.testing.assert_allclose(RosPose.model_validate(ros).matrix(), matrix, atol=1e-12)
    by_ros = post(client, [objects[0], {"object_id": objects[1]["object_id"], "ros_pose": ros}]).json()
    by_matrix = post(client, objects).json()
    assert by_matrix["found"]
    np.testing.assert_allclose(by_ros["push"]["start"], by_matrix["push"]["start"], atol=1e-9)
    np.testing.assert_allclose(by_ros["push"]["end"], by_matrix["push"]["end"], atol=1e-9)


def test_a_heap_with_no_collision_free_push_says_so(client, store, tables):
    # Eight copies of one object turned about one centre, in a bin 2 mm larger than them: the
    # finger can come down only in the bin's corners, and from there reach no target.
    hull = store.objects["random_001"].hull_vertices
    pose = resting(tables, "random_001", 0.0, 0.0)
    poses = [planar_transform(k * math.pi / 8, 0.0, 0.0) @ pose for k in range(8)]
    points = np.concatenate([fp.footprint(hull, p) for p in poses])
    for p in poses:
        p[:2, 3] -= (points.max(axis=0) + points.min(axis=0)) / 2
    extent = points.max(axis=0) - points.min(axis=0)
    bin = {"length": float(extent[0]) + 0.002, "width": float(extent[1]) + 0.002}
    objects = [{"object_id": "random_001", "pose": p.tolist()} for p in poses]
    for policy in ("boundary_shear", "free_space", "max_clearance", "cluster_diffusion"):
        assert library_push(store, objects, policy, bin=Bin(**bin)) is None
        body = post(client, objects, policy, bin=bin).json()
        assert body["found"] is False and body["push"] is None and "no collision-free push" in body["reason"]


def test_a_pair_policy_on_one_object_says_it_needs_two(client, store, tables):
    objects = [{"object_id": "random_001", "pose": resting(tables, "random_001", 0.0, 0.0).tolist()}]
    for policy in ("boundary_shear", "free_space", "cluster_diffusion"):
        body = post(client, objects, policy).json()
        assert body["found"] is False and "needs" in body["reason"] and "one object" in body["reason"]
    assert post(client, objects, "max_clearance").json()["found"] is True


def test_one_id_may_appear_twice(client, store, tables):
    objects = side_by_side(store, tables, ids=("random_002", "random_002"))
    assert post(client, objects).status_code == 200


# --- errors ------------------------------------------------------------------------------


def test_an_unknown_object_is_404_naming_its_place(client, store, tables):
    objects = side_by_side(store, tables)
    objects[1]["object_id"] = "no_such_object"
    response = post(client, objects)
    assert response.status_code == 404 and response.json()["detail"].startswith("objects[1]: unknown object 'no_such_object'")


@pytest.mark.parametrize("where, reason", [("x", "outside_bin"), ("y", "outside_bin"), ("z", "below_floor")])
def test_an_object_outside_the_bin_or_below_its_floor_is_409(client, store, tables, where, reason):
    objects = side_by_side(store, tables)
    pose = np.array(objects[0]["pose"])
    pose[{"x": 0, "y": 1, "z": 2}[where], 3] += {"x": -0.5, "y": 0.3, "z": -0.02}[where]
    objects[0]["pose"] = pose.tolist()
    response = post(client, objects)
    assert response.status_code == 409, response.text
    body = response.json()
    assert body["reason"] == reason and body["index"] == 0 and body["object_id"] == objects[0]["object_id"]
    assert body["distance"] > BIN_TOLERANCE == body["tolerance"] and "objects[0]" in body["detail"]


def test_within_the_tolerance_an_object_may_touch_a_wall(client, store, tables):
    objects = side_by_side(store, tables)
    pose = np.array(objects[0]["pose"])
    poly = fp.footprint(store.objects[objects[0]["object_id"]].hull_vertices, pose)
    pose[0, 3] += -0.25 - poly[:, 0].min() - 0.8 * BIN_TOLERANCE  # 4 mm past the left wall
    objects[0]["pose"] = pose.tolist()
    assert post(client, objects).status_code == 200


def _eye_with(row: int, col: int, value) -> list:
    matrix = np.eye(4).tolist()
    matrix[row][col] = value
    return matrix


ONE = {"object_id": "random_001", "pose": np.eye(4).tolist()}
MALFORMED = [
    ('{"objects": [{"object_id": "random_001", "pose": [[NaN,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}', "finite number"),
    (json.dumps({"objects": [{"object_id": "random_001", "pose": np.diag([2.0, 1, 1, 1]).tolist()}]}), "not a rotation"),
    (json.dumps({"objects": [{"object_id": "random_001", "pose": _eye_with(3, 2, 0.5)}]}), "last row must be [0, 0, 0, 1]"),
    (json.dumps({"objects": [{"object_id": "random_001", "pose": _eye_with(1, 3, 1e300)}]}), "is beyond 1e+06 m"),
    (json.dumps({"objects": [{"object_id": "random_001"}]}), "body.objects.0: give exactly one of pose"),
    (json.dumps({"objects": [ONE], "policy": "shove"}), "body.policy"),
    (json.dumps({"objects": []}), "body.objects: List should have at least 1 item"),
    (json.dumps({"objects": [ONE] * 101}), "at most 100 items"),
    (json.dumps({"objects": [ONE], "bin": {"length": -0.5}}), "body.bin.length: Input should be greater than 0"),
    (json.dumps({"objects": [ONE], "bin": {"width": 50}}), "body.bin.width: Input should be less than or equal to 5"),
    (json.dumps({"objects": [ONE], "bin": {"depth": 0.2}}), "body.bin.depth: Extra inputs"),
    (json.dumps({"objects": [ONE], "seed": -1}), "body.seed: Input should be greater than or equal to 0"),
    (json.dumps({"objects": [ONE], "seed": MAX_SEED + 1}), f"body.seed: Input should be less than or equal to {MAX_SEED}"),
    (json.dumps({"objects": [ONE], "seed": "7"}), "body.seed: Input should be a valid integer"),
    (json.dumps({"objects": [ONE], "seed": 1.5}), "body.seed"),
    (json.dumps({"objects": [{"object_id": "random_001", "ros_pose": {"position": {"x": 0, "y": 0, "z": 0},
                 "orientation": {"x": 0, "y": 0, "z": 0, "w": 1}, "frame_id": "camera"}}]}),
     "body.objects.0.ros_pose.frame_id: 'camera' is not this service's frame"),
    ("{not json", "JSON decode error"),
]


@pytest.mark.parametrize("body, message", MALFORMED)
def test_malformed_heap_requests_are_422_with_a_message(client, body, message):
    assert_malformed(client, "/heaps/plan", body, message)


def test_openapi_documents_the_heap_planner(client):
    document = client.get("/openapi.json").json()
    operation = document["paths"]["/heaps/plan"]["post"]
    assert {"200", "404", "409", "422"} <= set(operation["responses"])
    # The seed's bound is written as a float: it must be one a float holds exactly, so the document
    # and the service refuse the same seeds (a bound of 2**63 - 1 read back as 2**63).
    maximum = document["components"]["schemas"]["HeapPlanRequest"]["properties"]["seed"]["maximum"]
    assert maximum == MAX_SEED and int(maximum) == MAX_SEED and float(MAX_SEED) == MAX_SEED


# --- the Python API gives the service's push -------------------------------------------------


@pytest.mark.parametrize("policy", ["boundary_shear", "quasi_random"])
def test_plan_heap_from_the_dataset_is_the_services_push(client, dataset, store, tables, policy):
    import pipeline as toppledb

    objects = side_by_side(store, tables) + [{"object_id": "random_002", "pose": resting(tables, "random_002", 0.12, 0.1, 0.5).tolist()}]
    served = post(client, objects, policy, seed=11).json()["push"]
    push = toppledb.plan_heap([o["object_id"] for o in objects], [o["pose"] for o in objects], dataset, policy, seed=11)
    assert push.target == served["target"]
    np.testing.assert_allclose(push.start, served["start"], atol=1e-12)
    np.testing.assert_allclose(push.end, served["end"], atol=1e-12)


def test_plan_heap_refuses_what_the_service_refuses(dataset, store, tables):
    import pipeline as toppledb

    objects = side_by_side(store, tables)
    poses = [np.array(o["pose"]) for o in objects]
    with pytest.raises(ValueError, match="no object 'nothing' in the dataset"):
        toppledb.plan_heap(["random_000", "nothing"], poses, dataset)
    poses[1][2, 3] -= 0.02
    with pytest.raises(ValueError, match=r"object 1 \('random_001'\) reaches .* below the bin's floor"):
        toppledb.plan_heap(["random_000", "random_001"], poses, dataset)
    with pytest.raises(ValueError, match="unknown push policy"):
        toppledb.plan_heap(["random_000"], poses[:1], dataset, "shove")
    for seed in (-1, MAX_SEED + 1, 1.5, True):  # the service's 422s
        with pytest.raises(ValueError, match=f"seed must be an integer from 0 to {MAX_SEED}"):
            toppledb.plan_heap(["random_000"], poses[:1], dataset, "quasi_random", seed=seed)
