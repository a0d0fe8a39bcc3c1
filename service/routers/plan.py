"""Routes for planning: POST /plan (on the event loop: the control path) and POST
/batch/plan (in the batch lane).  The planning itself is ``service.planning``."""

from __future__ import annotations

from fastapi import APIRouter, Request
from fastapi.responses import Response

from schema.api import (
    ErrorBody,
    NoMatchBody,
    OffTableBody,
    PlanBatch,
    PlanRequest,
    PlanResponse,
    PlanResults,
    ValidationErrorBody,
)

from .. import batches
from ..dependencies import BUILD_RESPONSES, SettingsDep, StoreDep
from ..planning import answer_json, plan

router = APIRouter(tags=["plan"], responses=BUILD_RESPONSES)
batch = APIRouter(prefix="/batch", tags=["batch"], responses=BUILD_RESPONSES)


@router.post(
    "/plan",
    response_model=PlanResponse,
    summary="What to do with an observed object: push (where, how hard), grasp, or neither",
    description="Matches the observed pose (object -> world, z up, table z = 0; a 4x4 matrix in `pose` or a ROS "
    "pose in `ros_pose`) to a stable pose (down vectors within the manifest's `poses.same_pose_angle`), checks "
    "that it rests on the table (|`match.z_offset`| <= `match.height_tolerance`), and returns the policy's "
    "`decision`: `push` (the push in world coordinates, placed through the observed pose, with its required "
    "force and whether it is within the finger's limit), `grasp` (now, at `grasp`), or `no_grasp` (the policy "
    "does not push and the pose has no suction grasp). `v_s`, `v_t`, `q_value` and `expected_v_s_after` mean "
    "the same for every policy.",
    responses={
        404: {"model": ErrorBody, "description": "Unknown object"},
        409: {"model": NoMatchBody | OffTableBody, "description": "No stable pose (reason no_stable_pose) or not on the table (off_table)"},
        422: {"model": ValidationErrorBody, "description": "Malformed request (NaN, not a rotation, unknown frame_id, ...)"},
    },
)
async def post_plan(request: PlanRequest, store: StoreDep, settings: SettingsDep) -> Response:
    # Serialised here: the answer is built from validated parts, and FastAPI's second validation
    # of response_model (kept for the OpenAPI document) would cost as much as the planning.
    # A valid body is normally answered before it gets here (service/fastplan.py), identically.
    return Response(answer_json(plan(store, request, settings)), media_type="application/json")


@batch.post(
    "/plan",
    response_model=PlanResults,
    summary="Plan for many observed poses at once",
    description="`results[i]` answers `items[i]`: `result` (as POST /plan) or `error` (`status` 404 for "
    "an unknown object, 409 for no matching stable pose or off the table, 422 for a ROS pose in an unknown frame, "
    "and a `detail`); one such item does not fail the batch. A malformed body (any item's NaN, non-rotation, "
    "unknown policy, ...) or more than 1000 items fails the whole batch with 422. Batches run in their own "
    "lane (a child process per worker), one at a time, so they do not delay POST /plan.",
    responses={422: {"model": ValidationErrorBody, "description": "Malformed request"}},
    openapi_extra=batches.request_body(PlanBatch),
)
async def batch_plan(request: Request, store: StoreDep, settings: SettingsDep) -> Response:
    body = await request.body()
    answer = await batches.run(request.app.state.lane, "plan", body, store, settings)
    return Response(answer, media_type="application/json")
