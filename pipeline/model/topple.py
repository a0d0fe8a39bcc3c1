"""The quasi-static toppling model (thesis 4.2), vectorised over actions x trials x edges.

One trial of one action asks, for every base edge of the pose:

1. contact slip: is the push inside the friction cone at the contact, both at the
   start and with the normal rotated to the apex of the topple over this edge?
2. minimum push force: F* = (gravity torque about the edge) / (push torque per
   newton about the edge); infeasible unless the push rotates the object outward;
3. workspace slip: with force F* d, do the tangential force and the torque about z
   stay inside the friction limit surface ellipse of the edge contact?

The object topples over the passing edge with the least F*, or stays.  Where it
ends up is a property of (pose, edge) computed once (``pipeline.model.poses``).

Noise (4.2.5) perturbs friction, the contact point, the push direction and the
object's orientation; the perturbed contact is found again on the mesh by casting
the finger's ray (embree through trimesh).  ``pipeline.model.reference`` computes the
same trial one scalar at a time; the tests hold this module to it trial by trial.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schema.frames import axis_angle_matrices, transform_points, unit
from schema.vocabulary import OUTCOME_NO_EDGE, OUTCOME_NOT_EVALUATED, STATUS_OK

from .config import ToppleConfig
from .edges import EdgeGeometry, edge_geometry
from .mesh import ObjectModel
from .outcomes import Actions, StablePose, ToppleTable


@dataclass
class TrialNoise:
    """Noise draws for A actions x T trials (zeros and means for noise-free variants).

    mu_table, mu_finger : (A, T) float, friction coefficients (mu_finger clipped at 0)
    contact_offset : (A, T, 3) float, m
    direction_offset : (A, T, 3) float
    rotation_axis : (A, T, 3) float, unit; rotation_angle : (A, T) float, rad
    """

    mu_table: np.ndarray
    mu_finger: np.ndarray
    contact_offset: np.ndarray
    direction_offset: np.ndarray
    rotation_axis: np.ndarray
    rotation_angle: np.ndarray


def sample_noise(rng: np.random.Generator, n_actions: int, config: ToppleConfig) -> TrialNoise:
    """Draw every trial's noise for ``n_actions`` actions, in a fixed order."""
    shape = (n_actions, config.trials)
    if not config.robust:
        return TrialNoise(
            mu_table=np.full(shape, config.mu_table_mean),
            mu_finger=np.full(shape, config.mu_finger_mean),
            contact_offset=np.zeros(shape + (3,)),
            direction_offset=np.zeros(shape + (3,)),
            rotation_axis=np.tile([0.0, 0.0, 1.0], shape + (1,)),
            rotation_angle=np.zeros(shape),
        )
    return TrialNoise(
        mu_table=rng.normal(config.mu_table_mean, config.mu_table_std, shape),
        mu_finger=np.maximum(rng.normal(config.mu_finger_mean, config.mu_finger_std, shape), 0.0),
        contact_offset=rng.normal(0.0, config.contact_std, shape + (3,)),
        direction_offset=rng.normal(0.0, config.direction_std, shape + (3,)),
        rotation_axis=unit(rng.normal(size=shape + (3,))),
        rotation_angle=rng.normal(0.0, config.rotation_std, shape),
    )


@dataclass
class Trials:
    """Per-trial inputs of the model, flattened over (action, trial); pose frame.

    contact : (n, 3) float, m;  normal : (n, 3) float, unit outward;  push : (n, 3) float, unit
    mu_table, mu_finger : (n,) float;  valid : (n,) bool, the finger found the surface from outside
    """

    contact: np.ndarray
    normal: np.ndarray
    push: np.ndarray
    mu_table: np.ndarray
    mu_finger: np.ndarray
    valid: np.ndarray


