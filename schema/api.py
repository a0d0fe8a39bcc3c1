"""Pydantic models of the HTTP API: every request and response body of ``service``.

This module is the API's contract, as ``schema.tables`` is the dataset's; the
OpenAPI document the service publishes (``/openapi.json``, ``/docs``) is made
from it.

Units and frames (as in the dataset): SI throughout (metres, kilograms, newtons,
radians).  *world*: z up, table plane z = 0.  *pose*: the canonical frame of one
stable pose (z up, table at z = 0, centre of mass over the origin).  *object*:
the mesh's own frame.  An observed resting pose is ``planar @ transform`` where
``transform`` (object -> pose frame) is the stable pose's and ``planar`` (pose ->
world frame) is a rotation about z plus a translation in x, y.

Conventions: a push that cannot be executed (status other than ``ok``) has null
``p_topple``, ``mean_force``, ``q`` and ``greedy`` and an empty next-pose
distribution; a policy that chooses not to push has ``action`` null.  Errors are
``{"detail": "<one message>"}`` (``ErrorBody``), with a few extra fields for
422 and 409.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field

from schema.vocabulary import PolicyName, StatusName

MAX_BATCH = 1000
"""Most items in one batch request; more is a 422."""

ROTATION_TOLERANCE = 1e-3
"""Largest |R^T R - I| entry and |det R - 1| accepted for the rotation of an observed pose."""

Policy = PolicyName
"""Policies whose choice per pose is stored (thesis 4.3), ``schema.vocabulary.POLICIES``."""

RankBy = Literal["q", "greedy", "p_topple"]

Status = StatusName
"""``ok``, or why a candidate push cannot be executed (``schema.vocabulary.STATUS_NAMES``)."""

Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Vector2 = Annotated[list[float], Field(min_length=2, max_length=2)]
Matrix4 = Annotated[list[Annotated[list[float], Field(min_length=4, max_length=4)]], Field(min_length=4, max_length=4)]
"""4x4 homogeneous matrix, row-major (``matrix[row][column]``)."""


def check_rigid(matrix: list[list[float]]) -> list[list[float]]:
    """Accept a 4x4 rigid transform: rotation (orthonormal, det +1) and last row [0, 0, 0, 1].

    The tolerance (``ROTATION_TOLERANCE``) admits rotations that went through float32 or
    a few printed digits; anything further off is a client bug, not a pose.
    """
    m = np.asarray(matrix, dtype=float)
    rotation = m[:3, :3]
    drift = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if drift > ROTATION_TOLERANCE:
        raise ValueError(
            f"the upper-left 3x3 block is not a rotation: its columns are not orthonormal "
            f"(largest |R^T R - I| entry {drift:.3g}, at most {ROTATION_TOLERANCE:g})"
        )
    det = float(np.linalg.det(rotation))
    if abs(det - 1.0) > ROTATION_TOLERANCE:
        raise ValueError(f"the upper-left 3x3 block is not a rotation: det = {det:.3g}, expected +1 (a reflection?)")
    if np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-9:
        raise ValueError(f"the last row must be [0, 0, 0, 1], got {m[3].tolist()}")
    return matrix


MatrixEntry = Annotated[float, Field(strict=True, allow_inf_nan=False)]
"""A finite JSON number; strict, so that true or "1" is an error rather than 1.0."""

RigidTransform = Annotated[
    list[Annotated[list[MatrixEntry], Field(min_length=4, max_length=4)]],
    Field(min_length=4, max_length=4),
    AfterValidator(check_rigid),
]
"""A 4x4 rigid transform in a request: finite numbers, rotation block, last row [0, 0, 0, 1]."""


class Model(BaseModel):
    """Base of every API model: unknown request fields are an error, not silently ignored."""

    model_config = ConfigDict(extra="forbid")


# --- errors -------------------------------------------------------------------------


class ErrorBody(Model):
    """Body of every error response (404, 409, 413, 422, 500)."""

    detail: str = Field(description="What went wrong, in one message")


class FieldError(Model):
    loc: list[str | int] = Field(description="Where in the request, e.g. ['body', 'pose', 1, 2]")
    msg: str
    type: str


class ValidationErrorBody(ErrorBody):
    """422: the request is malformed; ``detail`` joins every problem, ``errors`` lists them."""

    errors: list[FieldError]


class NoMatchBody(ErrorBody):
    """409: the observed orientation is no stable pose of the object."""

    object_id: str
    nearest_pose: int = Field(description="Stable pose whose down vector is closest to the observed one")
    angle_error: float = Field(description="rad, angle between the observed and the nearest pose's down vector")
    tolerance: float = Field(description="rad, largest angle that still matches (manifest poses.same_pose_angle)")


# --- service -----------------------------------------------------------------------


class Counts(Model):
    objects: int
    poses: int
    actions: int
    ok_actions: int
    transitions: int


class Health(Model):
    status: Literal["ok"]
    schema_version: str
    counts: Counts
    load_seconds: float = Field(description="s, time taken to load the dataset at start")


# --- objects and poses -------------------------------------------------------------


class ObjectSummary(Model):
    object_id: str
    n_poses: int
    mass: float = Field(description="kg")
    source: str = Field(description="Where the mesh comes from, e.g. pybullet_data/random_urdfs")


class ObjectList(Model):
    count: int
    objects: list[ObjectSummary]


class PolicyChoice(Model):
    action: int | None = Field(description="Action index within the pose; null: no push (grasp now)")
    value: float = Field(description="Expected value of the choice (stored <policy>_value); V_s for no push")


class PoseSummary(Model):
    pose: int
    probability: float = Field(description="Probability of coming to rest in this pose when dropped")
    height: float = Field(description="m, top of the object above the table")
    v_s: float = Field(description="Robust quality of the best suction grasp from above, in [0, 1]")
    v_t: float = Field(description="Value of the pose under value iteration")
    n_actions: int
    n_ok_actions: int
    value_iteration_action: int | None = Field(description="null: no push")


class ObjectDetail(ObjectSummary):
    sha256: str = Field(description="SHA-256 of the mesh file")
    scale: float = Field(description="Mesh file units -> metres")
    center_mass: Vector3 = Field(description="m, object frame")
    poses: list[PoseSummary]


class PoseList(Model):
    object_id: str
    poses: list[PoseSummary]


class Grasp(Model):
    point: Vector3 = Field(description="m, suction contact point")
    axis: Vector3 = Field(description="unit approach axis, gripper -> object")


class PoseDetail(Model):
    object_id: str
    pose: int
    probability: float
    down: Vector3 = Field(description="unit, object frame, points onto the table")
    transform: Matrix4 = Field(description="object frame -> pose frame, row-major")
    height: float = Field(description="m, top of the object above the table")
    com_height: float = Field(description="m, centre of mass above the table")
    v_s: float = Field(description="Robust quality of the best suction grasp from above, in [0, 1]")
    grasp: Grasp | None = Field(description="Best suction grasp, pose frame; null when there is none")
    v_t: float = Field(description="V_T, value under value iteration")
    policies: dict[Policy, PolicyChoice]
    n_actions: int
    action_counts: dict[Status, int] = Field(description="Candidate pushes by status")


# --- actions and Q-values ----------------------------------------------------------


class NextPose(Model):
    next_pose: int = Field(description="Pose the object comes to rest in (equal to pose: it stayed)")
    probability: float = Field(description="P(next_pose | pose, action)")


class ActionDetail(Model):
    """One candidate push (pose frame) and, when it can be executed, where it leads."""

    object_id: str
    pose: int
    action: int
    status: Status
    executable: bool = Field(description="status == ok; otherwise the value fields are null and next_poses empty")
    is_max_height: bool = Field(description="The Max-Height baseline's action")
    point: Vector3 = Field(description="m, contact point, pose frame")
    normal: Vector3 = Field(description="outward unit surface normal, pose frame")
    direction: Vector3 = Field(description="unit push direction, pose frame")
    p_topple: float | None = Field(description="P(next pose != pose); null unless ok")
    mean_force: float | None = Field(description="N, mean required push force over toppling trials; null when none")
    q: float | None = Field(description="Q_T(pose, action); null unless ok")
    greedy: float | None = Field(description="E[V_s(next pose)]; null unless ok")
    next_poses: list[NextPose] = Field(description="P(next pose | pose, action), sums to 1; empty unless ok")


class RankedAction(Model):
    action: int
    q: float
    greedy: float
    p_topple: float
    is_max_height: bool


class QValues(Model):
    object_id: str
    pose: int
    by: RankBy = Field(description="Column the top actions are ranked by")
    gamma: float = Field(description="Discount of value iteration")
    v_s: float = Field(description="Value of not pushing (grasping now)")
    v_t: float = Field(description="V_T = max(V_s, gamma max_u Q_T)")
    q: list[float | None] = Field(description="Q_T of every action, in action order; null unless ok")
    top: list[RankedAction] = Field(description="The best ok actions, highest first (ties: lower action first)")


class TransitionQuery(Model):
    object_id: str
    pose: int
    action: int


class TransitionBatch(Model):
    items: list[TransitionQuery] = Field(max_length=MAX_BATCH)


# --- planning ----------------------------------------------------------------------


class PlanRequest(Model):
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "examples": [
                {
                    "object_id": "random_001",
                    "pose": [[0, -1, 0, 0.4], [1, 0, 0, -0.1], [0, 0, 1, 0.02], [0, 0, 0, 1]],
                    "policy": "value_iteration",
                }
            ]
        },
    )

    object_id: str
    pose: RigidTransform = Field(
        description="Observed pose: object frame -> world frame (z up, table z = 0), 4x4 row-major"
    )
    policy: Policy = "value_iteration"


class PoseMatch(Model):
    pose: int = Field(description="Matched stable pose")
    angle_error: float = Field(description="rad, between the observed and the stable pose's down vectors")
    tolerance: float = Field(description="rad, largest angle_error that matches")
    yaw: float = Field(description="rad, rotation about world z of the pose frame, in (-pi, pi]")
    translation: Vector2 = Field(description="m, world x, y of the pose frame's origin (below the centre of mass)")
    z_offset: float = Field(
        description="m, observed height of the pose frame's origin above z = 0; "
        "nonzero when the object does not rest on the table z = 0 (the push assumes it does)"
    )
    planar: Matrix4 = Field(description="pose frame -> world frame: rotation yaw about z, translation in x, y")


class WorldPush(Model):
    """A push in the world frame, ready to execute."""

    point: Vector3 = Field(description="m, contact point")
    normal: Vector3 = Field(description="outward unit surface normal at the contact")
    direction: Vector3 = Field(description="unit push direction")
    start: Vector3 = Field(description="m, start of the finger's line: point + approach_offset * normal")
    end: Vector3 = Field(description="m, end of the finger's line: point - push_depth * normal")
    approach_offset: float = Field(description="m, manifest contacts.approach_offset")
    push_depth: float = Field(description="m, manifest contacts.push_depth")


class PlanResponse(Model):
    object_id: str
    policy: Policy
    match: PoseMatch
    v_s: float = Field(description="Suction quality of the matched pose (the value of grasping now)")
    action: int | None = Field(description="The policy's action in the matched pose; null: no push, grasp now")
    expected_value: float = Field(description="The policy's expected value (stored <policy>_value)")
    p_topple: float | None = Field(description="null for no push")
    push: WorldPush | None = Field(description="The push in world coordinates; null for no push")
    next_poses: list[NextPose] = Field(description="Where the push leads; empty for no push")
    grasp: Grasp | None = Field(description="The matched pose's best suction grasp, world frame; null when none")


class PlanBatch(Model):
    items: list[PlanRequest] = Field(max_length=MAX_BATCH)


class ItemError(Model):
    status: int = Field(description="HTTP status the item would have had alone: 404 or 409")
    detail: str


class TransitionResult(Model):
    """One batch item: exactly one of ``result`` and ``error`` is set."""

    result: ActionDetail | None = None
    error: ItemError | None = None


class TransitionResults(Model):
    results: list[TransitionResult]


class PlanResult(Model):
    """One batch item: exactly one of ``result`` and ``error`` is set."""

    result: PlanResponse | None = None
    error: ItemError | None = None


class PlanResults(Model):
    results: list[PlanResult]
