"""Planning from an observed pose: match it to a stable pose, look up the policy's
action, and return the push in world coordinates.

Frames: the observed pose ``O`` (object -> world) equals ``planar @ T_p`` where
``T_p`` (object -> pose frame) is stable pose p's transform and ``planar`` (pose ->
world) a yaw about z plus an x, y translation (``schema.frames.match_pose``).  A
pose-frame point x is therefore at ``planar @ [x, 1]`` in the world and a
pose-frame direction d at ``planar[:3, :3] @ d``.
"""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter

from schema.api import (
    ErrorBody,
    ItemError,
    NoMatchBody,
    PlanBatch,
    PlanRequest,
    PlanResponse,
    PlanResult,
    PlanResults,
    PoseMatch,
    ValidationErrorBody,
    WorldPush,
)
from schema.frames import match_pose
from schema.vocabulary import NO_OP

from ..dependencies import StoreDep
from ..errors import NoStablePose, ServiceError
from ..store import Store, optional, widen
from .objects import grasp_model, next_poses

router = APIRouter(tags=["plan"])
batch = APIRouter(prefix="/batch", tags=["batch"])


def plan(store: Store, request: PlanRequest) -> PlanResponse:
    """The policy's push for an object observed at ``request.pose``; NotFound, NoStablePose."""
    obj = store.object(request.object_id)
    observed = np.asarray(request.pose, dtype=np.float64)
    # An infinite tolerance always names the nearest pose, which the 409 message reports.
    match = match_pose(observed, obj.downs, obj.transforms, tolerance=np.inf)
    if match.angle_error > store.tolerance:
        raise NoStablePose(
            f"the observed orientation of '{obj.object_id}' is no stable pose: the nearest, pose {match.pose}, "
            f"is {np.degrees(match.angle_error):.1f} deg away (tolerance {np.degrees(store.tolerance):.1f} deg); "
            "is the object resting on the table, and is the world frame z up?",
            object_id=obj.object_id,
            nearest_pose=match.pose,
            angle_error=match.angle_error,
            tolerance=store.tolerance,
        )
    pose = match.pose
    planar = match.planar
    rotation = planar[:3, :3]
    z_offset = float((observed @ obj.inverse_transforms[pose])[2, 3])

    grasp_point, grasp_axis = obj.grasp_point[pose], obj.grasp_axis[pose]
    grasp = grasp_model(rotation @ grasp_point + planar[:3, 3], rotation @ grasp_axis)

    action = int(obj.policy_action[request.policy][pose])
    push = p_topple = None
    outcomes = []
    if action != NO_OP:
        row = obj.row(pose, action)
        local = widen(np.stack([obj.points[row], obj.normals[row], obj.directions[row]]))  # (3, 3) pose frame
        point = rotation @ local[0] + planar[:3, 3]
        normal = rotation @ local[1]
        direction = rotation @ local[2]
        push = WorldPush(
            point=point.tolist(),
            normal=normal.tolist(),
            direction=direction.tolist(),
            start=(point + store.approach_offset * normal).tolist(),
            end=(point - store.push_depth * normal).tolist(),
            approach_offset=store.approach_offset,
            push_depth=store.push_depth,
        )
        p_topple = optional(widen(obj.p_topple[row]))
        outcomes = next_poses(obj, row)

    return PlanResponse(
        object_id=obj.object_id,
        policy=request.policy,
        match=PoseMatch(
            pose=pose,
            angle_error=match.angle_error,
            tolerance=store.tolerance,
            yaw=match.yaw,
            translation=match.translation.tolist(),
            z_offset=z_offset,
            planar=planar.tolist(),
        ),
        v_s=float(obj.v_s[pose]),
        action=None if action == NO_OP else action,
        expected_value=float(obj.policy_value[request.policy][pose]),
        p_topple=p_topple,
        push=push,
        next_poses=outcomes,
        grasp=grasp,
    )


@router.post(
    "/plan",
    response_model=PlanResponse,
    summary="Which push, where in the world, and what happens next",
    description="Matches the observed pose (object -> world, z up, table z = 0) to a stable pose "
    "(down vectors within the manifest's `poses.same_pose_angle`), looks up the policy's action "
    "and returns the push in world coordinates: contact point, normal, direction and the finger's "
    "line from `point + approach_offset * normal` to `point - push_depth * normal`. "
    "`action` null means: do not push, grasp now (`grasp`, world frame).",
    responses={
        404: {"model": ErrorBody, "description": "Unknown object"},
        409: {"model": NoMatchBody, "description": "The observed orientation is no stable pose"},
        422: {"model": ValidationErrorBody, "description": "Malformed request (NaN, not a rotation, ...)"},
    },
)
async def post_plan(request: PlanRequest, store: StoreDep) -> PlanResponse:
    return plan(store, request)


def _plan_item(store: Store, request: PlanRequest) -> PlanResult:
    try:
        return PlanResult(result=plan(store, request))
    except ServiceError as err:
        return PlanResult(error=ItemError(status=err.status_code, detail=err.detail))


# A plain def: run in a worker thread so that a large batch does not stall the event loop.
@batch.post(
    "/plan",
    response_model=PlanResults,
    summary="Plan for many observed poses at once",
    description="`results[i]` answers `items[i]`: `result` (as POST /plan) or `error` (`status` 404 for "
    "an unknown object, 409 for no matching stable pose, and a `detail`); one such item does not fail "
    "the batch. A malformed body (any item's NaN, non-rotation, unknown policy, ...) or more than "
    "1000 items fails the whole batch with 422.",
    responses={422: {"model": ValidationErrorBody, "description": "Malformed request"}},
)
def batch_plan(body: PlanBatch, store: StoreDep) -> PlanResults:
    return PlanResults(results=[_plan_item(store, item) for item in body.items])
