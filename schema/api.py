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

import math
import re
from decimal import Decimal
from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, BeforeValidator, ConfigDict, Field, model_validator

from schema.horizon import MAX_PUSHES_LEFT
from schema.vocabulary import POLICIES, STATUS_NAMES, PolicyName, StatusName

MAX_BATCH = 1000
"""Most items in one batch request; more is a 422."""
MAX_FAILED_ACTIONS = 100
"""Most failed pushes a /plan request may report: a robot gives up long before."""

ROTATION_TOLERANCE = 1e-3
"""Largest |R^T R - I| entry and |det R - 1| accepted for the rotation of an observed pose."""

MAX_TRANSLATION = 1e6
"""m, largest |x|, |y| or |z| of a pose's translation in a request: 1,000 km admits any frame a robot
works in; past it a push's 1.5 cm approach and 4 cm depth would soon vanish in float64 (at 1e14 m
its spacing is 1.6 cm), so a start, contact and end served as one point would read as executable."""

HEIGHT_TOLERANCE = 0.005
"""m, default largest |z_offset| of an observed pose: the height above z = 0 of the matched
stable pose's support point (the pose frame's origin, on the bottom under the centre of mass).
Further off, the object is not resting on the table (stacked, held, or a perception error) and
/plan answers 409; the service's ``--height-tolerance`` / ``TOPPLEDB_HEIGHT_TOLERANCE`` overrides it."""

HEIGHT_ROUNDING = 1e-9
"""m, slack on ``HEIGHT_TOLERANCE``: an observed height comes out of a product of 4x4 transforms a few
ulps either side of the true one, and an object lifted by exactly the tolerance is within it."""


def height_in_mm(z_offset: float, height_tolerance: float) -> str:
    """|z_offset| in millimetres for a refusal: one decimal, or four where one would read as the
    tolerance itself ("5.0 mm ... tolerance 5.0 mm" for an object 5.001 mm up)."""
    height, tolerance = abs(z_offset) * 1000, height_tolerance * 1000
    if not height < 1e9:  # past 1,000 km: four figures, in decimal so that 1e308 m is not "inf" mm
        return f"{(Decimal(repr(abs(z_offset))) * 1000).normalize():.4g}"
    return f"{height:.1f}" if f"{height:.1f}" != f"{tolerance:.1f}" else f"{height:.4f}"


def rests_on_table(z_offset: float, height_tolerance: float) -> bool:
    """Whether an observed pose's support point is within ``height_tolerance`` (m) of the table,
    the edge included (``HEIGHT_ROUNDING``); NaN is not."""
    return bool(abs(z_offset) <= height_tolerance + HEIGHT_ROUNDING)


FINGER_FORCE_LIMIT = 20.0
"""N, default largest push force the finger may apply, used when the manifest has no
``parameters.topple.max_finger_force``.  An assumed budget for a thin finger on a
collaborative arm, not a measured one: set it for your robot (``--finger-force-limit`` or
``TOPPLEDB_FINGER_FORCE_LIMIT`` overrides both)."""

QUATERNION_TOLERANCE = 1e-3
"""Largest | |q| - 1 | accepted for a ROS orientation quaternion (it is then normalised)."""

Policy = PolicyName
"""Policies whose choice per pose is stored (thesis 4.3), ``schema.vocabulary.POLICIES``."""

RankBy = Literal["q", "greedy", "p_topple"]

Status = StatusName
"""``ok``, or why a candidate push cannot be executed (``schema.vocabulary.STATUS_NAMES``)."""

Vector3 = Annotated[list[float], Field(min_length=3, max_length=3)]
Vector2 = Annotated[list[float], Field(min_length=2, max_length=2)]
Matrix4 = Annotated[list[Annotated[list[float], Field(min_length=4, max_length=4)]], Field(min_length=4, max_length=4)]
"""4x4 homogeneous matrix, row-major (``matrix[row][column]``)."""


