"""What one object's evaluation produces: the contract between the model
(poses, topple model, suction, MDP) and the build (rows, shards, manifest).
Status codes, policy names and outcome codes are ``schema.vocabulary``'s.

Frames: "object" is the mesh's own frame (metres); "pose" is the canonical frame
of one stable pose: z up, table at z = 0, centre of mass over the origin.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class StablePose:
    """One stable resting pose of an object.

    index : int, position in the object's pose list (sorted by probability, descending)
    down : (3,) float, unit vector in the object frame pointing down onto the table
    probability : float, probability of resting in this pose when dropped (Goldberg et al.)
    transform : (4, 4) float, object frame -> pose frame
    height : float, m, top of the object above the table in this pose
    com_height : float, m, centre of mass above the table
    base_edges : (E, 2, 3) float, m, pose frame, counter-clockwise seen from above
    edge_final_pose : (E,) int, pose reached by toppling over each edge
      (this pose's own index when the topple is blocked)
    edge_blocked : (E,) bool, another part of the hull meets the table before the apex
    apex_angle : (E,) float, rad, rotation about the edge that brings the COM above it
    edge_rolled_pose : (E,) int, pose reached with the ``rolling`` correction (MODEL.md C.6):
      as ``edge_final_pose``, but a blocked topple rolls on while the finger pushes
    edge_momentum_pose : (E,) int, pose reached with the ``momentum`` correction (MODEL.md C.8):
      as ``edge_final_pose``, but the energy of the fall may roll the object on past shallow poses
    edge_onward_pose : (E,) int, the pose one fall beyond ``edge_momentum_pose``, over its edge
      ahead, where the fall's energy fell short of the rise (MODEL.md C.18); ``edge_momentum_pose``
      itself where nothing lies ahead, where the pose set left out the onward pose (or the
      momentum pose), for blocked edges and for edges back into this pose
    """

    index: int
    down: np.ndarray
    probability: float
    transform: np.ndarray
    height: float
    com_height: float
    base_edges: np.ndarray
    edge_final_pose: np.ndarray
    edge_blocked: np.ndarray
    apex_angle: np.ndarray
    edge_rolled_pose: np.ndarray
    edge_momentum_pose: np.ndarray
    edge_onward_pose: np.ndarray


@dataclass
class Actions:
    """Candidate pushes of one pose, in the pose frame.

    points : (A, 3) float, m, contact points
    normals : (A, 3) float, outward unit surface normals
    directions : (A, 3) float, unit push directions (default -normals)
    status : (A,) int8, ``STATUS_*`` codes
    max_height : int, index of the Max-Height baseline's action (the last one), or -1 if the
      pose has no surface point with a near-horizontal normal
    """

    points: np.ndarray
    normals: np.ndarray
    directions: np.ndarray
    status: np.ndarray
    max_height: int = -1


@dataclass
class ToppleTable:
    """Outcome of the toppling model for every action of one pose.

    next_pose : (A, P) float, P(x' | x, u); rows sum to 1 for ``ok`` actions and are NaN otherwise
    p_topple : (A,) float, P(x' != x | x, u); NaN for actions that are not ``ok``
    mean_force : (A,) float, N, mean required force over the trials that topple over
      some edge; NaN when none does
    outcomes : (A, T) int16, per trial: base edge toppled over, ``OUTCOME_NO_EDGE``, or ``OUTCOME_NOT_EVALUATED``
    edge_landed_pose : (E,) int, pose a topple over each base edge lands in under this variant
      (``topple.landed_poses``: the thesis's ``edge_final_pose``, or C.6's and C.8's landings)
    edge_onward_pose : (E,) int, pose a share of that landing is carried on to (MODEL.md C.18);
      ``edge_landed_pose`` where nothing is
    edge_onward_share : (E,) float in [0, 1], that share; 0 where nothing is carried on (every thesis variant)

    A trial that topples over edge k counts 1 - share[k] in ``edge_landed_pose[k]`` and share[k] in
    ``edge_onward_pose[k]``: the rows before the smoothing and the maps (C.12-C.19) and the landing
    spread (C.17), which act on rows, not edges.
    """

    next_pose: np.ndarray
    p_topple: np.ndarray
    mean_force: np.ndarray
    outcomes: np.ndarray
    edge_landed_pose: np.ndarray
    edge_onward_pose: np.ndarray
    edge_onward_share: np.ndarray


@dataclass
class SuctionResult:
    """Best suction grasp of one pose (pose frame).

    quality : float in [0, 1], V_s, robust quality of the best grasp (0 when none)
    point : (3,) float, m, grasp contact point (NaN when none)
    axis : (3,) float, unit approach axis pointing from the gripper into the object (NaN when none)
    """

    quality: float
    point: np.ndarray
    axis: np.ndarray


@dataclass
class PolicyChoice:
    """A policy's decision in one pose: an action id (or ``NO_OP``) and its expected value."""

    action: int
    value: float


@dataclass
class PoseValues:
    """Value-iteration results of one pose.

    q : (A,) float, Q_T(x, u) for every action (NaN when not ``ok``)
    greedy : (A,) float, E[V_s(x')] for every action (NaN when not ``ok``)
    value : float, V_T(x)
    policies : dict name -> PolicyChoice for ``max_height``, ``greedy``, ``value_iteration``
    failed_value : float, what ``q`` counts the pose at when a push leaves the object in it: V1(x) of
      (12.13) when the build plans with its failures, else V_T(x) (retries, (12.1)) or V_s(x) ((12.9));
      so q(u) = sum_{x' != x} P(x' | x, u) V_T(x') + P(x | x, u) failed_value
    """

    q: np.ndarray
    greedy: np.ndarray
    value: float
    policies: dict[str, PolicyChoice]
    failed_value: float


@dataclass
class ObjectResult:
    """Everything computed for one object."""

    object_id: str
    mass: float
    center_mass: np.ndarray
    hull_vertices: np.ndarray
    hull_faces: np.ndarray
    repairs: list[str]
    poses: list[StablePose]
    actions: list[Actions]
    topple: list[ToppleTable]
    suction: list[SuctionResult]
    values: list[PoseValues]
    timings: dict[str, float] = field(default_factory=dict)
    equivalent_transforms: list[np.ndarray] | None = None
    """Per pose, (k, 4, 4) float: every orientation that is the pose (``PoseSet.equivalents``),
    its own transform first; None when no symmetric poses were merged."""
    choosable: list[np.ndarray] | None = None
    """Per pose, (A_x,) bool: the pushes greedy and value iteration could choose under the
    build's ``mdp.min_direction_z`` (``schema.horizon.choosable_pushes``); None: every push."""
