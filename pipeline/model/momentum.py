"""Rolling on after a topple lands: the energy the fall leaves (docs/MODEL.md C.8).

The thesis's topple ends on the first stable pose the object settles into
quasi-statically.  A real topple falls: from the apex the centre of mass drops to
the landing pose's height, and the object hits the table turning.  If the pose it
lands on is shallow (its centre of mass near an edge of its base), what is left of
that energy after the impact carries it on over the next edge.

The impact is Housner's (1963) for a rocking block: rigid, plastic and without
slip, the object turning about the old pivot line hits the table and then turns
about the new pivot line (the landing pose's base edge it travels towards), and
its angular momentum about the new line is conserved.  With I the inertia tensor
about the centre of mass per unit mass (m^2), r and r' the centre of mass from a
point of the old and the new line, w and w' their unit axes in the senses the
object turns:

    omega' / omega = w' . (I w + r' x (w x r)) / (w' . I w' + |r'_perp|^2)

and the energy kept is that ratio squared times (w . I w + |r_perp|^2) / (w' . I w' +
|r'_perp|^2), the two moments about the lines.  Energies here are heights (m): energy
over m g.

Everything is in the object frame or a pose frame (z up, table at z = 0) and per
(pose, edge): computed once with the pose set, never per trial.
"""

from __future__ import annotations

import numpy as np
import trimesh

from schema.frames import transform_points, unit

from .edges import edge_geometry


def inertia_per_mass(mesh: trimesh.Trimesh, hull: trimesh.Trimesh, center_mass: np.ndarray, mass: float = 1.0) -> np.ndarray:
    """Inertia tensor about ``center_mass`` per unit mass (or of a body of ``mass``), object frame.

    Uniform density over the mesh (its hull when the mesh encloses no volume), scaled to
    ``mass`` and moved to ``center_mass`` by the parallel axis theorem.  ``pushsim.body_model``
    takes the object's mass and inertia from here too.

    center_mass : (3,) float, m;  mass : float, kg (1: per unit mass)
    returns : (3, 3) float, m^2 (kg m^2 with ``mass``)
    """
    solid = mesh if mesh.is_volume and mesh.volume > 0 else hull
    offset = np.asarray(center_mass, float) - solid.center_mass
    return solid.moment_inertia * (mass / solid.mass) + mass * (np.dot(offset, offset) * np.eye(3) - np.outer(offset, offset))


def impact_energy_ratio(
    inertia: np.ndarray, center_mass: np.ndarray, old_point: np.ndarray, old_axis: np.ndarray, new_point: np.ndarray, new_axis: np.ndarray
) -> float:
    """Share of the kinetic energy kept when the pivot jumps from one line to another (Housner).

    The object turns about the old line (``old_point``, unit ``old_axis``) in the sense that
    lowers the centre of mass, hits the table, and goes on turning about the new line in the
    sense given by ``new_axis`` (unit).

    inertia : (3, 3) float, m^2, about the centre of mass per unit mass, same frame
    center_mass, old_point, new_point : (3,) float, m
    returns : float in [0, 1]; 0 when the impact stops the object or turns it back
    """
    r = center_mass - old_point
    w = old_axis if np.cross(old_axis, r)[2] <= 0 else -old_axis  # the sense in which the centre of mass falls
    r_perp = r - (r @ w) * w
    r_new = center_mass - new_point
    r_new_perp = r_new - (r_new @ new_axis) * new_axis
    moment_old = w @ inertia @ w + r_perp @ r_perp
    moment_new = new_axis @ inertia @ new_axis + r_new_perp @ r_new_perp
    momentum = new_axis @ (inertia @ w + np.cross(r_new, np.cross(w, r)))  # about the new line, per unit omega
    if momentum <= 0:
        return 0.0
    return float(momentum**2 / (moment_old * moment_new))


def exit_edge(outward: np.ndarray, com_distance: np.ndarray, travel: np.ndarray) -> int:
    """The base edge the centre of mass's horizontal travel heads for.

    outward : (E, 3) unit, pose frame;  com_distance : (E,) m, > 0 inside the base
    travel : (3,) float, horizontal direction
    returns : int, edge index, or -1 when no edge lies ahead
    """
    ahead = outward @ travel  # (E,)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(ahead > 1e-9, com_distance / ahead, np.inf)  # (E,), distance to each edge line
    edge = int(np.argmin(reach))
    return edge if np.isfinite(reach[edge]) else -1