def noisy_trials(
    obj: ObjectModel,
    transform: np.ndarray,
    center_mass: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    directions: np.ndarray,
    noise: TrialNoise,
    config: ToppleConfig,
) -> Trials:
    """Apply the noise to actions and re-find each noisy contact on the mesh.

    The finger ray starts ``config.ray_offset`` outside the perturbed point along the
    nominal normal and points along -normal; ray and push direction are rotated by
    R_theta about the centre of mass (the object's orientation error seen from the
    object).  A miss, or a first hit on a back face (the ray started inside the
    object), is an invalid trial.

    transform : (4, 4) object -> pose frame;  center_mass : (3,) pose frame
    points, normals, directions : (a, 3) pose frame;  noise : for these a actions
    """
    a, t = noise.mu_table.shape
    flat = lambda v: v.reshape(a * t, -1)  # noqa: E731
    push = unit(directions[:, None, :] + noise.direction_offset)
    if not config.robust:
        return Trials(
            contact=flat(np.broadcast_to(points[:, None], (a, t, 3))).copy(),
            normal=flat(np.broadcast_to(normals[:, None], (a, t, 3))).copy(),
            push=flat(push),
            mu_table=noise.mu_table.ravel(),
            mu_finger=noise.mu_finger.ravel(),
            valid=np.ones(a * t, dtype=bool),
        )
    rotation = axis_angle_matrices(flat(noise.rotation_axis), noise.rotation_angle.ravel())
    origin = points[:, None] + noise.contact_offset + config.ray_offset * normals[:, None]
    origin = np.einsum("nij,nj->ni", rotation, flat(origin) - center_mass) + center_mass
    ray = np.einsum("nij,nj->ni", rotation, flat(np.broadcast_to(-normals[:, None], (a, t, 3))))
    push = np.einsum("nij,nj->ni", rotation, flat(push))

    to_object = np.linalg.inv(transform)
    faces, rays, hits = obj.mesh.ray.intersects_id(
        transform_points(to_object, origin), ray @ to_object[:3, :3].T, multiple_hits=False, return_locations=True
    )
    contact = np.full((a * t, 3), np.nan)
    normal = np.full((a * t, 3), np.nan)
    contact[rays] = transform_points(transform, hits)
    normal[rays] = obj.mesh.face_normals[faces] @ transform[:3, :3].T
    valid = np.zeros(a * t, dtype=bool)
    valid[rays] = np.einsum("ij,ij->i", normal[rays], ray[rays]) < 0.0
    return Trials(contact, normal, push, noise.mu_table.ravel(), noise.mu_finger.ravel(), valid)


