"""POST /heaps/plan: a planar push for a heap of objects in a bin (thesis chapter 3).

The objects' hulls and centres of mass come from the served dataset; the push from
``clutter.policies``.  Same error discipline as /plan: 404 an unknown object, 409 an object
outside the bin or below its floor, 422 malformed input (a ROS pose in another frame too).
Plans run in a thread of their own (``PLANNER``), not on the event loop that answers /plan.
"""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from fastapi import APIRouter
from fastapi.responses import Response

from clutter.policies import PushConfig, outside_bin, plan_push
from clutter.state import Bin, HeapState, Push
from schema.api import (
    BIN_TOLERANCE,
    ErrorBody,
    HeapPlanRequest,
    HeapPlanResponse,
    HeapPush,
    OutsideBinBody,
    ValidationErrorBody,
)

from ..dependencies import BUILD_RESPONSES, SettingsDep, StoreDep
from ..errors import NotFound, ServiceError
from ..settings import Settings
from ..store import Store

router = APIRouter(tags=["heaps"], responses=BUILD_RESPONSES)

PLANNER = ThreadPoolExecutor(max_workers=1, thread_name_prefix="heap-planner")
"""The thread heap plans run in, one per worker process (its thread starts with the first plan,
so a forked worker gets its own).  A 10-object plan is 5-15 ms of Python and numpy; on the
event loop it held /plan up for as long (a 50 Hz controller's p99 27 ms behind two clients
planning heaps back to back); in one thread, with the server's short switch interval, 4-9 ms."""

CONFIG = PushConfig()
"""The planner's numbers (clutter.policies.PushConfig defaults; the pybullet heaps plan with them too)."""

NEEDS_TWO = {"boundary_shear": "two objects to separate", "free_space": "two objects to separate",
             "cluster_diffusion": "a cluster of two or more objects"}


class OutsideBin(ServiceError):
    """An object's hull past a wall (reason outside_bin) or below the floor (below_floor)."""

    status_code = 409

    def __init__(self, detail: str, reason: str, **extra):
        super().__init__(detail, **extra)
        self.reason = reason


class Malformed(ServiceError):
    """422 found after validation (a ROS pose in another frame, a heap the planner refuses)."""

    status_code = 422

    def __init__(self, loc: list, message: str, kind: str):
        super().__init__(message)
        self.loc, self.kind = loc, kind

    def body(self) -> dict:
        where = ".".join(str(part) for part in self.loc)
        return {"detail": f"{where}: {self.detail}", "errors": [{"loc": self.loc, "msg": self.detail, "type": self.kind}]}


def heap_inputs(store: Store, request: HeapPlanRequest, settings: Settings) -> tuple[HeapState, list[np.ndarray], np.ndarray]:
    """The heap state, hulls (V_i, 3) and centres of mass (n, 3) of the request; NotFound, Malformed."""
    hulls, centres, poses = [], [], []
    for index, item in enumerate(request.objects):
        try:
            obj = store.object(item.object_id)
        except NotFound as err:
            raise NotFound(f"objects[{index}]: {err.detail}") from None
        if item.ros_pose is not None and item.ros_pose.frame_id != settings.frame_id:
            raise Malformed(
                ["body", "objects", index, "ros_pose", "frame_id"],
                f"'{item.ros_pose.frame_id}' is not this service's frame '{settings.frame_id}' (the bin's: z up, floor at z = 0); "
                "transform the pose into it first (e.g. tf2)", "unknown_frame",
            )
        hulls.append(obj.hull_vertices)
        centres.append(obj.center_mass)
        poses.append(item.observed())
    state = HeapState(Bin(**request.bin.model_dump()), tuple(o.object_id for o in request.objects), np.stack(poses))
    return state, hulls, np.asarray(centres, dtype=np.float64)