def rotation_problem(r) -> str | None:
    """Why a 3x3 block (rows of numbers) is no rotation: its columns are not orthonormal, or its
    determinant is not +1 (a reflection), each within ``ROTATION_TOLERANCE``; None when it is one.

    Plain Python arithmetic: on a 3x3 block it is several times faster than numpy's per-call
    overhead, and it runs on every /plan request.  Shared with the Python API (``pipeline``'s
    ``settle`` and ``plan``), so that both refuse the same matrices in the same words.
    """
    try:
        drift = max(
            abs(sum(r[k][i] * r[k][j] for k in range(3)) - (1.0 if i == j else 0.0)) for i in range(3) for j in range(3)
        )
        det = (r[0][0] * (r[1][1] * r[2][2] - r[1][2] * r[2][1]) - r[0][1] * (r[1][0] * r[2][2] - r[1][2] * r[2][0])
               + r[0][2] * (r[1][0] * r[2][1] - r[1][1] * r[2][0]))
    except OverflowError:  # huge entries: not a rotation either
        drift = det = math.inf
    if not drift <= ROTATION_TOLERANCE:  # NaN too
        return (f"its columns are not orthonormal "
                f"(largest |R^T R - I| entry {drift:.3g}, at most {ROTATION_TOLERANCE:g})")
    if not abs(det - 1.0) <= ROTATION_TOLERANCE:
        return f"det = {det:.3g}, expected +1 (a reflection?)"
    return None


def check_rigid(matrix: list[list[float]]) -> list[list[float]]:
    """Accept a 4x4 rigid transform: rotation (orthonormal, det +1) and last row [0, 0, 0, 1].

    The tolerance (``ROTATION_TOLERANCE``) admits rotations that went through float32 or
    a few printed digits; anything further off is a client bug, not a pose.
    """
    problem = rotation_problem([row[:3] for row in matrix[:3]])
    if problem is not None:
        raise ValueError(f"the upper-left 3x3 block is not a rotation: {problem}")
    if max(abs(a - b) for a, b in zip(matrix[3], (0.0, 0.0, 0.0, 1.0))) > 1e-9:
        transposed = max(abs(matrix[i][3] - (1.0 if i == 3 else 0.0)) for i in range(4)) <= 1e-9
        hint = " (the last column is [0, 0, 0, 1]: is the matrix column-major? send it row by row)" if transposed else ""
        raise ValueError(f"the last row must be [0, 0, 0, 1], got {list(matrix[3])}{hint}")
    if not max(abs(matrix[i][3]) for i in range(3)) <= MAX_TRANSLATION:
        raise ValueError(f"the translation {[matrix[i][3] for i in range(3)]} is beyond {MAX_TRANSLATION:g} m: "
                         "send metres in the table frame")
    return matrix


Finite = Annotated[float, Field(strict=True, allow_inf_nan=False)]
"""A finite JSON number; strict, so that true or "1" is an error rather than 1.0."""

LONE_SURROGATE = re.compile("[\ud800-\udfff]")


def check_text(value: str) -> str:
    """A request's id or frame as UTF-8 can carry it. JSON may escape a lone UTF-16 surrogate
    (\\ud800), which Python keeps in the string but no UTF-8 response can hold, so an error that
    named the id would fail to encode (a 500); it is refused here instead."""
    if not value.isascii() and LONE_SURROGATE.search(value):
        raise ValueError("is not Unicode text: it holds a lone UTF-16 surrogate (\\ud800-\\udfff)")
    return value


Text = Annotated[str, AfterValidator(check_text)]
"""An id or frame name in a request: any Unicode text, nothing UTF-8 cannot encode."""


RigidTransform = Annotated[
    list[Annotated[list[Finite], Field(min_length=4, max_length=4)]],
    Field(min_length=4, max_length=4),
    AfterValidator(check_rigid),
]
"""A 4x4 rigid transform in a request: finite numbers, rotation block, last row [0, 0, 0, 1]."""


class Model(BaseModel):
    """Base of every request model and of what requests hold: an unknown field is an error, not silently
    ignored, so a misspelt field reaches its sender as a 422."""

    model_config = ConfigDict(extra="forbid")


class Answer(BaseModel):
    """Base of every answer model: an unknown field is ignored, so a newer service may add a field to an
    answer without breaking a client built on an older copy of these models (docs/SERVICE.md, "Versions")."""

    model_config = ConfigDict(extra="ignore")


