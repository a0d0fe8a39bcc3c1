"""Planning from an observed pose: match it to a stable pose, check that the object rests
on the table, look up the policy's action, and place the push and the grasp in the world.

Frames: the observed pose ``O`` (object -> world) is ``pose_to_world @ T_p`` where ``T_p``
(object -> pose frame) is stable pose p's transform, so ``pose_to_world = O @ T_p^-1``.
A symmetric object's pose has several such transforms (its merged turns, the served
``matches``); the nearest one is ``T_p`` here, so a can lying at any roll gets its push.
For an exact observation that is ``planar`` (a yaw about z and an x, y translation,
``schema.frames.match_pose``); a real one adds a small tilt (within the pose tolerance)
and a small height (within ``height_tolerance``).  Pushes and grasps are mapped through
``pose_to_world`` itself, so they lie on the object's surface as observed: mapping through
``planar`` alone would leave a tilted object's contact point millimetres off its surface.

The answer is a plain dict with the fields of ``schema.api.PlanResponse`` in its order,
serialised by orjson (``answer_json``): every value is a Python int, float, str, bool,
None or list made here from the validated request and the loaded store.  Building the
pydantic models, even with ``model_construct``, cost as much as the planning itself.
tests/test_service_fastplan.py holds the dicts to the models (same fields, same bytes as
``PlanResponse.model_validate(answer).model_dump_json()``); tests/test_service_fuzz.py checks
the served answers against the OpenAPI schema.

Imports numpy and schema only (the service never loads the geometry stack).
"""

from __future__ import annotations

import numpy as np
import orjson

from schema import horizon, retry
from schema.api import PlanRequest, height_in_mm, quaternion_matrix, rests_on_table
from schema.frames import PoseMatch, match_pose, place_push
from schema.vocabulary import NO_OP, STATUS_OK

from .errors import NoStablePose, OffTable, UnknownAction, UnknownFrame
from .settings import Settings
from .store import ObjectData, Store, optional, widen


def next_poses(obj: ObjectData, row: int) -> list[dict]:
    """``NextPose`` fields of one action row's next-pose distribution."""
    poses, probabilities = obj.transitions(row)
    return [{"next_pose": p, "probability": q} for p, q in zip(poses.tolist(), probabilities.tolist())]


def world_grasp(obj: ObjectData, pose: int, pose_to_world: np.ndarray) -> dict | None:
    """``Grasp`` fields of the pose's best grasp mapped to the world; None when it has none (NaN)."""
    point, axis = obj.grasp_point[pose], obj.grasp_axis[pose]
    if np.isnan(point).any() or np.isnan(axis).any():
        return None
    rotation = pose_to_world[:3, :3]
    return {"point": (rotation @ point + pose_to_world[:3, 3]).tolist(), "axis": (rotation @ axis).tolist()}


def answer_json(answer: dict) -> bytes:
    """A plan's JSON bytes (what POST /plan sends)."""
    return orjson.dumps(answer)


def observed_pose(request: PlanRequest, settings: Settings) -> np.ndarray:
    """(4, 4) object -> world from the request; UnknownFrame for a ROS pose in another frame."""
    if request.ros_pose is not None and request.ros_pose.frame_id != settings.frame_id:
        raise UnknownFrame(
            f"ros_pose.frame_id is '{request.ros_pose.frame_id}', but this service plans in '{settings.frame_id}' "
            "(z up, table at z = 0); transform the pose into it first (e.g. tf2)"
        )
    return request.observed()


W_FIRST_MATCH = 0.25
"""The share of the pose tolerance within which a refused ROS quaternion read w first must match a pose for the
refusal to name it.  A quaternion really sent w first reads, so, at the perception error; a tilted object's
quaternion read w first lands anywhere within the tolerance, and a quarter of it names few of those."""