def check_in_bin(state: HeapState, hulls: list[np.ndarray]) -> None:
    """OutsideBin for the first object whose hull reaches more than BIN_TOLERANCE past a wall or
    below the floor."""
    found = outside_bin(state, hulls, BIN_TOLERANCE)
    if found is None:
        return
    index, reason, distance = found
    object_id = state.object_ids[index]
    if reason == "outside_bin":
        detail = (f"objects[{index}] ('{object_id}') reaches {distance * 1000:.1f} mm past a wall of the {state.bin.length:g} x "
                  f"{state.bin.width:g} m bin (tolerance {BIN_TOLERANCE * 1000:g} mm): is the pose in the bin's frame "
                  "(origin at the centre of its floor)?")
    else:
        detail = (f"objects[{index}] ('{object_id}') reaches {distance * 1000:.1f} mm below the bin's floor z = 0 "
                  f"(tolerance {BIN_TOLERANCE * 1000:g} mm): is the world frame z up with the floor at z = 0?")
    raise OutsideBin(detail, reason, index=index, object_id=object_id, distance=distance, tolerance=BIN_TOLERANCE)


def describe(policy: str, push: Push | None, state: HeapState) -> str:
    if push is not None:
        d = (push.end - push.start) / push.length
        return (f"{policy} pushes objects[{push.target}] ('{state.object_ids[push.target]}') {push.length:.3f} m "
                f"along ({d[0]:.3f}, {d[1]:.3f}) through its centre of mass")
    if policy in NEEDS_TWO and len(state) < 2:
        return f"{policy} needs {NEEDS_TWO[policy]}; the heap has one object"
    return (f"{policy} found no collision-free push: for every candidate the finger would come down on an object "
            "or against a wall, or meet another object on its way to the target")


def plan_heap(store: Store, request: HeapPlanRequest, settings: Settings) -> HeapPlanResponse:
    """The policy's push for the request's heap (see the module docstring for the errors)."""
    state, hulls, centres = heap_inputs(store, request, settings)
    check_in_bin(state, hulls)
    try:
        push = plan_push(request.policy, state, hulls, centres, rng=np.random.default_rng(request.seed), config=CONFIG)
    except ValueError as err:  # a hull the planner cannot use (flat): the request names objects it cannot plan for
        raise Malformed(["body", "objects"], str(err), "unplannable") from None
    answer = None
    if push is not None:
        answer = HeapPush(
            target=push.target, object_id=state.object_ids[push.target], start=push.start.tolist(), end=push.end.tolist(),
            direction=((push.end - push.start) / push.length).tolist(), length=push.length,
        )
    return HeapPlanResponse(
        policy=request.policy, frame_id=settings.frame_id, found=push is not None, reason=describe(request.policy, push, state),
        push=answer, finger_radius=CONFIG.finger_radius, push_length=CONFIG.push_length, approach_offset=CONFIG.approach_offset,
    )


@router.post(
    "/heaps/plan",
    response_model=HeapPlanResponse,
    summary="A planar push for a heap of objects in a bin (thesis chapter 3)",
    description="Given the bin and the objects' ids and poses (object -> world, the bin's frame: origin at the "
    "centre of its floor, z up, x along its length; a 4x4 matrix in `pose` or a ROS pose in `ros_pose`), the "
    "`policy`'s push: which object (`push.target`, an index into `objects`) and the finger's straight line "
    "from `push.start` to `push.end` (world, m), clipped to the bin and with a collision-free approach. "
    "`found` false (and `push` null) when the policy finds no collision-free push. `seed` drives "
    "`quasi_random`'s draws.",
    responses={
        404: {"model": ErrorBody, "description": "Unknown object"},
        409: {"model": OutsideBinBody, "description": "An object past a wall (outside_bin) or below the floor (below_floor)"},
        422: {"model": ValidationErrorBody, "description": "Malformed request (NaN, not a rotation, unknown policy or frame_id, ...)"},
    },
)
async def post_heap_plan(request: HeapPlanRequest, store: StoreDep, settings: SettingsDep) -> Response:
    answer = await asyncio.get_running_loop().run_in_executor(PLANNER, plan_heap, store, request, settings)
    return Response(answer.model_dump_json(), media_type="application/json")