def known_keys(names: tuple[str, ...]) -> BeforeValidator:
    """For an answer's map keyed by a closed vocabulary (``PoseDetail.policies``): keys this code does not
    know are dropped, as unknown fields are, so a newer service may add a policy or a status."""
    known = frozenset(names)

    def keep_known(value):
        return {k: v for k, v in value.items() if k in known} if isinstance(value, dict) else value

    return BeforeValidator(keep_known)


Coordinate = Annotated[Finite, Field(ge=-MAX_TRANSLATION, le=MAX_TRANSLATION)]
"""m, a position's coordinate in a request (``MAX_TRANSLATION``)."""


class Point(Model):
    """geometry_msgs/Point: m."""

    x: Coordinate
    y: Coordinate
    z: Coordinate


class Quaternion(Model):
    """geometry_msgs/Quaternion, x, y, z, w (Hamilton, w the scalar part); unit within QUATERNION_TOLERANCE."""

    x: Finite
    y: Finite
    z: Finite
    w: Finite

    @model_validator(mode="after")
    def _unit(self) -> Quaternion:
        norm = math.hypot(self.x, self.y, self.z, self.w)  # no overflow for huge components
        if abs(norm - 1.0) > QUATERNION_TOLERANCE:
            raise ValueError(f"the orientation quaternion is not unit: |q| = {norm:.6g} (tolerance {QUATERNION_TOLERANCE:g})")
        return self


class RosPose(Model):
    """A pose as ROS sends it (geometry_msgs/PoseStamped flattened): the object frame in ``frame_id``."""

    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={"examples": [{"position": {"x": 0.4, "y": -0.1, "z": 0.02},
                                         "orientation": {"x": 0.0, "y": 0.0, "z": 0.7071068, "w": 0.7071068},
                                         "frame_id": "world"}]},
    )

    position: Point
    orientation: Quaternion
    frame_id: Text = Field(description="Must be the service's table frame (z up, table at z = 0), 'world' unless configured; "
                          "the service does not know other frames: transform the pose into it first")

    def matrix(self) -> np.ndarray:
        """(4, 4) float, object frame -> ``frame_id``."""
        q = self.orientation
        out = np.eye(4)
        out[:3, :3] = quaternion_matrix(q.x, q.y, q.z, q.w)
        out[:3, 3] = [self.position.x, self.position.y, self.position.z]
        return out


def quaternion_matrix(x: float, y: float, z: float, w: float) -> np.ndarray:
    """(3, 3) float rotation of the Hamilton quaternion x, y, z, w (w the scalar part), normalised first."""
    x, y, z, w = np.array([x, y, z, w], dtype=float) / np.linalg.norm([x, y, z, w])
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


# --- errors -------------------------------------------------------------------------


class ErrorBody(Answer):
    """Body of every error response (404, 409, 412, 413, 422, 500)."""

    detail: str = Field(description="What went wrong, in one message")


class FieldError(Answer):
    loc: list[str | int] = Field(description="Where in the request, e.g. ['body', 'pose', 1, 2]")
    msg: str
    type: str


class ValidationErrorBody(ErrorBody):
    """422: the request is malformed; ``detail`` joins every problem, ``errors`` lists them."""

    errors: list[FieldError]


class NoMatchBody(ErrorBody):
    """409: the observed orientation is no stable pose of the object."""

    reason: Literal["no_stable_pose"] = "no_stable_pose"
    object_id: str
    nearest_pose: int = Field(description="Stable pose whose down vector is closest to the observed one")
    angle_error: float = Field(description="rad, angle between the observed and the nearest pose's down vector")
    tolerance: float = Field(description="rad, largest angle that still matches (manifest poses.same_pose_angle)")


class OffTableBody(ErrorBody):
    """409: the observed orientation matches a stable pose but the object is not on the table z = 0."""

    reason: Literal["off_table"] = "off_table"
    object_id: str
    pose: int = Field(description="The matched stable pose")
    z_offset: float = Field(description="m, observed height of the pose's support point (pose frame origin) above z = 0")
    height_tolerance: float = Field(description="m, largest |z_offset| accepted")


