"""Suction grasp quality V_s of one stable pose (Dex-Net 3.0 style).

V_s is the robust quality of the best suction grasp reachable from above: the
fraction of Monte Carlo perturbations (grasp position, approach axis, friction,
mass) under which the grasp (a) forms a seal, (b) keeps the gripper body clear
of object and table, and (c) resists gravity under the compliant suction
contact model of Mahler et al., "Dex-Net 3.0", ICRA 2018.  Every parameter is a
field of ``SuctionConfig``; their physical meaning and sources are in
``docs/MODEL.md``.

Frames: everything here is in the pose frame (z up, table z = 0, metres).  An
approach axis points from the gripper into the object (roughly -z).

The work is vectorised over candidates x samples x ring points: one batched ray
cast per pose, closed-form wrench checks in numpy, and one python-fcl query per
nominal candidate for the gripper body.
"""

from __future__ import annotations

import fcl
import numpy as np
import trimesh

from schema.frames import tangent_frames, unit

from .collision import collides_each, collision_object
from .config import SuctionConfig
from .outcomes import SuctionResult
from .sampling import area_weighted_faces, points_in_triangles

TIE_TOLERANCE = 1e-9
"""Qualities closer than this are ties; the grasp nearer the centre of mass (in plan) wins."""


# ----------------------------------------------------------------------------- candidates


def upward_faces(face_normals: np.ndarray, max_approach_angle: float) -> np.ndarray:
    """Faces a cup can approach from above along their inward normal.

    face_normals : (F, 3) float, outward unit normals, pose frame
    max_approach_angle : rad, largest angle between the approach axis and straight down
    returns : (F,) bool
    """
    return face_normals[:, 2] >= np.cos(max_approach_angle)


