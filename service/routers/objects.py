"""Objects, their stable poses, candidate pushes, Q-values, and batch transition lookups.

Everything here is a lookup in the store.  Pose-frame quantities are served as stored:
metres, unit vectors, the pose's canonical frame (z up, table at z = 0, centre of
mass over the origin).
"""

from __future__ import annotations

import numpy as np
from fastapi import APIRouter, Query, Request
from fastapi.responses import Response

from schema.api import (
    ActionDetail,
    ErrorBody,
    Grasp,
    ObjectDetail,
    ObjectList,
    ObjectSummary,
    PolicyChoice,
    PoseDetail,
    PoseList,
    PoseSummary,
    QValues,
    RankBy,
    RankedAction,
    TransitionBatch,
    TransitionResults,
    ValidationErrorBody,
)
from schema.vocabulary import NO_OP, POLICIES

from .. import batches
from ..dependencies import BUILD_RESPONSES, StoreDep
from ..planning import next_poses
from ..store import ObjectData, optional, widen

ERRORS = {404: {"model": ErrorBody, "description": "Unknown object, pose or action"},
          422: {"model": ValidationErrorBody, "description": "Malformed request"}}

router = APIRouter(prefix="/objects", tags=["objects"], responses={**ERRORS, **BUILD_RESPONSES})
batch = APIRouter(prefix="/batch", tags=["batch"], responses={422: ERRORS[422], **BUILD_RESPONSES})


def _action_or_none(action) -> int | None:
    return None if int(action) == NO_OP else int(action)


def grasp_model(point: np.ndarray, axis: np.ndarray) -> Grasp | None:
    if np.isnan(point).any() or np.isnan(axis).any():
        return None
    return Grasp(point=point.tolist(), axis=axis.tolist())


def pose_summary(obj: ObjectData, pose: int) -> PoseSummary:
    return PoseSummary(
        pose=pose,
        probability=float(obj.probability[pose]),
        height=float(obj.height[pose]),
        v_s=float(obj.v_s[pose]),
        v_t=float(obj.v_t[pose]),
        n_actions=int(obj.n_actions[pose]),
        n_ok_actions=int(obj.n_ok_actions[pose]),
        value_iteration_action=_action_or_none(obj.policy_action["value_iteration"][pose]),
    )


def action_detail(obj: ObjectData, pose: int, action: int) -> ActionDetail:
    """One push of one pose, pose frame; NotFound for unknown ids."""
    row = obj.row(pose, action)
    values = widen(np.concatenate([obj.points[row], obj.normals[row], obj.directions[row], [obj.p_topple[row], obj.mean_force[row]]]))
    point, normal, direction = values[0:3].tolist(), values[3:6].tolist(), values[6:9].tolist()
    p_topple, mean_force = values[9], values[10]
    return ActionDetail(
        object_id=obj.object_id,
        pose=pose,
        action=action,
        status=obj.status_name(row),
        executable=obj.is_ok(row),
        choosable=bool(obj.choosable([row])[0]),
        is_max_height=bool(obj.is_max_height[row]),
        point=point,
        normal=normal,
        direction=direction,
        p_topple=optional(p_topple),
        mean_force=optional(mean_force),
        q=optional(obj.q[row]),
        greedy=optional(obj.greedy[row]),
        next_poses=next_poses(obj, row),
    )


@router.get("", response_model=ObjectList, summary="List the objects")
async def list_objects(store: StoreDep) -> ObjectList:
    objects = [ObjectSummary(object_id=o.object_id, n_poses=o.n_poses, mass=o.mass, source=o.source) for o in store.objects.values()]
    return ObjectList(count=len(objects), objects=objects)


@router.get("/{object_id}", response_model=ObjectDetail, summary="One object and a summary of its stable poses")
async def get_object(object_id: str, store: StoreDep) -> ObjectDetail:
    obj = store.object(object_id)
    return ObjectDetail(
        object_id=obj.object_id,
        n_poses=obj.n_poses,
        mass=obj.mass,
        source=obj.source,
        sha256=obj.sha256,
        scale=obj.scale,
        center_mass=obj.center_mass.tolist(),
        poses=[pose_summary(obj, p) for p in range(obj.n_poses)],
    )