class OtherBuildBody(ErrorBody):
    """412: the request names (in ``x-toppledb-build``) a build other than the one that would answer it."""

    build: str = Field(description="The build that would have answered (manifest SHA-256), as the answer's x-toppledb-build")
    requested: str = Field(description="The build the request named (at most its first 80 characters)")


# --- service -----------------------------------------------------------------------


class Counts(Answer):
    objects: int
    poses: int
    actions: int
    ok_actions: int
    transitions: int


class DatasetIdentity(Answer):
    """Which build the service answers from."""

    path: str = Field(description="Dataset directory as the service was given it")
    manifest_sha256: str = Field(description="SHA-256 of manifest.json: names the build (its tables' checksums are in it)")
    created: str = Field(description="UTC, ISO 8601, when the build finished (manifest created)")
    code_version: str = Field(description="toppledb version that built it, with the git commit when known")
    parameters_sha256: str = Field(description=(
        "SHA-256 of the manifest's parameters (canonical JSON), a parameter that names a file taken as its "
        "content's SHA-256 (manifest parameter_files): equal digests, equal model"))
    loaded_at: str = Field(description="UTC, ISO 8601, when this worker loaded it")


class Health(Answer):
    status: Literal["ok"]
    schema_version: str
    service_version: str = Field(description="toppledb version of the running service")
    dataset: DatasetIdentity
    counts: Counts
    load_seconds: float = Field(description="s, time taken to load the dataset")
    reloads: int = Field(description="Datasets swapped in since start (SIGHUP or a changed manifest.json)")
    reload_error: str | None = Field(
        None, description="Why the dataset on disk could not be swapped in (a half-written or broken rebuild): the build "
                          "named in dataset is still served. Absent when the last reload succeeded, found nothing new, "
                          "or none was tried, or when the served build's manifest is back")


# --- objects and poses -------------------------------------------------------------


class ObjectSummary(Answer):
    object_id: str
    n_poses: int
    mass: float = Field(description="kg")
    source: str = Field(description="Where the mesh comes from, e.g. pybullet_data/random_urdfs")


class ObjectList(Answer):
    count: int
    objects: list[ObjectSummary]


class PolicyChoice(Answer):
    action: int | None = Field(description="Action index within the pose; null: no push (grasp now)")
    value: float = Field(description="Expected value of the choice (stored <policy>_value); V_s for no push")


class PoseSummary(Answer):
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


class PoseList(Answer):
    object_id: str
    poses: list[PoseSummary]


class Grasp(Answer):
    point: Vector3 = Field(description="m, suction contact point")
    axis: Vector3 = Field(description="unit approach axis, gripper -> object")


class PoseDetail(Answer):
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
    policies: Annotated[dict[Policy, PolicyChoice], known_keys(POLICIES)]
    n_actions: int
    action_counts: Annotated[dict[Status, int], known_keys(STATUS_NAMES)] = Field(description="Candidate pushes by status")


# --- actions and Q-values ----------------------------------------------------------


class NextPose(Answer):
    next_pose: int = Field(description="Pose the object comes to rest in (equal to pose: it stayed)")
    probability: float = Field(description="P(next_pose | pose, action)")


class ActionDetail(Answer):
    """One candidate push (pose frame) and, when it can be executed, where it leads."""

    object_id: str
    pose: int
    action: int
    status: Status
    executable: bool = Field(description="status == ok; otherwise the value fields are null and next_poses empty")
    choosable: bool = Field(description="Whether greedy and value iteration may choose this push (ok, and its direction's u_z at least the build's mdp.min_direction_z); its q is its value either way")
    is_max_height: bool = Field(description="The Max-Height baseline's action")
    point: Vector3 = Field(description="m, contact point, pose frame")
    normal: Vector3 = Field(description="outward unit surface normal, pose frame")
    direction: Vector3 = Field(description="unit push direction, pose frame")
    p_topple: float | None = Field(description="P(next pose != pose); null unless ok")
    mean_force: float | None = Field(description="N, mean required push force over toppling trials; null when none")
    q: float | None = Field(description="Q_T(pose, action): expected V_T after this push (in a build with mdp.retry_failed false, "
                                        "the pose itself counted at its grasp V_s should the push fail); null unless ok")
    greedy: float | None = Field(description="E[V_s(next pose)]; null unless ok")
    next_poses: list[NextPose] = Field(description="P(next pose | pose, action), sums to 1; empty unless ok")