def nearest_pose(obj: ObjectData, observed: np.ndarray) -> tuple[PoseMatch, np.ndarray]:
    """The stable pose nearest an observed object -> world transform (at any angle: a 409 names it), and
    that pose's frame in the world, (4, 4) pose -> world: its z translation is the support point's height."""
    match = match_pose(observed, obj.match_downs, obj.match_transforms, np.inf, obj.match_inverses)
    return match, observed @ obj.match_inverses[match.pose]


def w_first_hint(request: PlanRequest, obj: ObjectData, tolerance: float, height_tolerance: float) -> str:
    """For a ROS pose refused as no stable pose or off the table: a sentence naming the pose its quaternion
    gives read w first, if that reading rests on the table in a stable pose (within ``W_FIRST_MATCH`` of the
    tolerance), else "".  Eigen's ``Quaterniond(w, x, y, z)`` constructor, transforms3d and pyquaternion
    order a quaternion w first, geometry_msgs x, y, z, w; sent in the wrong order it reads as another
    rotation.  When that rotation also rests in a pose the service cannot tell, so only a refusal says so."""
    if request.ros_pose is None:
        return ""
    q = request.ros_pose.orientation
    observed = request.observed()
    observed[:3, :3] = quaternion_matrix(q.y, q.z, q.w, q.x)  # the fields x, y, z, w read as w, x, y, z
    match, pose_to_world = nearest_pose(obj, observed)
    if match.angle_error > W_FIRST_MATCH * tolerance or not rests_on_table(float(pose_to_world[2, 3]), height_tolerance):
        return ""
    return (" If the quaternion came from a library that orders it w, x, y, z (Eigen's Quaterniond constructor, "
            f"transforms3d, pyquaternion): read so, it is pose {int(obj.match_pose[match.pose])}, "
            f"{np.degrees(match.angle_error):.1f} deg away and on the table; geometry_msgs orders it x, y, z, w")


def untried_push(obj: ObjectData, pose: int, request: PlanRequest, gamma: float,
                 power: float | None = None, retry_failed: bool = True, *,
                 believes: bool = False) -> tuple[int, float | None, int]:
    """The policy's push among the candidates of ``pose`` that the request's failed pushes do
    not rule out (``schema.retry``), by the rule the dataset's policy or the budget uses.
    Value iteration (no budget) ranks them by what it believes of them now: Q1 of a build
    that believes failures (``believes``, ``retry.failed_state_values``, docs/MODEL.md (12.13)),
    else ``retry.believed_values`` with k = ``power`` (12.12); the table's Q when None or 1 and
    with nothing failed.  A budget ranks them by ``ObjectData.budget_q``: Q1_h of (12.14) in a
    build that believes failures once one has failed.

    returns : action (NO_OP: grasp now), with ``pushes_left`` what the budget ranked the push by
      (V_h of (12.8), or Q1_h of (12.14) after a failure in a build that believes failures; else None), the
      number of candidates the policy could choose that are ruled out.  UnknownAction for a
      failed index the pose does not have, or of a push that is not ok: /plan never serves one,
      so it is a client's mistake, and it would silently rule out the ok pushes around it.
    """
    rows = obj.pose_rows(pose)
    count = rows.stop - rows.start
    impossible = retry.impossible_failure(request.failed_actions, obj.status[rows] == STATUS_OK)
    if impossible is not None:
        index, action, exists = impossible
        if not exists:
            raise UnknownAction(f"pose {pose} of '{obj.object_id}' has no action {action}: its actions are 0..{count - 1}", index)
        raise UnknownAction(f"action {action} of pose {pose} of '{obj.object_id}' is {obj.status_name(rows.start + action)}, "
                            "not ok: /plan never serves it, so it cannot have failed", index)
    choosable = obj.budget_choosable(rows) if request.pushes_left is not None else obj.choosable(rows)
    stay = float(obj.v_s[pose])
    if request.pushes_left is not None:
        values = obj.budget_q(pose, request.pushes_left, after_failure=bool(request.failed_actions))
        improvement, scale = horizon.IMPROVEMENT, 1.0
    elif request.policy == "greedy":
        values, improvement, scale = obj.greedy[rows], retry.POLICY_IMPROVEMENT, 1.0
    else:
        believed = power if request.failed_actions else None  # nothing failed: the table's own choice
        values = retry.ranking_values(np.asarray(obj.q[rows], dtype=float), widen(obj.p_topple[rows]), stay, float(obj.v_t[pose]),
                                      believed, retry_failed, believes=believes, gamma=gamma, choosable=choosable)
        improvement, scale = retry.POLICY_IMPROVEMENT, gamma
    action, ruled = retry.choose_untried(values, obj.points[rows], obj.directions[rows], request.failed_actions, choosable,
                                         stay, improvement, scale)
    final = float(values[action]) if request.pushes_left is not None and action != NO_OP else None
    return action, final, ruled