@router.get("/{object_id}/poses", response_model=PoseList, summary="The object's stable poses")
async def list_poses(object_id: str, store: StoreDep) -> PoseList:
    obj = store.object(object_id)
    return PoseList(object_id=obj.object_id, poses=[pose_summary(obj, p) for p in range(obj.n_poses)])


@router.get("/{object_id}/poses/{pose}", response_model=PoseDetail, summary="One stable pose: grasp, values, policies")
async def get_pose(object_id: str, pose: int, store: StoreDep) -> PoseDetail:
    obj = store.object(object_id)
    obj.check_pose(pose)
    return PoseDetail(
        object_id=obj.object_id,
        pose=pose,
        probability=float(obj.probability[pose]),
        down=obj.downs[pose].tolist(),
        transform=obj.transforms[pose].tolist(),
        height=float(obj.height[pose]),
        com_height=float(obj.com_height[pose]),
        v_s=float(obj.v_s[pose]),
        grasp=grasp_model(obj.grasp_point[pose], obj.grasp_axis[pose]),
        v_t=float(obj.v_t[pose]),
        policies={
            p: PolicyChoice(action=_action_or_none(obj.policy_action[p][pose]), value=float(obj.policy_value[p][pose]))
            for p in POLICIES
        },
        n_actions=int(obj.n_actions[pose]),
        action_counts=obj.action_counts(pose),
    )


@router.get(
    "/{object_id}/poses/{pose}/actions/{action}",
    response_model=ActionDetail,
    summary="One candidate push and its next-pose distribution",
    description="A push whose status is not `ok` is returned too (200), with `executable` false, "
    "null `p_topple`/`mean_force`/`q`/`greedy` and an empty `next_poses`: it cannot be executed, "
    "so it has no outcome.",
)
async def get_action(object_id: str, pose: int, action: int, store: StoreDep) -> ActionDetail:
    return action_detail(store.object(object_id), pose, action)


@router.get(
    "/{object_id}/poses/{pose}/q",
    response_model=QValues,
    summary="Q-values of a pose and its best actions",
    description="`q` lists Q_T of every action (null unless `ok`); `top` the `top` best `ok` actions "
    "ranked by `by` (Q_T, the Greedy score E[V_s(next pose)], or P(topple)), highest first.",
)
async def get_q(
    object_id: str,
    pose: int,
    store: StoreDep,
    top: int = Query(10, ge=1, le=10_000, description="How many actions to rank"),
    by: RankBy = Query("q", description="Rank by q, greedy or p_topple"),
) -> QValues:
    obj = store.object(object_id)
    rows = obj.pose_rows(pose)
    q = obj.q[rows]
    greedy = obj.greedy[rows]
    p_topple = obj.p_topple[rows]
    score = {"q": q, "greedy": greedy, "p_topple": p_topple}[by]
    candidates = np.flatnonzero(~np.isnan(score))
    # lexsort: last key is primary; ties go to the lower action index, deterministically.
    ranked = candidates[np.lexsort((candidates, -score[candidates]))][:top]
    ranked_p_topple = widen(p_topple[ranked])
    max_height = obj.is_max_height[rows]
    choosable = obj.choosable(rows)
    return QValues(
        object_id=obj.object_id,
        pose=pose,
        by=by,
        gamma=store.gamma,
        v_s=float(obj.v_s[pose]),
        v_t=float(obj.v_t[pose]),
        q=[optional(v) for v in q],
        top=[
            RankedAction(
                action=int(a), q=float(q[a]), greedy=float(greedy[a]), p_topple=float(p), is_max_height=bool(max_height[a]),
                choosable=bool(choosable[a]),
            )
            for a, p in zip(ranked, ranked_p_topple)
        ],
    )


@batch.post(
    "/transitions",
    response_model=TransitionResults,
    summary="Many actions and their next-pose distributions at once",
    description="`results[i]` answers `items[i]`: `result` (as GET .../actions/{action}) or `error` "
    "(`status` 404 and a `detail`) for an unknown id; one bad id does not fail the batch. A malformed "
    "body, or more than 1000 items, fails the whole batch with 422. Batches run in their own lane, one at a "
    "time per worker, so they do not delay the single lookups and POST /plan.",
    openapi_extra=batches.request_body(TransitionBatch),
)
async def batch_transitions(request: Request, store: StoreDep) -> Response:
    body = await request.body()
    answer = await batches.run(request.app.state.lane, "transitions", body, store, request.app.state.settings)
    return Response(answer, media_type="application/json")