class RankedAction(Answer):
    action: int
    q: float
    greedy: float
    p_topple: float
    is_max_height: bool
    choosable: bool = Field(description="Whether greedy and value iteration may choose this push (ok, and its direction's u_z at least the build's mdp.min_direction_z); its q is its value either way")


class QValues(Answer):
    object_id: str
    pose: int
    by: RankBy = Field(description="Column the top actions are ranked by")
    gamma: float = Field(description="Discount of value iteration")
    v_s: float = Field(description="Value of not pushing (grasping now)")
    v_t: float = Field(description="V_T = max(V_s, gamma max_u Q_T), u over the choosable pushes")
    q: list[float | None] = Field(description="Q_T of every action, in action order; null unless ok")
    top: list[RankedAction] = Field(description="The best ok actions, highest first (ties: lower action first)")


StrictInt = Annotated[int, Field(strict=True)]
"""A JSON integer; strict, so that true, 1.0 or "1" is an error rather than 1."""


class TransitionQuery(Model):
    object_id: Text
    pose: StrictInt
    action: StrictInt


class TransitionBatch(Model):
    items: list[TransitionQuery] = Field(max_length=MAX_BATCH)


# --- planning ----------------------------------------------------------------------


class PlanRequest(Model):
    """Plan for one observed object. The served OpenAPI document's example is a real object
    and pose of the served dataset (the service fills it in at start)."""

    # Exactly one of pose and ros_pose; neither is nullable (a default is not validated, so an
    # absent field is None while an explicit null is refused), which the schema says with oneOf.
    model_config = ConfigDict(extra="forbid", json_schema_extra={"oneOf": [{"required": ["pose"]}, {"required": ["ros_pose"]}]})

    object_id: Text
    pose: RigidTransform = Field(
        None, description="Observed pose, object frame -> world frame (z up, table z = 0), 4x4 row-major; "
        "give this or ros_pose"
    )
    ros_pose: RosPose = Field(
        None, description="The observed pose as ROS sends it (position, orientation quaternion x, y, z, w, frame_id); "
        "give this or pose"
    )
    policy: Policy = "value_iteration"
    pushes_left: StrictInt = Field(
        None, ge=1, le=MAX_PUSHES_LEFT,
        description="The most pushes the robot will still make before it grasps, this one included. Given, the push "
        "is value iteration's for that budget (finite horizon, no discount: schema/horizon.py), which prefers a "
        "likely topple to a long shot; only with policy value_iteration. Absent: the thesis's value iteration",
    )

    failed_actions: list[Annotated[StrictInt, Field(ge=0)]] = Field(
        [], max_length=MAX_FAILED_ACTIONS,
        description="Actions of the matched pose already pushed on this object that left it in this pose. A push's "
        "outcome is nearly fixed by the push (in simulated physics, value iteration's repeats of a failed push toppled "
        "12% of the time where its table said 31%), so the policy chooses among the candidates that no failed push "
        "rules out: each failed push and its neighbourhood (contacts within 2 cm, directions within 0.5 rad: "
        "schema/retry.py); greedy and a budget by their table values, value iteration by what it believes of the "
        "pushes now (docs/MODEL.md (12.13); (12.12) in a build that does not believe failures). Only with greedy or value_iteration (pushes_left too); an index the "
        "matched pose does not have, or of a push that is not ok (never served), is a 422",
    )

    @model_validator(mode="after")
    def _one_pose(self) -> PlanRequest:
        if (self.pose is None) == (self.ros_pose is None):
            raise ValueError("give exactly one of pose (a 4x4 matrix) and ros_pose (position, orientation, frame_id)")
        if self.pushes_left is not None and self.policy != "value_iteration":
            raise ValueError(f"pushes_left plans by value iteration for a budget; it cannot be combined with policy {self.policy}")
        if self.failed_actions and self.policy == "max_height":
            raise ValueError("max_height has one push per pose and nothing to choose after it fails; give failed_actions "
                             "with greedy or value_iteration")
        return self

    def observed(self) -> np.ndarray:
        """(4, 4) float, object frame -> world frame, from whichever form was given."""
        return np.asarray(self.pose, dtype=np.float64) if self.pose is not None else self.ros_pose.matrix()


