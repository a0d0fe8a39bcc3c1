"""Scalar reference of one toppling trial, written straight from thesis 4.2.

Plain Python floats and loops, no numpy in the arithmetic: it is slow on purpose
and exists so the tests can hold the vectorised engine (``pipeline.model.topple``) to
it trial by trial, and ``make bench`` can measure the speed-up.

Inputs are the same noise draws the engine uses (``pipeline.model.topple.TrialNoise``
values for one action and trial), so both compute the same trial.

No shapes here: every vector is a ``Vec`` (3 floats) and the loop over base edges is an
explicit ``for``; the engine's (n, E) arrays are this function's values for every
(trial, edge) pair (docs/MODEL.md section 10).  The equation numbers in the comments are
docs/MODEL.md's.  The only thresholds are the push-torque cut (7.4), shared with the
engine (``MIN_PUSH_TORQUE``), and the two of the ray cast below, which stands in for
embree's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

from .config import FROM_ABOVE_U_Z
from .topple import MIN_PUSH_TORQUE, landed_poses

Vec = tuple[float, float, float]

RAY_PARALLEL_DET = 1e-18
"""m^2, Moller-Trumbore's determinant det = e1 . (r x e2) (unit ray r, triangle edges e1,
e2 in m) below which the ray counts as parallel to the triangle's plane and the triangle is
skipped.  It only guards the division by det: 1e-18 m^2 is the scale of a triangle with
1 nm edges, below any real face, and an almost-parallel ray that passes it gets huge
barycentric coordinates, which the range tests then reject."""

RAY_MIN_DISTANCE = 1e-12
"""m, hits at a ray parameter t at or below this are behind or at the ray's origin, not in
front of it.  The finger's ray starts ``ray_offset`` (15 mm) outside the surface, so real
hits lie at t ~ 1e-2 m; 1e-12 m only rejects t <= 0 up to rounding.  Embree, which the
engine uses, likewise reports only hits in front of the origin."""


def _add(a: Vec, b: Vec) -> Vec:
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2])


def _sub(a: Vec, b: Vec) -> Vec:
    return (a[0] - b[0], a[1] - b[1], a[2] - b[2])


def _scale(a: Vec, s: float) -> Vec:
    return (a[0] * s, a[1] * s, a[2] * s)


def _dot(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _norm(a: Vec) -> float:
    return math.sqrt(_dot(a, a))


def _unit(a: Vec) -> Vec:
    return _scale(a, 1.0 / _norm(a))


def _rotate(v: Vec, axis: Vec, angle: float) -> Vec:
    """Rodrigues: v rotated by ``angle`` about the unit ``axis`` (the engine's ``axis_angle_matrices``)."""
    c, s = math.cos(angle), math.sin(angle)
    return _add(_add(_scale(v, c), _scale(_cross(axis, v), s)), _scale(axis, _dot(axis, v) * (1.0 - c)))


def ray_cast(origin: Vec, direction: Vec, triangles: Sequence[tuple[Vec, Vec, Vec]]):
    """First hit of a ray on a triangle soup (Moller-Trumbore); (t, triangle index) or None."""
    best = None
    for index, (a, b, c) in enumerate(triangles):
        e1, e2 = _sub(b, a), _sub(c, a)
        p = _cross(direction, e2)
        det = _dot(e1, p)
        if abs(det) < RAY_PARALLEL_DET:
            continue
        inv = 1.0 / det
        s = _sub(origin, a)
        u = _dot(s, p) * inv
        if u < 0.0 or u > 1.0:  # barycentric range: exact, a hit on an edge belongs to both triangles
            continue
        q = _cross(s, e1)
        v = _dot(direction, q) * inv
        if v < 0.0 or u + v > 1.0:
            continue
        t = _dot(e2, q) * inv
        if t > RAY_MIN_DISTANCE and (best is None or t < best[0]):
            best = (t, index)
    return best


@dataclass
class Scene:
    """One pose of one object, as plain Python values (pose frame, SI units)."""

    triangles: list[tuple[Vec, Vec, Vec]]
    face_normals: list[Vec]
    center_mass: Vec
    mass: float
    gravity: float
    edges: list[tuple[Vec, Vec]]


@dataclass
class TrialDraw:
    """One trial's inputs: the nominal action and its noise draws."""

    point: Vec
    normal: Vec
    direction: Vec
    mu_table: float
    mu_finger: float
    contact_offset: Vec
    direction_offset: Vec
    rotation_axis: Vec
    rotation_angle: float
    stuck_draw: float = 0.0


def in_friction_cone(push: Vec, normal: Vec, mu: float) -> bool:
    """Condition 1: the push lies in the friction cone at the contact (4.2.1), (7.1)."""
    cos = -_dot(push, normal)
    if cos <= 0.0:  # pointing away from or along the surface: outside every cone
        return False
    angle = math.acos(min(1.0, cos))  # the clip only absorbs rounding of a unit dot product above 1
    return math.tan(angle) <= mu


def reference_trial(
    scene: Scene,
    draw: TrialDraw,
    robust: bool,
    predicts_rotations: bool,
    ray_offset: float,
    corrections: frozenset = frozenset(),
    max_force: float = math.inf,
    friction_scale: float = 1.0,
    min_margin: float = 0.0,
    stroke: float = math.inf,
    stuck_share: float = 1.0,
    tip_points: int = 2,
    tip_back_force: float = math.inf,
    carried_slide: float = 0.0,
):
    """Outcome of one trial: (edge index or -1, required force in N or inf).

    ``corrections`` (names of ``config.CORRECTIONS``), ``max_force``, ``friction_scale``,
    ``min_margin``, ``stroke``, ``stuck_share``, ``tip_points``, ``tip_back_force`` and ``carried_slide`` are the corrected variant's (docs/MODEL.md "Corrections beyond the thesis");
    empty, it is the thesis's trial.
    """
    if "stability_margin" in corrections:
        edge = marginal_edge(scene, min_margin)
        if edge is not None:  # C.3: a marginal pose falls over that edge, push or not
            return edge, 0.0
    push = _unit(_add(draw.direction, draw.direction_offset))  # u0 (8.2)
    if robust:  # (8.2)-(8.3): re-find the noisy contact with the rotated finger ray
        c = scene.center_mass
        origin = _add(_add(draw.point, draw.contact_offset), _scale(draw.normal, ray_offset))
        origin = _add(_rotate(_sub(origin, c), draw.rotation_axis, draw.rotation_angle), c)
        ray = _rotate(_scale(draw.normal, -1.0), draw.rotation_axis, draw.rotation_angle)
        push = _rotate(push, draw.rotation_axis, draw.rotation_angle)
        hit = ray_cast(origin, ray, scene.triangles)
        if hit is None:
            return -1, math.inf
        contact = _add(origin, _scale(ray, hit[0]))
        normal = scene.face_normals[hit[1]]
        if _dot(normal, ray) >= 0.0:  # the finger started inside the object
            return -1, math.inf
    else:
        contact, normal = draw.point, draw.normal

    weight = scene.mass * scene.gravity
    com = scene.center_mass
    spin_stops = predicts_rotations and "edge_spin" not in corrections  # C.9: a turn does not stop the topple
    best_edge, best_force = -1, math.inf
    for index, (y0, y1) in enumerate(scene.edges):
        e, _, com_distance = _edge_frame(y0, y1, com)
        if "finger_friction" in corrections:
            force = sliding_force(contact, normal, push, draw.mu_table, friction_scale * draw.mu_finger, e, y0, y1, com, weight,
                                  com_distance, spin_stops)
        else:
            force = _thesis_force(contact, normal, push, draw, e, y0, y1, com, weight, com_distance, spin_stops)
        if force is None:
            continue
        if "force_limit" in corrections and not 0.0 < force <= max_force:  # C.1: a finger pushes, and only so hard
            continue
        if force < best_force:  # (7.10): the least-force passing edge; the first on a tie, as argmin
            best_edge, best_force = index, force
    if "stroke" in corrections and best_edge >= 0:
        y0, y1 = scene.edges[best_edge]
        if not finger_travel(contact, normal, push, y0, y1, com) <= stroke:  # C.10: falls back short of the apex
            best_edge, best_force = -1, math.inf
    if "tip_path" in corrections and best_edge >= 0:
        y0, y1 = scene.edges[best_edge]
        limit = max_force if "force_limit" in corrections else math.inf
        if not holds_along_tip(contact, normal, push, draw.mu_table, friction_scale * draw.mu_finger, y0, y1, com, weight,
                               spin_stops, limit, tip_points):  # C.14: the tip stalls on the way
            best_edge, best_force = -1, math.inf
    if "carried_finger" in corrections and best_edge < 0 and push[2] < FROM_ABOVE_U_Z:
        limit = max_force if "force_limit" in corrections else math.inf
        for index, (y0, y1) in enumerate(scene.edges):  # C.23: the finger carried with the face, pressing along its normal
            e, _, com_distance = _edge_frame(y0, y1, com)
            force = sliding_force(contact, normal, push, draw.mu_table, 0.0, e, y0, y1, com, weight, com_distance, spin_stops)
            if force is None or not 0.0 < force <= limit or face_slide(contact, normal, push, y0, y1, com) > carried_slide:
                continue
            if force < best_force:
                best_edge, best_force = index, force
    if "stuck_finger" in corrections and best_edge < 0 and draw.stuck_draw < stuck_share and drags_base(push, draw.mu_table):
        for index, (y0, y1) in enumerate(scene.edges):  # C.11: the finger holds, the base slides
            e, outward, com_distance = _edge_frame(y0, y1, com)
            torque = _dot(e, _cross(_sub(contact, y0), push))
            if _dot(_sub(contact, y0), outward) <= 0.0 or com_distance <= 0.0 or torque <= MIN_PUSH_TORQUE:
                continue
            force = weight * com_distance / torque
            if force <= max_force and force < best_force:
                best_edge, best_force = index, force
    if "tip_back" in corrections and best_edge >= 0 and best_force > tip_back_force and push[2] < FROM_ABOVE_U_Z:
        back = line_edge(contact, scene.edges, com)  # C.22, after C.11: a hard press from above tips it back
        if back >= 0:
            best_edge = back
    return best_edge, best_force


def configured_trial(scene: Scene, draw: TrialDraw, topple) -> tuple[int, float]:
    """``reference_trial`` with every model parameter taken from ``topple`` (a
    ``config.ToppleConfig``), as the engine reads them: what tests and the bench hold the
    engine against, so neither can leave a parameter at its default."""
    return reference_trial(
        scene, draw, topple.robust, topple.predicts_rotations, topple.ray_offset, topple.applied_corrections,
        topple.max_finger_force, topple.finger_friction_scale, topple.min_stability_margin, topple.stroke,
        topple.stuck_finger_share, topple.tip_path_points, topple.tip_back_force, topple.carried_slide,
    )


def line_edge(contact: Vec, edges, com: Vec) -> int:
    """C.22: the base edge the line from the centre of mass's foot through the contact's foot meets first
    (t = d_e / ((p - c) . o_e) over the edges it heads for), or -1 when it heads for none."""
    best, best_reach = -1, math.inf
    for index, (y0, y1) in enumerate(edges):
        _, outward, com_distance = _edge_frame(y0, y1, com)
        towards = _dot(_sub(contact, y0), outward) + com_distance  # (p - c) . o_e
        if towards > 0.0 and com_distance / towards >= 0.0 and com_distance / towards < best_reach:
            best, best_reach = index, com_distance / towards
    return best


def _edge_frame(y0: Vec, y1: Vec, com: Vec) -> tuple[Vec, Vec, float]:
    """Base edge y0 -> y1: its unit direction e, horizontal outward normal o = (e_y, -e_x, 0), and
    the centre of mass's distance inside it, d = -(c - y0) . o (m)."""
    e = _unit(_sub(y1, y0))
    outward = (e[1], -e[0], 0.0)
    return e, outward, -_dot(_sub(com, y0), outward)


def drags_base(push: Vec, mu_table: float) -> bool:
    """C.11's push: down, yet able to drag the base (|u_xy| > mu_T |u_z|)."""
    return push[2] < 0.0 and math.hypot(push[0], push[1]) > mu_table * -push[2]


def finger_travel(contact: Vec, normal: Vec, push: Vec, y0: Vec, y1: Vec, com: Vec) -> float:
    """C.10: how far past the contact the finger advances to bring the face to the apex of the
    topple over the edge y0 -> y1 (m; inf if the face turns away from the finger first)."""
    e, _, com_distance = _edge_frame(y0, y1, com)
    apex_normal = _rotate(normal, e, math.atan2(com_distance, com[2]))
    approach = _dot(apex_normal, push)
    if approach >= 0.0:
        return math.inf
    offset = _sub(contact, y0)
    return (_dot(normal, offset) - _dot(apex_normal, offset)) / approach


def face_slide(contact: Vec, normal: Vec, push: Vec, y0: Vec, y1: Vec, com: Vec) -> float:
    """C.23: how far the face slides along the fingertip on the way to the apex of the edge y0 -> y1, to first
    order: |v_e - s_e u| theta_e with v_e = e x (p - y0) and s_e = v_e . n / u . n (m; the finger moves into the face)."""
    e, _, com_distance = _edge_frame(y0, y1, com)
    velocity = _cross(e, _sub(contact, y0))
    advance = _dot(velocity, normal) / _dot(push, normal)
    return _norm(_sub(velocity, _scale(push, advance))) * math.atan2(com_distance, com[2])


def holds_along_tip(contact: Vec, normal: Vec, push: Vec, mu_table: float, mu_finger: float, y0: Vec, y1: Vec, com: Vec,
                    weight: float, spin_stops: bool, max_force: float, points: int) -> bool:
    """C.14: whether C.2's balance holds at k / (points + 1) of the way to the apex of the edge
    y0 -> y1, k = 1..points, the face turned with the object and the finger advanced along the
    push onto it (``mu_finger``: the trial's mu_f times ``finger_friction_scale``)."""
    e, _, com_distance = _edge_frame(y0, y1, com)
    apex = math.atan2(com_distance, com[2])
    offset = _sub(contact, y0)
    for k in range(1, points + 1):
        theta = apex * (k / (points + 1))  # grouped as the engine groups it, so the angles agree bit for bit
        turned = _rotate(normal, e, theta)
        approach = _dot(turned, push)
        if approach >= 0.0:  # the face has turned away from the finger
            return False
        finger = _add(contact, _scale(push, _dot(_sub(normal, turned), offset) / approach))
        inside = com_distance * (math.sin(apex - theta) / math.sin(apex))
        force = sliding_force(finger, turned, push, mu_table, mu_finger, e, y0, y1, com, weight, inside, spin_stops)
        if force is None or force > max_force:
            return False
    return True


def landed_pose(pose, edge: int, corrections: frozenset = frozenset()) -> int:
    """Pose one trial ends in (``StablePose``, its edge or -1): the thesis's per-edge final pose,
    or with ``rolling`` (MODEL.md C.6) or ``momentum`` (C.8) the rolled-on one; the same per-(pose, edge) tables
    the engine reads (``topple.landed_poses``), looked up one trial at a time."""
    if edge < 0:
        return int(pose.index)
    return int(landed_poses(pose, corrections)[edge])


def landed_masses(pose, edge: int, corrections: frozenset, drop_probabilities, onward_share: float,
                  onward_below: float) -> dict[int, float]:
    """Where one trial's unit mass rests (pose -> mass): all of it in ``landed_pose``, or with a
    ``landing_onward`` share (MODEL.md C.18) that share carried on to the edge's onward pose
    when the landing pose's drop probability is at most ``onward_below`` and the onward pose is
    neither the landing nor the start pose; with ``momentum`` (the chain whose landings it
    carries on) and unblocked edges only, one trial at a time (the engine:
    ``landing_onward.onward_shares``)."""
    landed = landed_pose(pose, edge, corrections)
    if edge < 0 or not onward_share or "momentum" not in corrections or pose.edge_blocked[edge]:
        return {landed: 1.0}
    onward = int(pose.edge_onward_pose[edge])
    if onward in (landed, pose.index) or landed == pose.index or drop_probabilities[landed] > onward_below:
        return {landed: 1.0}
    return {landed: 1.0 - onward_share, onward: onward_share}


def marginal_edge(scene: Scene, min_margin: float):
    """The edge a marginal pose falls over (C.3): the one the centre of mass is nearest to, if
    nearer than ``min_margin`` (m); None for a pose that stands."""
    best, best_distance = None, math.inf
    for index, (y0, y1) in enumerate(scene.edges):
        _, _, distance = _edge_frame(y0, y1, scene.center_mass)
        if distance < best_distance:  # the first on a tie, as argmin
            best, best_distance = index, distance
    return best if best_distance < min_margin else None


def sliding_force(contact: Vec, normal: Vec, push: Vec, mu_table: float, mu_finger: float, e: Vec, y0: Vec, y1: Vec, com: Vec, weight: float,
                  com_distance: float, spin_stops: bool = True):
    """Finger force (N) to topple over edge (y0, y1) with the finger sliding on the face (C.2), or None.

    mu_finger : the friction that resists tipping (the trial's mu_f times ``finger_friction_scale``)
    spin_stops : False with ``edge_spin`` (C.9): the check (7.9) without its moment term
    """
    velocity = _cross(e, _sub(contact, y0))  # the contact point's velocity per unit tipping rate
    face_speed = _dot(velocity, normal)
    approach = _dot(push, normal)
    if approach >= 0.0 or face_speed >= -MIN_PUSH_TORQUE:  # the finger cannot follow the face
        return None
    relative = _sub(velocity, _scale(push, face_speed / approach))  # the face sliding along the finger
    slide = _norm(relative)
    tangent = _scale(relative, -1.0 / slide) if slide > MIN_PUSH_TORQUE else (0.0, 0.0, 0.0)
    direction = _sub(_scale(tangent, mu_finger), normal)  # -n + k mu_f t, per newton of normal force
    torque = _dot(direction, velocity)
    if torque <= MIN_PUSH_TORQUE or com_distance <= 0.0:
        return None
    normal_force = weight * com_distance / torque
    f = _scale(direction, normal_force)
    table = weight - f[2]
    if table <= 0.0 or mu_table <= 0.0:
        return None
    origin_on_edge = _add(y0, _scale(e, _dot(_sub(com, y0), e)))
    half_span = (abs(_dot(_sub(y0, origin_on_edge), e)) + abs(_dot(_sub(y1, origin_on_edge), e))) / 2.0
    tau_z = _cross(_sub(contact, origin_on_edge), f)[2] if spin_stops else 0.0
    # (7.9) with the whole finger force: |f_xy|^2 + (tau_z / h_e)^2 <= (mu_T F_table)^2
    if f[0] ** 2 + f[1] ** 2 + (tau_z / half_span) ** 2 > (mu_table * table) ** 2:
        return None
    return normal_force * _norm(direction)


def _thesis_force(contact, normal, push, draw, e, y0, y1, com, weight, com_distance, spin_stops):
    """Thesis 4.2.1-4.2.3 for one edge: F*_e in N if the edge passes, else None (``spin_stops``:
    the slip check counts the moment about the vertical, as ``topple._thesis_conditions``)."""
    # The tipping point: rotate about the edge until the COM is above it.
    apex = math.atan2(com_distance, com[2])
    if not in_friction_cone(push, normal, draw.mu_finger):  # (7.2), at the start
        return None
    if not in_friction_cone(push, _rotate(normal, e, apex), draw.mu_finger):  # (7.2), at the apex
        return None

    # Condition 3 (4.2.3): |r_f x f'_f| >= |r_g x f_g| about the edge, (7.3)-(7.5).
    push_torque = _dot(_cross(_sub(contact, y0), push), e)
    if push_torque <= MIN_PUSH_TORQUE:  # (7.4): does not rotate the object outward
        return None
    force = weight * com_distance / push_torque

    # Condition 2 (4.2.2): friction limit surface, two point contacts at the ends, (7.6)-(7.9).
    if draw.mu_table <= 0.0:
        return None
    f = _scale(push, force)
    normal_force = weight + max(0.0, -f[2])
    tangential = math.hypot(f[0], f[1])
    origin_on_edge = _add(y0, _scale(e, _dot(_sub(com, y0), e)))
    tau_max = draw.mu_table * normal_force / 2.0 * (
        abs(_dot(_sub(y0, origin_on_edge), e)) + abs(_dot(_sub(y1, origin_on_edge), e))
    )
    tau_z = _cross(_sub(contact, origin_on_edge), f)[2] if spin_stops else 0.0
    ellipse = (tangential / (draw.mu_table * normal_force)) ** 2 + (tau_z / tau_max) ** 2
    if ellipse > 1.0:  # outside the unit ellipse (7.9): the base slides or spins
        return None
    return force


def scene_from_pose(obj, pose, gravity: float) -> Scene:
    """Plain-Python scene of one stable pose (``ObjectModel``, ``StablePose``)."""
    rotation, shift = pose.transform[:3, :3], pose.transform[:3, 3]
    triangles = obj.mesh.triangles @ rotation.T + shift
    as_vec = lambda v: tuple(float(x) for x in v)  # noqa: E731
    return Scene(
        triangles=[tuple(as_vec(corner) for corner in tri) for tri in triangles],
        face_normals=[as_vec(n) for n in obj.mesh.face_normals @ rotation.T],
        center_mass=as_vec(rotation @ obj.center_mass + shift),
        mass=float(obj.mass),
        gravity=float(gravity),
        edges=[(as_vec(y0), as_vec(y1)) for y0, y1 in pose.base_edges],
    )


def draw_of(actions, noise, action: int, trial: int) -> TrialDraw:
    """The ``TrialDraw`` of one (action, trial) from engine arrays (``Actions``, ``TrialNoise``)."""
    as_vec = lambda v: tuple(float(x) for x in v)  # noqa: E731
    return TrialDraw(
        point=as_vec(actions.points[action]),
        normal=as_vec(actions.normals[action]),
        direction=as_vec(actions.directions[action]),
        mu_table=float(noise.mu_table[action, trial]),
        mu_finger=float(noise.mu_finger[action, trial]),
        contact_offset=as_vec(noise.contact_offset[action, trial]),
        direction_offset=as_vec(noise.direction_offset[action, trial]),
        rotation_axis=as_vec(noise.rotation_axis[action, trial]),
        rotation_angle=float(noise.rotation_angle[action, trial]),
        stuck_draw=float(noise.stuck_draw[action, trial]),
    )