def sample_candidates(
    mesh: trimesh.Trimesh, count: int, max_approach_angle: float, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """Uniform random grasp points on the upward-facing surface, approach = -normal.

    returns : points (C, 3) m, axes (C, 3) unit; C = ``count``, or 0 when no face
      faces up within ``max_approach_angle``
    """
    normals = np.asarray(mesh.face_normals, dtype=float)
    faces = np.flatnonzero(upward_faces(normals, max_approach_angle) & (mesh.area_faces > 0))
    if len(faces) == 0 or count <= 0:
        return np.zeros((0, 3)), np.zeros((0, 3))
    chosen = faces[area_weighted_faces(mesh.area_faces[faces], count, rng)]
    # Two rows of uniforms (all u, then all v): this stream's draw order since version 1.0.
    points = points_in_triangles(mesh.triangles[chosen], rng.random((2, count)).T)
    return points, -normals[chosen]


def perturb(
    points: np.ndarray, axes: np.ndarray, mass: float, config: SuctionConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Monte Carlo perturbations of every candidate grasp.

    The draws do not depend on ``mass`` (it only scales its own perturbation), so the
    same generator state gives the same samples for objects of different mass.

    points, axes : (C, 3) float, nominal grasp points (m) and unit approach axes
    returns : points (C, S, 3) m, axes (C, S, 3) unit, friction (C, S), mass (C, S) kg;
      S = ``config.n_samples``
    """
    shape = (len(points), config.n_samples)
    offset = rng.normal(0.0, config.position_std, shape + (3,))
    tilt = rng.normal(0.0, config.axis_std, shape + (3,))
    friction = rng.normal(config.friction, config.friction_std, shape)
    scale = rng.normal(1.0, config.mass_std_fraction, shape)
    nominal = np.broadcast_to(axes[:, None, :], shape + (3,))
    # Only the tilt perpendicular to the axis rotates it; small-angle: std = axis_std rad.
    tilt = tilt - np.sum(tilt * nominal, axis=-1, keepdims=True) * nominal
    return (
        points[:, None, :] + offset,
        unit(nominal + tilt),
        np.maximum(friction, 0.0),
        mass * np.maximum(scale, 0.0),
    )


# ----------------------------------------------------------------------------- seal


def ring_offsets(radius: float, count: int, axes: np.ndarray) -> np.ndarray:
    """Points of the flat perimeter ring relative to its centre, perpendicular to each axis.

    axes : (..., 3) float, unit
    returns : (..., count, 3) float, m
    """
    angle = 2.0 * np.pi * np.arange(count) / count
    u, v = tangent_frames(axes)
    return radius * (np.cos(angle)[:, None] * u[..., None, :] + np.sin(angle)[:, None] * v[..., None, :])


def cast_depths(mesh: trimesh.Trimesh, origins: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Distance along each ray to its first hit on the mesh, in one batched embree call.

    origins, directions : (N, 3) float, m and unit
    returns : (N,) float, m; NaN where the ray misses
    """
    tri = mesh.ray.intersects_first(origins, directions)
    hit = tri >= 0
    depth = np.full(len(origins), np.nan)
    if hit.any():
        # Plane distance of the hit triangle: exact in float64 (embree works in float32).
        normal = mesh.face_normals[tri[hit]]
        vertex = mesh.triangles[tri[hit], 0]
        along = np.sum(directions[hit] * normal, axis=1)
        depth[hit] = np.sum((vertex - origins[hit]) * normal, axis=1) / np.where(along == 0.0, np.nan, along)
    return depth


def seal_contacts(
    mesh: trimesh.Trimesh, points: np.ndarray, axes: np.ndarray, config: SuctionConfig
) -> tuple[np.ndarray, np.ndarray]:
    """Project the cup along its approach and test whether it seals.

    The cup is its perimeter ring (radius ``cup_radius``, ``ring_samples`` points) plus
    its centre.  Each is projected along the approach axis onto the mesh from a
    stand-off of one cup radius above the grasp point; a seal needs every ray to
    hit (a miss is an edge or a hole under the cup), the ring's edges to stretch by at
    most ``max_strain`` relative to the flat ring, and all hits to lie within
    ``max_deflection`` of each other along the approach.  Obstacles above the
    stand-off (overhangs) are the gripper-body check's business, not the seal's.

    points, axes : (..., 3) float, grasp points (m) and unit approach axes
    returns : sealed (...,) bool, contact (..., 3) float m, the centre's hit point
      (NaN where it misses)
    """
    lead = points.shape[:-1]
    k = config.ring_samples
    standoff = config.cup_radius
    ring = ring_offsets(config.cup_radius, k, axes)  # (..., K, 3)
    starts = np.concatenate([points[..., None, :], points[..., None, :] + ring], axis=-2)
    starts = starts - standoff * axes[..., None, :]
    directions = np.broadcast_to(axes[..., None, :], starts.shape)
    depth = cast_depths(mesh, starts.reshape(-1, 3), np.ascontiguousarray(directions).reshape(-1, 3))
    depth = depth.reshape(lead + (k + 1,))
    hits = starts + depth[..., None] * directions  # (..., K+1, 3)

    found = np.isfinite(depth)
    complete = found.all(axis=-1)
    deflection = np.where(found, depth, -np.inf).max(axis=-1) - np.where(found, depth, np.inf).min(axis=-1)
    flat_edge = 2.0 * config.cup_radius * np.sin(np.pi / k)
    ring_hits = np.where(np.isfinite(hits[..., 1:, :]), hits[..., 1:, :], 0.0)
    edges = np.linalg.norm(np.roll(ring_hits, -1, axis=-2) - ring_hits, axis=-1)
    strain = np.abs(edges / flat_edge - 1.0).max(axis=-1)
    sealed = complete & (strain <= config.max_strain) & (deflection <= config.max_deflection)
    return sealed, hits[..., 0, :]


# ----------------------------------------------------------------------------- wrench


def wrench_resisted(
    contacts: np.ndarray,
    axes: np.ndarray,
    center_mass: np.ndarray,
    mass: np.ndarray,
    friction: np.ndarray,
    config: SuctionConfig,
    gravity: float = 9.81,
) -> np.ndarray:
    """Whether one compliant suction contact can hold the object against gravity.

    With a single contact the contact wrench is fixed: it is the negated gravity
    wrench about the contact, f = (0, 0, m g) and tau = (com - contact) x f.  In the
    contact frame (z along the approach, into the object) Dex-Net 3.0's constraints
    are checked in closed form (see docs/MODEL.md):

    - suction: f_z >= -V, i.e. the normal force f_N = V + f_z is not negative;
    - friction and torsional friction on the soft ring, one elliptic limit surface
      (|f_t| / (mu f_N))^2 + (tau_z / (r_t mu f_N))^2 <= 1 whose inscribed box is
      Dex-Net's linearisation sqrt(3)|f_x|, sqrt(3)|f_y|, sqrt(3)|tau_z|/r_t <= mu f_N;
    - elastic bending limit: |tau_t| <= ``elastic_limit`` about the tangent axes.

    contacts : (..., 3) float, m;  axes : (..., 3) float, unit approach axes
    center_mass : (3,) float, m;  mass : (...,) kg;  friction : (...,) coefficient
    returns : (...,) bool
    """
    force = np.zeros(contacts.shape)
    force[..., 2] = mass * gravity
    torque = np.cross(np.asarray(center_mass, dtype=float) - contacts, force)
    f_z = np.sum(force * axes, axis=-1)
    tau_z = np.sum(torque * axes, axis=-1)
    f_t = np.linalg.norm(force - f_z[..., None] * axes, axis=-1)
    tau_t = np.linalg.norm(torque - tau_z[..., None] * axes, axis=-1)
    normal = config.vacuum_force + f_z
    limit = friction * np.maximum(normal, 0.0)
    # Multiplied through by r_t^2 so that r_t = 0 (no torsional friction) needs no division.
    # That product loses |f_t| <= mu f_N when r_t = 0 (the ellipse collapses to a segment of
    # the f_t axis), so the sliding limit is also checked alone; for r_t > 0 it adds nothing.
    r_t = config.torsional_friction
    slip = ((r_t * f_t) ** 2 + tau_z**2 > (r_t * limit) ** 2) | (f_t > limit)
    return (normal >= 0.0) & ~slip & (tau_t <= config.elastic_limit)


# ----------------------------------------------------------------------------- gripper body


def body_segments(points: np.ndarray, axes: np.ndarray, config: SuctionConfig) -> tuple[np.ndarray, np.ndarray]:
    """End points of the gripper body's axis: a cylinder behind the cup along the approach.

    The rigid body starts ``max_deflection`` behind the contact: closer than that
    the compliant cup itself is what touches the surface.

    returns : bottom, top, each (..., 3) float, m
    """
    bottom = points - config.max_deflection * axes
    return bottom, bottom - config.gripper_length * axes


def table_collisions(points: np.ndarray, axes: np.ndarray, config: SuctionConfig) -> np.ndarray:
    """Whether the gripper body cylinder dips below the table plane z = 0 (closed form).

    points, axes : (..., 3) float
    returns : (...,) bool
    """
    bottom, top = body_segments(points, axes, config)
    # A cylinder's lowest point is on a rim: an end centre lowered by R sin(tilt).
    rim_drop = config.gripper_radius * np.sqrt(np.clip(1.0 - axes[..., 2] ** 2, 0.0, 1.0))
    return np.minimum(bottom[..., 2], top[..., 2]) - rim_drop < 0.0


def body_collisions(
    collision_mesh: fcl.CollisionObject, points: np.ndarray, axes: np.ndarray, config: SuctionConfig
) -> np.ndarray:
    """Whether the nominal gripper body of each grasp intersects the object (python-fcl).

    points, axes : (C, 3) float, nominal grasp points (m) and unit approach axes
    returns : (C,) bool
    """
    bottom, top = body_segments(points, axes, config)
    cylinder = fcl.Cylinder(config.gripper_radius, config.gripper_length)
    return collides_each(cylinder, 0.5 * (bottom + top), -axes, collision_mesh)


# ----------------------------------------------------------------------------- quality


def grasp_qualities(
    mesh: trimesh.Trimesh,
    center_mass: np.ndarray,
    mass: float,
    points: np.ndarray,
    axes: np.ndarray,
    config: SuctionConfig,
    rng: np.random.Generator,
    gravity: float = 9.81,
) -> np.ndarray:
    """Robust quality of each candidate grasp: the fraction of perturbations that succeed.

    points, axes : (C, 3) float, nominal grasp points (m) and unit approach axes
    returns : (C,) float in [0, 1]
    """
    if len(points) == 0:
        return np.zeros(0)
    s_points, s_axes, friction, s_mass = perturb(points, axes, mass, config, rng)
    sealed, contacts = seal_contacts(mesh, s_points, s_axes, config)
    # Where the seal fails the sample fails anyway; its NaN contact must not poison the math.
    contacts = np.where(sealed[..., None], contacts, s_points)
    held = wrench_resisted(contacts, s_axes, center_mass, s_mass, friction, config, gravity)
    success = sealed & held & ~table_collisions(contacts, s_axes, config)
    # The body is checked once per nominal grasp, not per sample: perturbations move it
    # by about position_std + axis_std * gripper_length (~6 mm at the defaults), far less
    # than the clearances that decide a collision (an overhang, a wall); per-sample
    # checks would cost n_samples times more fcl calls for a rarely different answer.
    alive = np.flatnonzero(success.any(axis=1))
    if len(alive):
        blocked = body_collisions(collision_object(mesh), points[alive], axes[alive], config)
        success[alive[blocked]] = False
    return success.mean(axis=1)


def suction_quality(
    mesh: trimesh.Trimesh,
    center_mass: np.ndarray,
    mass: float,
    config: SuctionConfig,
    rng: np.random.Generator,
    gravity: float = 9.81,
) -> SuctionResult:
    """V_s of one pose: the robust quality of the best suction grasp reachable from above.

    mesh : trimesh.Trimesh, the object in the pose frame (resting on z = 0, z up), metres
    center_mass : (3,) float, m, pose frame
    mass : float, kg
    config : SuctionConfig
    rng : generator, e.g. ``rng.stream(seed, object_id, pose, "suction")``
    gravity : float, m/s^2
    returns : SuctionResult with quality in [0, 1], the best grasp's point (m) and approach
      axis (unit, gripper -> object); quality 0 and NaN point/axis when no grasp succeeds
    """
    center_mass = np.asarray(center_mass, dtype=float)
    points, axes = sample_candidates(mesh, config.n_candidates, config.max_approach_angle, rng)
    quality = grasp_qualities(mesh, center_mass, mass, points, axes, config, rng, gravity)
    if len(quality) == 0 or quality.max() <= 0.0:
        return SuctionResult(quality=0.0, point=np.full(3, np.nan), axis=np.full(3, np.nan))
    best = np.flatnonzero(quality >= quality.max() - TIE_TOLERANCE)
    # Among equally robust grasps prefer the one nearest the centre of mass in plan:
    # it leaves the most margin on the bending limit when the model is off.
    best = best[np.argmin(np.linalg.norm(points[best, :2] - center_mass[:2], axis=1))]
    return SuctionResult(quality=float(quality[best]), point=points[best].copy(), axis=axes[best].copy())