class PoseMatch(Answer):
    pose: int = Field(description="Matched stable pose")
    angle_error: float = Field(description="rad, between the observed and the stable pose's down vectors")
    tolerance: float = Field(description="rad, largest angle_error that matches")
    yaw: float = Field(description="rad, rotation about world z of the pose frame, in (-pi, pi]")
    translation: Vector2 = Field(description="m, world x, y of the pose frame's origin (below the centre of mass)")
    z_offset: float = Field(
        description="m, observed height of the pose frame's origin (the support point under the centre of mass) "
        "above z = 0; |z_offset| <= height_tolerance, else the answer is 409 off_table"
    )
    height_tolerance: float = Field(description="m, largest |z_offset| accepted")
    planar: Matrix4 = Field(description="pose frame -> world frame, the planar part only: rotation yaw about z, translation in x, y")
    pose_to_world: Matrix4 = Field(
        description="pose frame -> world frame as observed (observed pose @ inverse of the stable pose's transform): "
        "planar plus the observed tilt and z_offset. Pushes and grasps are placed through it, so they lie on "
        "the object's surface as observed"
    )


class WorldPush(Answer):
    """A push in the world frame, ready to execute."""

    point: Vector3 = Field(description="m, contact point")
    normal: Vector3 = Field(description="outward unit surface normal at the contact")
    direction: Vector3 = Field(description="unit push direction")
    start: Vector3 = Field(description="m, start of the finger's line: point + approach_offset * normal")
    end: Vector3 = Field(description="m, end of the finger's line: point - push_depth * normal")
    approach_offset: float = Field(description="m, manifest contacts.approach_offset")
    push_depth: float = Field(description="m, manifest contacts.push_depth")
    required_force: float | None = Field(
        description="N, mean least push force that topples the object over its trials (dataset mean_force); "
        "null when no trial toppled it"
    )
    finger_force_limit: float = Field(description="N, largest force the finger may apply (see docs/SERVICE.md)")
    within_force_limit: bool | None = Field(description="required_force <= finger_force_limit; null when required_force is null")


Decision = Literal["push", "grasp", "no_grasp"]
"""What to do: ``push`` (then look again), ``grasp`` now at ``grasp``, or ``no_grasp``: the
policy does not push and this pose has no suction grasp (V_s = 0): neither helps."""