def momentum_poses(
    transforms: np.ndarray,
    base_edges: list[np.ndarray],
    final_pose: list[np.ndarray],
    blocked: list[np.ndarray],
    center_mass: np.ndarray,
    inertia: np.ndarray,
    energy_scale: float = 1.0,
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Pose each topple ends in once the energy of its fall is counted (C.8), and the pose one
    fall beyond it (its onward pose, C.18).

    From the apex of edge e of pose s the centre of mass falls to the landing pose q
    (``final_pose[s][e]``).  The impact keeps ``impact_energy_ratio`` of that energy;
    if what is kept exceeds the rise over q's edge ahead (the one the centre of mass
    travels towards), the object rolls on over it, falls again, and so on; otherwise it
    stays in q.  A blocked edge ahead stops it (the hull meets the table before its apex).

    transforms : (P, 4, 4) float, object frame -> each pose's frame
    base_edges : per pose (E_p, 2, 3) float, m, pose frame
    final_pose, blocked : per pose (E_p,), the quasi-static outcome of each edge and whether it is blocked
    center_mass : (3,) float, m, object frame;  inertia : (3, 3) float, m^2 per unit mass, object frame
    energy_scale : multiplies the share an impact keeps (at most all of it); 1 is Housner's
    returns : two lists, per pose (E_p,) int:
      - the pose each edge's topple ends in (``final_pose`` where nothing rolls on);
      - the onward pose: where that end pose's edge ahead would have taken the object had the
        impact kept enough energy to rise over it (the next fall the chain stopped short of;
        MODEL.md C.18), or the end pose itself where nothing lies ahead (no travel, no edge
        ahead, a blocked edge ahead, a topple back into the pose) and for edges that do not
        leave the start pose
    """
    com = transforms[:, :3, :3] @ center_mass + transforms[:, :3, 3]  # (P, 3), pose frames
    geometry = [edge_geometry(edges, c) for edges, c in zip(base_edges, com)]
    apex_height = [np.hypot(g.com_distance, c[2]) for g, c in zip(geometry, com)]  # per pose (E_p,), m
    to_object = np.linalg.inv(transforms)

    def roll_on(pose: int, pivot: np.ndarray, energy: float) -> tuple[int, int]:
        """Pose a fall ends in that lands in ``pose`` turning about ``pivot`` ((2, 3), object
        frame) with ``energy`` (m) to spare, and its onward pose (the one the edge ahead leads
        to when the energy kept falls short of the rise; else the end pose itself).

        It stays in the pose it has reached when the centre of mass lies right over the pivot
        line there (no travel, so no edge ahead), when ``exit_edge`` finds none (-1; a closed
        base polygon always has one, so a guard), when the edge ahead is blocked or its topple
        returns to the pose, or when what the impact keeps is not enough to rise over that edge.
        An impact keeps at most the energy it had, so energy plus the centre of mass's height
        never grows and a chain could go round only through lossless impacts; the bound of P
        rolls guards against that, and a chain that reaches it ends where it is.
        """
        for _ in range(len(final_pose)):
            pose_edges = geometry[pose]
            rotation = transforms[pose, :3, :3]
            old = transform_points(transforms[pose], pivot)  # (2, 3), pose frame
            old_axis = unit(old[1] - old[0])
            travel = com[pose] - old[0]
            travel = travel - (travel @ old_axis) * old_axis  # away from the pivot line, horizontal
            travel[2] = 0.0
            if travel @ travel < 1e-18:
                return pose, pose
            ahead = exit_edge(pose_edges.outward, pose_edges.com_distance, unit(travel))
            if ahead < 0 or blocked[pose][ahead] or final_pose[pose][ahead] == pose:
                return pose, pose
            kept = energy * min(1.0, energy_scale * impact_energy_ratio(
                rotation @ inertia @ rotation.T, com[pose], old[0], old_axis, pose_edges.start[ahead], pose_edges.direction[ahead]
            ))
            rise = apex_height[pose][ahead] - com[pose][2]
            following = int(final_pose[pose][ahead])
            if kept <= rise:
                return pose, following
            energy = kept - rise + apex_height[pose][ahead] - com[following][2]
            pivot = transform_points(to_object[pose], base_edges[pose][ahead])
            pose = following
        return pose, pose

    ends, onwards = [], []
    for start, finals in enumerate(final_pose):
        ended, onward = finals.copy(), finals.copy()
        for edge in np.flatnonzero(~blocked[start] & (finals != start)):
            landing = int(finals[edge])
            pivot = transform_points(to_object[start], base_edges[start][edge])  # (2, 3), object frame
            ended[edge], onward[edge] = roll_on(landing, pivot, apex_height[start][edge] - com[landing][2])
        ends.append(ended)
        onwards.append(onward)
    return ends, onwards