def trial_outcomes(
    trials: Trials, edges: EdgeGeometry, mass: float, gravity: float, predicts_rotations: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Edge each trial topples over, and the force it takes.

    returns : edge (n,) int (``OUTCOME_NO_EDGE`` when none), required_force (n,) float, N (inf when none)
    """
    n = trials.contact.shape[0]
    u, normal, contact = trials.push, trials.normal, np.nan_to_num(trials.contact)
    normal = np.nan_to_num(normal)
    mu_f = trials.mu_finger[:, None]

    # 1. Contact slip, at the start and with the normal rotated to each edge's apex.
    cos_start = -np.einsum("ij,ij->i", u, normal)[:, None]
    outer = (u[:, :, None] * normal[:, None, :]).reshape(n, 9)
    cos_tip = -(outer @ edges.tip_rotation.reshape(-1, 9).T)
    in_cone = _inside_cone(cos_start, mu_f) & _inside_cone(cos_tip, mu_f)

    # 2. Minimum push force: e . ((p - y0) x u) = e . (p x u) - u . (e x y0).
    p_cross_u = np.cross(contact, u)
    torque = p_cross_u @ edges.direction.T - u @ np.cross(edges.direction, edges.start).T
    rotates = torque > 1e-12
    gravity_torque = mass * gravity * edges.com_distance
    force = np.where(rotates, gravity_torque / np.where(rotates, torque, 1.0), np.inf)

    # 3. Workspace slip on the friction limit surface, divided through by F*^2.
    #    tangential: F*|u_xy| <= mu_T F_n;  F_n = m g + F* max(0, -u_z)
    with np.errstate(divide="ignore", invalid="ignore"):
        normal_per_newton = mass * gravity / force + np.maximum(0.0, -u[:, 2:3])
    limit = (trials.mu_table[:, None] * normal_per_newton) ** 2
    load = (u[:, 0:1] ** 2 + u[:, 1:2] ** 2) * np.ones_like(force)
    if predicts_rotations:
        # tau_z per newton about the COM's projection on the edge: (p x u)_z - (O x u)_z
        origin_cross = np.column_stack([-edges.origin[:, 1], edges.origin[:, 0], np.zeros(len(edges.origin))])
        tau = p_cross_u[:, 2:3] - u @ origin_cross.T
        load = load + (tau / edges.half_span) ** 2
    holds = (load <= limit) & (trials.mu_table[:, None] > 0.0)

    passes = in_cone & rotates & holds & trials.valid[:, None]
    candidate = np.where(passes, force, np.inf)
    edge = np.argmin(candidate, axis=1)
    required = candidate[np.arange(n), edge]
    return np.where(np.isfinite(required), edge, OUTCOME_NO_EDGE), required


def _inside_cone(cos: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """tan(angle) <= mu for a push making angle acos(cos) with the inward normal."""
    sin = np.sqrt(np.maximum(0.0, 1.0 - cos * cos))
    return (cos > 0.0) & (sin <= mu * cos)


def evaluate_pose(
    obj: ObjectModel,
    pose: StablePose,
    n_poses: int,
    actions: Actions,
    config: ToppleConfig,
    rng: np.random.Generator,
) -> ToppleTable:
    """Transition table of every action of one pose.

    obj : the object;  pose : one of its stable poses;  n_poses : size of its pose set
    actions : candidate pushes of this pose;  rng : stream for this (object, pose)
    """
    n_actions, trials = len(actions.status), config.trials
    noise = sample_noise(rng, n_actions, config)
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    edges = edge_geometry(pose.base_edges, center_mass)
    final_pose = np.append(pose.edge_final_pose, pose.index)  # index -1 (OUTCOME_NO_EDGE): stays

    outcomes = np.full((n_actions, trials), OUTCOME_NOT_EVALUATED, dtype=np.int16)
    forces = np.full((n_actions, trials), np.inf)
    ok = np.flatnonzero(actions.status == STATUS_OK)
    for chunk in np.array_split(ok, max(1, int(np.ceil(len(ok) / config.chunk_actions)))):
        if len(chunk) == 0:
            continue
        chunk_noise = TrialNoise(*(getattr(noise, f)[chunk] for f in TrialNoise.__dataclass_fields__))
        chunk_trials = noisy_trials(
            obj,
            pose.transform,
            center_mass,
            actions.points[chunk],
            actions.normals[chunk],
            actions.directions[chunk],
            chunk_noise,
            config,
        )
        edge, force = trial_outcomes(chunk_trials, edges, obj.mass, config.gravity, config.predicts_rotations)
        outcomes[chunk] = edge.reshape(len(chunk), trials)
        forces[chunk] = force.reshape(len(chunk), trials)

    next_pose = np.full((n_actions, n_poses), np.nan)
    landed = final_pose[outcomes[ok]]
    cells = np.repeat(np.arange(len(ok)), trials) * n_poses + landed.ravel()
    counts = np.bincount(cells, minlength=len(ok) * n_poses).reshape(len(ok), n_poses)
    next_pose[ok] = counts / trials
    p_topple = np.full(n_actions, np.nan)
    p_topple[ok] = 1.0 - next_pose[ok, pose.index]
    toppled = outcomes >= 0
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_force = np.where(toppled, forces, 0.0).sum(axis=1) / toppled.sum(axis=1)
    mean_force[toppled.sum(axis=1) == 0] = np.nan
    return ToppleTable(next_pose=next_pose, p_topple=p_topple, mean_force=mean_force, outcomes=outcomes)