def plan(store: Store, request: PlanRequest, settings: Settings) -> dict:
    """The policy's decision for an object observed at the request's pose.

    NotFound (unknown object), NoStablePose (orientation within tolerance of no stable pose),
    OffTable (|z_offset| > settings.height_tolerance), UnknownFrame (ROS pose in another frame),
    UnknownAction (a failed action the matched pose does not have).
    """
    obj = store.object(request.object_id)
    observed = observed_pose(request, settings)
    # Every orientation that is a pose (a symmetric object's merged turns too); an infinite
    # tolerance always names the nearest, which the 409 message reports.
    match, pose_to_world = nearest_pose(obj, observed)
    pose = int(obj.match_pose[match.pose])
    if match.angle_error > store.tolerance:
        raise NoStablePose(
            f"the observed orientation of '{obj.object_id}' is no stable pose: the nearest, pose {pose}, "
            f"is {np.degrees(match.angle_error):.1f} deg away (tolerance {np.degrees(store.tolerance):.1f} deg); "
            "is the object resting on the table, and is the world frame z up?"
            f"{w_first_hint(request, obj, store.tolerance, settings.height_tolerance)}",
            object_id=obj.object_id,
            nearest_pose=pose,
            angle_error=match.angle_error,
            tolerance=store.tolerance,
        )
    z_offset = float(pose_to_world[2, 3])
    if not rests_on_table(z_offset, settings.height_tolerance):
        raise OffTable(
            f"'{obj.object_id}' is observed {height_in_mm(z_offset, settings.height_tolerance)} mm "
            f"{'above' if z_offset > 0 else 'below'} the table "
            f"(pose {pose}'s support point at z = {z_offset:.4g} m, tolerance {settings.height_tolerance * 1000:.1f} mm): "
            "it is not resting on the table z = 0, so no stored push applies; is the world frame's origin on the table?"
            f"{w_first_hint(request, obj, store.tolerance, settings.height_tolerance)}",
            object_id=obj.object_id,
            pose=pose,
            z_offset=z_offset,
            height_tolerance=settings.height_tolerance,
        )

    grasp = world_grasp(obj, pose, pose_to_world)
    v_s = float(obj.v_s[pose])
    ruled = 0
    if request.failed_actions:
        action, final, ruled = untried_push(obj, pose, request, store.gamma, store.after_failure_power, store.retry_failed,
                                            believes=store.believe_failures)
        near = np.nan if action == NO_OP else obj.neighbourhood_p(pose, action)
    elif request.pushes_left is None:
        action = int(obj.policy_action[request.policy][pose])
        near, final = obj.policy_p_topple_neighbourhood[request.policy][pose], None
    else:
        actions, finals = obj.budget(request.pushes_left)
        action = int(actions[pose])
        near = np.nan if action == NO_OP else obj.neighbourhood_p(pose, action)
        final = None if action == NO_OP else float(finals[pose])
    push = p_topple = p_near = p_given = q_value = after = None
    outcomes: list[dict] = []
    if action != NO_OP:
        row = obj.row(pose, action)
        # One widen for all float32 values of the row: (3, 3) pose-frame point, normal, direction, then the scalars.
        values = widen(np.concatenate([obj.points[row], obj.normals[row], obj.directions[row], [obj.mean_force[row], obj.p_topple[row]]]))
        world = place_push(pose_to_world, *values[:9].reshape(3, 3), store.approach_offset, store.push_depth)
        force = optional(values[9])
        limit = store.finger_force_limit(settings.finger_force_limit)
        push = {
            **{name: world[name].tolist() for name in ("point", "normal", "direction", "start", "end")},
            "approach_offset": store.approach_offset,
            "push_depth": store.push_depth,
            "required_force": force,
            "finger_force_limit": limit,
            "within_force_limit": None if force is None else bool(force <= limit),
        }
        p_topple = optional(values[10])
        if request.failed_actions and p_topple is not None:
            p_given = retry.given_failures(p_topple, store.after_failure_power)
        # float32 storage: a mean of stored 0.76s is 0.7639999986; six decimals are all it holds.
        p_near = optional(round(float(near), 6))
        q_value = optional(obj.q[row])
        after = optional(obj.greedy[row])
        outcomes = next_poses(obj, row)

    decision, reason = _decision(request.policy, request.pushes_left, action, v_s, grasp, p_topple, p_near, after, push,
                                 len(set(request.failed_actions)), ruled, p_given)
    return {
        "object_id": obj.object_id,
        "policy": request.policy,
        "pushes_left": request.pushes_left,
        "frame_id": settings.frame_id,
        "match": {
            "pose": pose,
            "angle_error": match.angle_error,
            "tolerance": store.tolerance,
            "yaw": match.yaw,
            "translation": match.translation.tolist(),
            "z_offset": z_offset,
            "height_tolerance": settings.height_tolerance,
            "planar": match.planar.tolist(),
            "pose_to_world": pose_to_world.tolist(),
        },
        "decision": decision,
        "reason": reason,
        "action": None if action == NO_OP else action,
        "ruled_out": ruled,
        "v_s": v_s,
        "v_t": float(obj.v_t[pose]),
        "q_value": q_value,
        "expected_v_s_after": after,
        "expected_v_s_final": final,
        "p_topple": p_topple,
        "p_topple_neighbourhood": p_near,
        "p_topple_given_failures": p_given,
        "push": push,
        "next_poses": outcomes,
        "grasp": grasp,
    }