class PlanResponse(Answer):
    """Every value field means the same for every policy; the policy only chooses ``action``."""

    object_id: str
    policy: Policy
    pushes_left: int | None = Field(description="The request's budget (the push is chosen for it); null when none was given")
    frame_id: str = Field(description="Frame of every world quantity here (the table frame, z up, table z = 0)")
    match: PoseMatch
    decision: Decision = Field(description="push, grasp (now, at grasp) or no_grasp (no push and no grasp: V_s = 0)")
    reason: str = Field(description="One sentence: why this decision, with the values behind it")
    action: int | None = Field(description="The policy's action in the matched pose; null when it does not push")
    ruled_out: int = Field(
        description="Candidates of the matched pose the policy could choose that the request's failed_actions rule out "
        "(each failed push and its neighbourhood); it chose among the others. 0 without failed_actions"
    )
    v_s: float = Field(description="V_s of the matched pose: robust suction grasp quality of grasping now, in [0, 1]")
    v_t: float = Field(description="V_T of the matched pose: its value under value iteration, max(V_s, gamma max_u Q_T); "
                       "V0 of docs/MODEL.md (12.13) in a build that believes failures")
    q_value: float | None = Field(
        description="Q_T(pose, action) of the push: expected V_T of the next pose, before the push's discount gamma (in a build "
        "with mdp.retry_failed false, the pose itself counted at its grasp V_s should the push fail; in a build that believes "
        "failures, at its failed state's value V1: Q0 of docs/MODEL.md (12.13), also after failed_actions); null when no push"
    )
    expected_v_s_after: float | None = Field(
        description="Expected V_s of the next pose after the push, sum_x' P(x' | pose, action) V_s(x'); null when no push"
    )
    expected_v_s_final: float | None = Field(
        description="With pushes_left: the expected V_s when the budget is spent, pushing as value iteration for the "
        "budget does and grasping then; null without pushes_left or when no push"
    )
    p_topple: float | None = Field(description="P(next pose != pose) of the push; null when no push")
    p_topple_neighbourhood: float | None = Field(
        description="Mean p_topple of this pose's ok candidate pushes within 2 cm (contact) and 0.5 rad (direction) of "
        "the push, itself included: a cautious estimate that choosing the best of ~1,000 candidates cannot inflate. "
        "In simulated physics on held-out objects it ran 0.07-0.10 below the topple rate of value iteration's "
        "pushes, and p_topple 0.02-0.06 above it (docs/VALIDATION.md, 'Pushes for a budget'); null when no push"
    )
    p_topple_given_failures: float | None = Field(
        description="With failed_actions: P(topple) of this push now that the reported pushes have failed, p_topple^k "
        "(k the build's mdp.after_failure_power, fitted and judged on value iteration's pushes: docs/VALIDATION.md, "
        "'After a failed push'). A failure says the pose topples less than the table thinks: value iteration's first "
        "tries are honest, the pushes after a failure topple far less than p_topple (p_topple^k ran 0.04 under the topple "
        "rate of value iteration's 943 after-failure pushes on 205 held-out objects, p_topple 0.10 over: docs/VALIDATION.md, "
        "'A failure weighed by its push'). Null without failed_actions, without a push, or for a build without the map "
        "(k = 1, as the thesis preset, or from before it)"
    )
    push: WorldPush | None = Field(description="The push in world coordinates; null when no push")
    next_poses: list[NextPose] = Field(description="Where the push leads; empty when no push")
    grasp: Grasp | None = Field(
        description="The matched pose's best suction grasp, world frame (execute it when decision is grasp); null when none"
    )


class PlanBatch(Model):
    items: list[PlanRequest] = Field(max_length=MAX_BATCH)


class ItemError(Answer):
    status: int = Field(description="HTTP status the item would have had alone: 404, 409, or 422 for a ros_pose in an unknown frame")
    detail: str
    reason: Literal["no_stable_pose", "off_table"] | None = Field(
        None, description="A 409's cause, as the single route's body names it; left out of the other errors")


class TransitionResult(Answer):
    """One batch item: exactly one of ``result`` and ``error`` is set."""

    result: ActionDetail | None = None
    error: ItemError | None = None


class TransitionResults(Answer):
    results: list[TransitionResult]


class PlanResult(Answer):
    """One batch item: exactly one of ``result`` and ``error`` is set."""

    result: PlanResponse | None = None
    error: ItemError | None = None


class PlanResults(Answer):
    results: list[PlanResult]


# --- heap planning (thesis chapter 3) ------------------------------------------------

HeapPolicy = Literal["quasi_random", "boundary_shear", "free_space", "max_clearance", "cluster_diffusion"]
"""The planar push policies of thesis 3.2 (``clutter.policies.POLICIES``, the same names in its order)."""

MAX_HEAP_OBJECTS = 100
"""Most objects in one heap request; more is a 422."""

MAX_BIN_SIZE = 5.0
"""m, largest bin length, width or height accepted (a bound on the planner's floor grid)."""

BIN_TOLERANCE = 0.005
"""m, how far an object's hull may reach past a wall of the bin or below its floor and still count
as in the bin (perception error, as ``HEIGHT_TOLERANCE``); further is a 409."""

BinLength = Annotated[float, Field(gt=0, le=MAX_BIN_SIZE, strict=True, allow_inf_nan=False)]


