"""One object, end to end: the unit of work the dataset job fans out.

load + validate -> stable poses -> per pose: candidate pushes, toppling model,
suction quality -> value iteration and policies.  Every random draw comes from a
stream of (seed, object id, pose), so the result does not depend on which worker
runs it.
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from typing import Protocol

import numpy as np

from schema import horizon, retry
from schema.api import check_rigid, height_in_mm, rests_on_table
from schema.frames import PoseMatch, match_pose, place_push, transform_points
from schema.neighbourhood import neighbour_mean
from schema.vocabulary import NO_OP, POLICIES, STATUS_NAMES, STATUS_OK

from .collision import collision_object
from .config import Config, ContactConfig, field_range
from .contacts import explicit_actions, object_contacts, pose_actions, with_probes
from .mdp import pose_values
from .mesh import ObjectModel, load_mesh
from .outcomes import Actions, ObjectResult, PolicyChoice, PoseValues, StablePose, SuctionResult, ToppleTable
from .poses import PoseSet, stable_poses
from .rng import stream
from .suction import suction_quality
from .topple import evaluate_pose


class Spec(Protocol):
    """What the job needs to know of a corpus entry (``pipeline.build.corpus.ObjectSpec``)."""

    object_id: str
    path: str
    scale: float
    mass: float


@contextmanager
def _stage(timings: dict[str, float], name: str) -> Iterator[None]:
    start = time.process_time()
    try:
        yield
    finally:
        timings[name] = timings.get(name, 0.0) + time.process_time() - start


class _PoseClock:
    """Wall-clock seconds of each timed step, appended per name; does nothing without a dict."""

    def __init__(self, seconds: dict[str, list[float]] | None):
        self.seconds = seconds

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        if self.seconds is None:
            yield
            return
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds.setdefault(name, []).append(time.perf_counter() - start)


def load_object(spec: Spec, config: Config) -> ObjectModel:
    """The spec's mesh, validated; raises ``MeshError`` with a one-line reason (a size
    error's unit hint names the corpus's settings too: this is a corpus object)."""
    return load_mesh(spec.path, scale=spec.scale, mass=spec.mass, name=spec.object_id, config=config.mesh, corpus_hint=True)


def pose_suction(obj: ObjectModel, pose: StablePose, config: Config) -> SuctionResult:
    """V_s and the best suction grasp of one pose (pose frame)."""
    mesh = obj.mesh.copy()
    mesh.apply_transform(pose.transform)
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    rng = stream(config.seed, obj.name, pose.index, "suction")
    return suction_quality(mesh, center_mass, obj.mass, config.suction, rng, config.topple.gravity)


def process_object(spec: Spec, config: Config) -> ObjectResult:
    """Evaluate every stable pose of one corpus object (CPU seconds per stage in ``timings``)."""
    timings: dict[str, float] = {}
    with _stage(timings, "load"):
        obj = load_object(spec, config)
    return evaluate_object(obj, config, object_id=spec.object_id, timings=timings)


def evaluate_object(
    obj: ObjectModel,
    config: Config = Config(),
    *,
    object_id: str | None = None,
    timings: dict[str, float] | None = None,
    pose_seconds: dict[str, list[float]] | None = None,
) -> ObjectResult:
    """One loaded object end to end, exactly as the dataset job computes it: stable
    poses, each pose's candidate pushes and toppling table, V_s and best grasp, value
    iteration and the three policies.

    object_id : the id in the result (default ``obj.name``); random streams use ``obj.name``
    timings : dict to add CPU seconds per stage to
    pose_seconds : if given, wall seconds per pose are appended under ``actions``, ``topple``
      and ``suction``, and per object under ``shared_contacts`` and ``mdp`` (``make bench``)
    """
    timings = {} if timings is None else timings
    clock = _PoseClock(pose_seconds)
    with _stage(timings, "poses"):
        pose_set = stable_poses(obj, config.poses)
    poses = pose_set.poses
    with _stage(timings, "contacts"):
        with clock("shared_contacts"):
            points, normals = object_contacts(obj, config.contacts, config.seed)
            mesh_collision = collision_object(obj.mesh)
        actions = []
        for p in poses:
            with clock("actions"):
                actions.append(pose_actions(points, normals, obj.mesh, mesh_collision, p.transform, config.contacts))
    with _stage(timings, "topple"):
        tables = []
        for p, a in zip(poses, actions):
            with clock("topple"):
                tables.append(evaluate_pose(obj, p, pose_set.probabilities, a, config.topple,
                                            stream(config.seed, obj.name, p.index, "trials")))
    with _stage(timings, "suction"):
        suction = []
        for p in poses:
            with clock("suction"):
                suction.append(pose_suction(obj, p, config))
    with _stage(timings, "mdp"), clock("mdp"):
        choosable = _choosable(actions, config.mdp.min_direction_z)
        values = pose_values(
            [t.next_pose for t in tables],
            np.array([s.quality for s in suction]),
            [a.max_height for a in actions],
            config.mdp,
            choosable,
            [(a.points, a.directions) for a in actions],
        )
    return ObjectResult(
        object_id=object_id or obj.name,
        mass=obj.mass,
        center_mass=obj.center_mass,
        hull_vertices=np.asarray(obj.hull.vertices),
        hull_faces=np.asarray(obj.hull.faces),
        repairs=obj.repairs,
        poses=poses,
        actions=actions,
        topple=tables,
        suction=suction,
        values=values,
        timings=timings,
        equivalent_transforms=pose_set.equivalents,
        choosable=choosable,
    )


def select_info(spec: Spec, config: Config) -> tuple[np.ndarray, np.ndarray]:
    """What the thesis 4.4.1 selection rule needs: V_s and COM height of every pose.

    returns : v_s (P,) float, com_heights (P,) float, m
    """
    obj = load_object(spec, config)
    poses = stable_poses(obj, config.poses).poses
    return (
        np.array([pose_suction(obj, p, config).quality for p in poses]),
        np.array([p.com_height for p in poses]),
    )


@dataclass
class PoseEvaluation:
    """Candidate pushes of one pose and what the toppling model says of them."""

    pose: int
    actions: Actions
    table: ToppleTable

    def transitions(self) -> list[tuple[int, int, float]]:
        """Long form (action, next_pose, probability) over ``ok`` actions, nonzero probabilities only."""
        rows, cols = np.nonzero(np.nan_to_num(self.table.next_pose) > 0)
        return [(int(a), int(x), float(self.table.next_pose[a, x])) for a, x in zip(rows, cols)]

    def status_names(self) -> list[str]:
        return [STATUS_NAMES[s] for s in self.actions.status]


def evaluate(
    obj: ObjectModel,
    poses: PoseSet,
    pose: int,
    *,
    points: np.ndarray | None = None,
    directions: np.ndarray | None = None,
    n_contacts: int | None = None,
    n_trials: int | None = None,
    variant: str | None = None,
    seed: int | None = None,
    config: Config = Config(),
) -> PoseEvaluation:
    """Evaluate the toppling model on one stable pose.

    pose : which of ``poses``, 0 to P - 1 (an int or numpy integer)
    points, directions : optional explicit pushes, (A, 3) finite, pose frame (z up, table at z = 0, centre of
      mass over the origin), points in m, on the surface within ``contacts.SNAP_TOLERANCE`` (1 mm; each is
      snapped to the closest surface point), directions non-zero, one per point; otherwise the
      pose's ``n_contacts`` candidates plus the Max-Height action.  A model that smooths or maps
      its rows over the candidates (the default) predicts each push among them, as the dataset
      does: a push that is an ok candidate (within 1e-6) gets its row, any other is averaged over
      the candidates and itself (docs/MODEL.md C.12, "Probes"), its noise drawn after theirs in the
      order given
    n_contacts, n_trials, variant : override ``config.contacts`` / ``config.topple`` (n_contacts within the
      range the config accepts, 1 to 100,000)
    seed : root of the random streams (same seed, same result); default ``config.seed``, the
      dataset's, so that a push is predicted as the dataset built with ``config`` predicts it.  With
      the default model, explicit pushes cost a whole pose's evaluation (a few tenths of a second):
      ask about many pushes of a pose in one call
    Raises ValueError, saying what was wrong, for anything else.
    """
    pose = pose_index(pose, poses)
    seed = config.seed if seed is None else seed
    contact_config = config.contacts if n_contacts is None else replace(config.contacts, n_contacts=contacts_count(n_contacts))
    topple_config = config.topple
    if n_trials is not None or variant is not None:
        topple_config = replace(
            topple_config,
            n_trials=topple_config.n_trials if n_trials is None else n_trials,
            variant=topple_config.variant if variant is None else variant,
        )
    stable = poses.poses[pose]
    # Explicit pushes are checked (``contacts.push_arrays``) and snapped before the pose's candidates cost anything;
    # the points as given are what ``with_probes`` matches to the candidates.
    pushes = None if points is None else explicit_actions(obj, stable.transform, points, directions)
    trials = stream(seed, obj.name, pose, "trials")
    if points is None or topple_config.needs_candidates:
        contacts, normals = object_contacts(obj, contact_config, seed)
        candidates = pose_actions(contacts, normals, obj.mesh, collision_object(obj.mesh), stable.transform, contact_config)
    if pushes is None:
        table = evaluate_pose(obj, stable, poses.probabilities, candidates, topple_config, trials)
        return PoseEvaluation(pose=pose, actions=candidates, table=table)
    if not topple_config.needs_candidates:  # each push's row is its own trials alone
        return PoseEvaluation(pose=pose, actions=pushes, table=evaluate_pose(obj, stable, poses.probabilities, pushes, topple_config, trials))
    # A model that smooths or maps a row over the pose's candidates (docs/MODEL.md C.12-C.19) predicts a push among
    # them, as the dataset does: a push that is a candidate gets that candidate's row, any other is a probe.
    evaluated, n_candidates, rows = with_probes(candidates, pushes, points, pushes.directions)
    table = evaluate_pose(obj, stable, poses.probabilities, evaluated, topple_config, trials, candidates=n_candidates)
    return PoseEvaluation(pose=pose, actions=pushes, table=table_rows(table, rows))


def table_rows(table: ToppleTable, rows: np.ndarray) -> ToppleTable:
    """The rows ``rows`` of a pose's table, its edges' landings as they are."""
    return replace(table, next_pose=table.next_pose[rows], p_topple=table.p_topple[rows],
                   mean_force=table.mean_force[rows], outcomes=table.outcomes[rows])


def grasp_quality(obj: ObjectModel, poses: PoseSet, pose: int, config: Config = Config()) -> SuctionResult:
    """V_s and the best suction grasp (pose frame) of one stable pose (``pose`` : 0 to P - 1)."""
    return pose_suction(obj, poses.poses[pose_index(pose, poses)], config)


def pose_index(pose, poses: PoseSet) -> int:
    """``pose`` as an int when it names one of ``poses``' P stable poses (0 to P - 1; a numpy integer
    will do), else ValueError.  A negative index would silently name a pose from the end."""
    count = len(poses.poses)
    if not _whole(pose) or not 0 <= pose < count:
        raise ValueError(f"pose must be an integer from 0 to {count - 1} (the object has {count} stable poses), got {pose!r}")
    return int(pose)


def contacts_count(n_contacts) -> int:
    """``n_contacts`` as an int when ``config.contacts.n_contacts`` accepts it (the range the config
    and the CLI check, ``ContactConfig``'s field), else ValueError."""
    accepted = field_range(ContactConfig, "n_contacts")
    if not _whole(n_contacts) or not accepted.contains(n_contacts):
        raise ValueError(f"n_contacts must be an integer {accepted.text()}, got {n_contacts!r}")
    return int(n_contacts)


def _whole(value) -> bool:
    """Whether ``value`` is an integer, Python's or numpy's, and not a bool (which Python counts as one)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_))


def solve(evaluations: list["PoseEvaluation"], v_s: np.ndarray, config: Config = Config()) -> list[PoseValues]:
    """Value iteration and the three policies over ``evaluate``'s tables, one per pose
    in pose order (``v_s`` : (P,) float, each pose's V_s)."""
    if [e.pose for e in evaluations] != list(range(len(v_s))):
        raise ValueError("solve needs one evaluation per stable pose, in pose order")
    return pose_values(
        [e.table.next_pose for e in evaluations], np.asarray(v_s, dtype=float),
        [e.actions.max_height for e in evaluations], config.mdp, _choosable([e.actions for e in evaluations], config.mdp.min_direction_z),
        [(e.actions.points, e.actions.directions) for e in evaluations],
    )


def _choosable(actions: list[Actions], min_direction_z: float) -> list[np.ndarray]:
    """Per pose, (A_x,) bool: the pushes with u_z at least ``min_direction_z``: ``mdp.min_direction_z``
    for greedy and value iteration, ``mdp.budget_min_direction_z`` for a budget (``pushes_left``)."""
    return [horizon.choosable_pushes(a.directions[:, 2], min_direction_z) for a in actions]


# --- an observed pose: match it, and the policy's push in the world --------------------------

DEFAULT_HEIGHT_TOLERANCE = 0.01
"""m; an observed pose whose support plane is further than this from the table is not resting on it."""


@dataclass
class ObservedPose(PoseMatch):
    """``schema.frames.PoseMatch`` plus where the matched pose stands in the world.

    pose_to_world : (4, 4) float, pose frame -> world (``observed @ inverse(transform)``)
    z_offset : float, m, height of the pose's support plane above the table (0 when resting on it)
    """

    pose_to_world: np.ndarray = field(default_factory=lambda: np.eye(4))
    z_offset: float = 0.0


def observe(
    observed: np.ndarray,
    poses: list[StablePose] | PoseSet,
    tolerance: float | None = None,
    table_height: float = 0.0,
    config: Config = Config(),
) -> ObservedPose:
    """Match an observed 4x4 pose (object -> world, z up) to the nearest stable pose.

    observed : (4, 4) finite rigid transform (rotation block orthonormal with det +1 within
      ``schema.api.ROTATION_TOLERANCE``, last row [0, 0, 0, 1]), else ValueError in the service's words
      (``schema.api.check_rigid``)
    poses : the stable poses, or a ``PoseSet`` (whose merged symmetric orientations also match)
    tolerance : rad, largest angle between down vectors (default ``config.poses.same_pose_angle``, 10 deg)
    table_height : m, the table's z in the world frame; ``z_offset`` is measured from it
    """
    observed = np.asarray(observed, dtype=float)
    if observed.shape != (4, 4) or not np.all(np.isfinite(observed)):
        raise ValueError("observed must be a finite (4, 4) object-to-world transform")
    try:  # the service's check: a reflection or a scaled matrix would match some pose, wrongly placed
        check_rigid(observed.tolist())
    except ValueError as error:
        raise ValueError(f"observed is no rigid object-to-world transform: {error}") from None
    tolerance = config.poses.same_pose_angle if tolerance is None else tolerance
    if isinstance(poses, PoseSet):
        downs, transforms, owner = poses.match_arrays()
    else:
        downs, transforms = np.array([p.down for p in poses]), np.array([p.transform for p in poses])
        owner = np.arange(len(poses))
    match = match_pose(observed, downs, transforms, np.inf)  # the nearest pose, whatever its angle
    pose_to_world = observed @ np.linalg.inv(transforms[match.pose])
    return ObservedPose(
        pose=int(owner[match.pose]) if match.angle_error <= tolerance else -1,
        angle_error=match.angle_error,
        yaw=match.yaw,
        translation=match.translation,
        planar=match.planar,
        pose_to_world=pose_to_world,
        z_offset=float(pose_to_world[2, 3] - table_height),
    )


@dataclass
class Plan:
    """A policy's decision for an observed pose, in world coordinates.

    match : ObservedPose (pose index, angle error, yaw, z_offset, pose_to_world)
    action : int or None; None means do not push (grasp now, at ``grasp``)
    value : float, the policy's expected value (V_s when it does not push)
    p_topple : float or None, probability that the push topples the object
    push : dict of (3,) world arrays ``point``, ``normal``, ``direction``, ``start``
      (``approach_offset`` out along the normal) and ``end`` (``push_depth`` in), or None
    next_poses : [(pose, probability), ...] after the push, most likely first
    grasp : (point (3,), axis (3,)) world, the best suction grasp in this pose, or None
    p_topple_neighbourhood : float or None, the mean P(topple) of the pose's ok candidates
      around the push (``schema.neighbourhood``; what /plan reports under the same name)
    ruled_out : int, candidates of the pose that ``failed_actions`` ruled out (``schema.retry``)
    p_topple_given_failures : float or None, with ``failed_actions``: P(topple)^k now that pushes
      from the pose have failed (``mdp.after_failure_power``; /plan's field of the same name)
    """

    match: ObservedPose
    policy: str
    action: int | None
    value: float
    p_topple: float | None
    push: dict[str, np.ndarray] | None
    next_poses: list[tuple[int, float]]
    grasp: tuple[np.ndarray, np.ndarray] | None
    p_topple_neighbourhood: float | None = None
    ruled_out: int = 0
    p_topple_given_failures: float | None = None


class NotResting(ValueError):
    """The observed pose is no stable pose, or not on the table (one-line message)."""


def plan(
    result: ObjectResult,
    observed: np.ndarray,
    policy: str = "value_iteration",
    tolerance: float | None = None,
    table_height: float = 0.0,
    height_tolerance: float = DEFAULT_HEIGHT_TOLERANCE,
    config: Config = Config(),
    pushes_left: int | None = None,
    failed_actions: Sequence[int] = (),
) -> Plan:
    """What ``policy`` (``max_height``, ``greedy``, ``value_iteration``) does for the object
    of ``result`` observed at ``observed`` (4x4, object -> world, z up, table at ``table_height``).
    With ``pushes_left`` (1 to ``schema.horizon.MAX_PUSHES_LEFT``, value_iteration only), value
    iteration's push for that budget (``schema.horizon``, as /plan's ``pushes_left``; over fresh
    and failed-here states, (12.14), when ``config`` plans with failures); the plan's ``value``
    is then the expected V_s when the budget is spent.  With
    ``failed_actions`` (actions of the matched pose that left the object in it; greedy and
    value_iteration), the policy's push among the candidates they do not rule out, and
    ``p_topple_given_failures`` (``schema.retry``, as /plan's ``failed_actions``; k is
    ``config``'s ``mdp.after_failure_power``, none when it is 1).  Value iteration then ranks
    them by what it believes of them (``retry.ranking_values``: Q1 of docs/MODEL.md (12.13) when
    the config believes failures, the default, else (12.12)), and the plan's ``value`` is that belief.
    ``config`` must be the one ``result`` was evaluated with: its ``mdp`` section says how the
    stored Q was solved, and Q1 read off a Q solved otherwise is no belief.

    Raises ``NotResting`` when the orientation is within ``tolerance`` of no stable pose
    or the pose's support plane is more than ``height_tolerance`` from the table (the edge
    included, ``schema.api.rests_on_table``).
    """
    if policy not in POLICIES:
        raise ValueError(f"unknown policy {policy!r}; choose one of {', '.join(POLICIES)}")
    if pushes_left is not None and (policy != "value_iteration" or not 1 <= pushes_left <= horizon.MAX_PUSHES_LEFT):
        raise ValueError(f"pushes_left must be 1..{horizon.MAX_PUSHES_LEFT} with policy value_iteration, "
                         f"got {pushes_left!r} with {policy}")
    failed = [int(a) for a in failed_actions]
    if failed and policy == "max_height":
        raise ValueError("max_height has one push per pose; give failed_actions with greedy or value_iteration")
    # A symmetric object's merged turns of a pose match too (PoseSet.match_arrays).
    candidates = result.poses if result.equivalent_transforms is None else PoseSet(
        result.poses, np.empty(0, dtype=int), result.equivalent_transforms)
    match = observe(observed, candidates, tolerance, table_height, config)
    if not match.matched:
        raise NotResting(
            f"{result.object_id}: the observed orientation is no stable pose "
            f"(nearest {np.degrees(match.angle_error):.1f} deg away)"
        )
    if not rests_on_table(match.z_offset, height_tolerance):
        raise NotResting(f"{result.object_id}: observed {height_in_mm(match.z_offset, height_tolerance)} mm off the table")
    pose = match.pose
    rotation, origin = match.pose_to_world[:3, :3], match.pose_to_world[:3, 3]
    suction = result.suction[pose]
    grasp = None
    if np.all(np.isfinite(suction.point)):
        grasp = (rotation @ suction.point + origin, rotation @ suction.axis)
    choice = result.values[pose].policies[policy]
    v_s = np.array([s.quality for s in result.suction], dtype=float)
    budget = None  # with pushes_left: the tables in the budgets' layout, V0_h and V1_h for h = 1..pushes_left
    if pushes_left is not None:
        csr = horizon.csr_from_rows([np.asarray(t.next_pose, dtype=float) for t in result.topple])
        # The pushes a budget may choose (mdp.budget_min_direction_z; the policies' own cut may be narrower).
        choosable = np.concatenate(_choosable(result.actions, config.mdp.budget_min_direction_z))
        actions, values, failed_values = horizon.solve_budgets(v_s, csr, pushes_left, config.mdp.failure_power, choosable)
        choice = PolicyChoice(int(actions[-1, pose]), float(values[-1, pose]))
        budget = csr, values, failed_values
    ruled = 0
    if failed:
        choice, ruled = _untried_choice(result, pose, policy, failed, v_s, budget, config)
    if choice.action == NO_OP:
        return Plan(match, policy, None, float(choice.value), None, None, [], grasp, ruled_out=ruled)
    actions, table = result.actions[pose], result.topple[pose]
    a = int(choice.action)
    push = place_push(
        match.pose_to_world, actions.points[a], actions.normals[a], actions.directions[a],
        config.contacts.approach_offset, config.contacts.push_depth,
    )
    distribution = np.nan_to_num(np.asarray(table.next_pose[a], dtype=float))
    order = np.argsort(-distribution, kind="stable")
    next_poses = [(int(x), float(distribution[x])) for x in order if distribution[x] > 0]
    near, _ = neighbour_mean(actions.points, actions.directions, table.p_topple, rows=[a])
    p_topple = float(table.p_topple[a])
    # k is the caller's config's, as everything ``evaluate_object`` was given.
    given = retry.given_failures(p_topple, config.mdp.after_failure_power) if failed else None
    return Plan(match, policy, a, float(choice.value), p_topple, push, next_poses, grasp, float(near[0]), ruled, given)


def _untried_choice(result: ObjectResult, pose: int, policy: str, failed: list[int], v_s: np.ndarray,
                    budget: tuple | None, config: Config) -> tuple[PolicyChoice, int]:
    """``plan``'s choice among the candidates of ``pose`` that no failed push rules out, by the
    policy's rule (/plan's ``service.planning.untried_push``, on the in-memory result).

    v_s : (P,) float;  budget : None, or with pushes_left h the object's tables in the budgets'
      layout (``horizon.csr_from_rows``), V0_1..V0_h and V1_1..V1_h ((h, P) each,
      ``horizon.belief_budget_choices``; both ``horizon.budget_choices``' V_h when the config
      does not plan with failures)
    returns : the choice (value: value iteration's Q1, (12.13), or Q'', (12.12), or Q_T when k is 1; greedy's
      E[V_s]; with a budget Q1_h (12.14), or V_h when the config does not plan with failures; V_s(x) for no push)
      and the number of candidates ruled out
    """
    actions, values = result.actions[pose], result.values[pose]
    count = len(actions.status)
    impossible = retry.impossible_failure(failed, actions.status == STATUS_OK)
    if impossible is not None:
        _, action, exists = impossible
        if not exists:
            raise ValueError(f"failed_actions [{action}] are no actions of pose {pose} (0..{count - 1})")
        raise ValueError(f"failed_actions [{action}] of pose {pose} are not ok: no policy pushes them, so they cannot have failed")
    if budget is not None:
        choosable = _choosable([actions], config.mdp.budget_min_direction_z)[0]
    else:
        choosable = np.ones(count, dtype=bool) if result.choosable is None else result.choosable[pose]
    stay = float(v_s[pose])
    if budget is not None:
        (action_offsets, transition_offsets, next_pose, probability), fresh, failed_values = budget
        rows = slice(int(action_offsets[pose]), int(action_offsets[pose + 1]))
        q = horizon.budget_q(v_s, fresh, failed_values, len(fresh), pose, rows, transition_offsets, next_pose, probability,
                             config.mdp.failure_power, after_failure=True)
        improvement, scale = horizon.IMPROVEMENT, 1.0
    elif policy == "greedy":
        q, improvement, scale = values.greedy, retry.POLICY_IMPROVEMENT, 1.0
    else:
        q = retry.ranking_values(values.q, result.topple[pose].p_topple, stay, float(values.value),
                                 config.mdp.after_failure_power, config.mdp.retry_failed,
                                 believes=config.mdp.believe_failures, gamma=config.mdp.gamma, choosable=choosable)
        improvement, scale = retry.POLICY_IMPROVEMENT, config.mdp.gamma
    action, ruled = retry.choose_untried(q, actions.points, actions.directions, failed, choosable, stay, improvement, scale)
    return (PolicyChoice(NO_OP, stay) if action == NO_OP else PolicyChoice(action, float(q[action]))), ruled