def _decision(policy, pushes_left, action, v_s, grasp, p_topple, p_near, after, push, failed=0, ruled=0,
              p_given=None) -> tuple[str, str]:
    """(decision, one-sentence reason) for the response."""
    if pushes_left is not None:
        policy = f"{policy} ({pushes_left} push{'es' if pushes_left > 1 else ''} left)"
    if failed:
        policy = (f"{policy}, after {failed} failed push{'es' if failed > 1 else ''} "
                  f"({ruled} candidate{'s' if ruled != 1 else ''} ruled out),")
    if action != NO_OP:
        force = ""
        if push is not None and push["within_force_limit"] is False:
            force = (f"; it needs {push['required_force']:.3g} N, more than the finger's limit of "
                     f"{push['finger_force_limit']:.3g} N: do not execute it with this finger")
        given = "" if p_given is None else f", {_g(p_given)} now that pushes here have failed"
        return "push", (f"{policy} pushes: P(topple) {_g(p_topple)} ({_g(p_near)} around it{given}), expected V_s after "
                        f"the push {_g(after)} vs V_s {v_s:.3g} now{force}")
    if grasp is None or v_s <= 0.0:
        untried = "untried " if failed else ""
        return "no_grasp", (f"{policy} does not push and this pose has no suction grasp (V_s = {v_s:.3g}): "
                            f"no {untried}stored push nor grasp helps; pick another object or another tool")
    return "grasp", f"{policy} does not push: grasp now at grasp (V_s = {v_s:.3g})"


def _g(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.3g}"