class HeapBin(Model):
    """The bin (an open box), world frame: inner floor centred on the origin, z up, floor at z = 0,
    x along its length.  The defaults are ``clutter.state.Bin``'s, a common picking tote."""

    length: BinLength = Field(0.50, description="m, inner floor length, along world x")
    width: BinLength = Field(0.40, description="m, inner floor width, along world y")
    height: BinLength = Field(0.15, description="m, wall height")
    wall: BinLength = Field(0.01, description="m, wall thickness")


class HeapObject(Model):
    """One object of the heap: exactly one of ``pose`` and ``ros_pose`` (as in PlanRequest)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"oneOf": [{"required": ["pose"]}, {"required": ["ros_pose"]}]})

    object_id: Text = Field(description="Dataset object id (its hull and centre of mass come from the dataset)")
    pose: RigidTransform = Field(None, description="Object frame -> world frame (the bin frame), 4x4 row-major; give this or ros_pose")
    ros_pose: RosPose = Field(None, description="The same as ROS sends it (position, orientation x, y, z, w, frame_id); give this or pose")

    @model_validator(mode="after")
    def _one_pose(self) -> HeapObject:
        if (self.pose is None) == (self.ros_pose is None):
            raise ValueError("give exactly one of pose (a 4x4 matrix) and ros_pose (position, orientation, frame_id)")
        return self

    def observed(self) -> np.ndarray:
        """(4, 4) float, object frame -> world frame, from whichever form was given."""
        return np.asarray(self.pose, dtype=np.float64) if self.pose is not None else self.ros_pose.matrix()


MAX_SEED = 2**53 - 1
"""The largest ``HeapPlanRequest.seed``."""


class HeapPlanRequest(Model):
    """A heap of objects in a bin and the push policy to plan with."""

    bin: HeapBin = Field(default_factory=HeapBin, description="The bin; omitted: the default tote")
    objects: list[HeapObject] = Field(min_length=1, max_length=MAX_HEAP_OBJECTS, description="The objects in the bin (an id may repeat)")
    policy: HeapPolicy = Field("boundary_shear", description="Push policy (thesis 3.2); boundary_shear ran on the physical robot (3.3.2)")
    # At most 2**53 - 1: the largest integer a JSON number keeps exactly in every client (a
    # JavaScript number, a float64), and so in FastAPI's OpenAPI document, which writes bounds as floats.
    seed: StrictInt = Field(0, ge=0, le=MAX_SEED, description="Seed of quasi_random's draws (the same seed, the same push)")


class HeapPush(Answer):
    """A straight finger stroke, world frame: the finger comes down at ``start`` and moves to ``end``."""

    target: int = Field(description="Index of the pushed object in the request's objects")
    object_id: str
    start: Vector3 = Field(description="m, where the finger's axis starts (a finger radius clear of every object)")
    end: Vector3 = Field(description="m, where it stops")
    direction: Vector3 = Field(description="unit, start -> end (horizontal)")
    length: float = Field(description="m, |end - start|")


class HeapPlanResponse(Answer):
    """The policy's push, or ``push`` null when it finds no collision-free one (thesis 3.4)."""

    policy: HeapPolicy
    frame_id: str = Field(description="Frame of start and end (the service's world frame: the bin's, z up, floor z = 0)")
    found: bool = Field(description="Whether the policy found a collision-free push")
    reason: str = Field(description="One sentence: what was pushed and why, or why nothing is")
    push: HeapPush | None = Field(description="The push; null when found is false")
    finger_radius: float = Field(description="m, finger radius the push was planned for")
    push_length: float = Field(description="m, how far the finger goes on past the object's footprint (before clipping to the bin)")
    approach_offset: float = Field(description="m, how far outside the object's footprint the finger starts")


class OutsideBinBody(ErrorBody):
    """409: an object reaches past a wall of the bin or below its floor by more than the tolerance."""

    reason: Literal["outside_bin", "below_floor"]
    index: int = Field(description="Index of the object in the request's objects")
    object_id: str
    distance: float = Field(description="m, how far its hull reaches past the wall (outside_bin) or below z = 0 (below_floor)")
    tolerance: float = Field(description="m, the largest distance accepted (BIN_TOLERANCE)")
