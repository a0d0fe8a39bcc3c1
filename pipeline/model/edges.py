"""The base of a resting object and the geometry of toppling over its edges.

Everything here is in a pose frame (z up, table at z = 0) and is a property of
(pose, edge): computed once per pose, never per trial.

For a base edge (y0, y1), taken counter-clockwise seen from above:
``direction`` e = (y1 - y0) / |y1 - y0|, ``outward`` o = (e_y, -e_x, 0).
Rotating by a positive angle about +e through y0 lifts the interior of the base
and swings the object outward over the edge: (o, e, z) -> e x z = o.

Shapes: E base edges, n hull vertices; every per-edge array is (E, ...) and is
broadcast, in ``pipeline.model.topple``, against (n, 1) per-trial columns (the names
are those of docs/MODEL.md sections 5 and 10).  Row-wise dot products of two (E, 3)
arrays are ``einsum("ij,ij->i", a, b)``; edges x vertices products are
``einsum("enk,ek->en", ...)`` on an (E, n, 2) offset array.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from schema.frames import DOWN, axis_angle_matrices


def base_polygon(vertices: np.ndarray, tolerance: float) -> np.ndarray:
    """Convex polygon of the vertices touching the table.

    vertices : (n, 3) float, m, pose frame (hull vertices)
    tolerance : float, m, vertices with z below this touch the table
    returns : (k, 3) float, m, polygon corners counter-clockwise seen from above, z = 0
    """
    low = vertices[vertices[:, 2] < tolerance][:, :2]  # (m, 2), m <= n touching vertices, xy only
    try:
        hull = ConvexHull(low)
    except (QhullError, ValueError):
        raise ValueError("the base is degenerate (fewer than three non-collinear contact points)") from None
    # scipy orders 2-D hull vertices counter-clockwise.
    corners = low[hull.vertices]  # (k, 2)
    return np.column_stack([corners, np.zeros(len(corners))])


def base_edges(polygon: np.ndarray) -> np.ndarray:
    """Consecutive corner pairs of a base polygon.

    polygon : (k, 3) float, counter-clockwise
    returns : (k, 2, 3) float, edges (y0, y1)
    """
    return np.stack([polygon, np.roll(polygon, -1, axis=0)], axis=1)


@dataclass
class EdgeGeometry:
    """Per-edge quantities of the toppling model (all (E, ...) arrays, pose frame).

    start : (E, 3) y0;  direction : (E, 3) unit e;  outward : (E, 3) unit o
    com_distance : (E,) m, horizontal distance from the centre of mass to the edge line (> 0 inside)
    origin : (E, 3) m, projection of the centre of mass onto the edge line (z = 0)
    half_span : (E,) m, (|y0| + |y1|) / 2 with y measured along the edge from ``origin``;
      tau_max = mu_T F_n half_span for two point contacts at the endpoints (thesis 4.2.2)
    apex_angle : (E,) rad, rotation about the edge that brings the centre of mass above it
    tip_rotation : (E, 3, 3) rotation by ``apex_angle`` about the edge (for contact normals)
    """

    start: np.ndarray
    direction: np.ndarray
    outward: np.ndarray
    com_distance: np.ndarray
    origin: np.ndarray
    half_span: np.ndarray
    apex_angle: np.ndarray
    tip_rotation: np.ndarray


def edge_geometry(edges: np.ndarray, center_mass: np.ndarray) -> EdgeGeometry:
    """Per-edge quantities for ``edges`` (E, 2, 3) and ``center_mass`` (3,), pose frame."""
    y0, y1 = edges[:, 0], edges[:, 1]  # (E, 3) each
    direction = (y1 - y0) / np.linalg.norm(y1 - y0, axis=1, keepdims=True)  # (E, 3), e; base edges have length > 0
    outward = np.column_stack([direction[:, 1], -direction[:, 0], np.zeros(len(edges))])  # (E, 3), o = e x z
    to_com = center_mass - y0  # (3,) - (E, 3) -> (E, 3), c - y0
    com_distance = -np.einsum("ij,ij->i", to_com, outward)  # (E,), d_e = -(c - y0) . o, m
    along = np.einsum("ij,ij->i", to_com, direction)  # (E,), (c - y0) . e, m
    origin = y0 + along[:, None] * direction  # (E, 3), O_e: c projected on the edge line (z = 0)
    s0 = -along  # (E,), y0 measured along e from O_e
    s1 = np.einsum("ij,ij->i", y1 - origin, direction)  # (E,), y1 measured along e from O_e
    apex = np.arctan2(com_distance, center_mass[2])  # (E,), theta_e, rad
    return EdgeGeometry(
        start=y0,
        direction=direction,
        outward=outward,
        com_distance=com_distance,
        origin=origin,
        half_span=0.5 * (np.abs(s0) + np.abs(s1)),
        apex_angle=apex,
        tip_rotation=axis_angle_matrices(direction, apex),  # (E, 3, 3), batched Rodrigues
    )


def push_torques(p_cross_u: np.ndarray, u: np.ndarray, geometry: EdgeGeometry) -> np.ndarray:
    """tau_e = e . ((p - y0) x u): each push's moment about each edge per newton along u, m
    (positive: it turns the object outward over the edge; thesis (7.3)).

    Torque identity (10.2): e . ((p - y0) x u) = e . (p x u) - u . (e x y0), so p x u is
    crossed once per push and e x y0 once per edge, instead of (p - y0) x u once per (push, edge).

    p_cross_u : (n, 3) float, p x u (p in m, pose frame);  u : (n, 3) float, unit pushes
    returns : (n, E) float, m
    """
    return p_cross_u @ geometry.direction.T - u @ np.cross(geometry.direction, geometry.start).T


def landing_angles(geometry: EdgeGeometry, vertices: np.ndarray, tolerance: float) -> np.ndarray:
    """Rotation about each edge at which another part of the hull meets the table.

    A hull vertex at height w and outward offset u from the edge touches the
    table after rotating by atan2(w, u).  Vertices on the table itself are
    skipped: they only rise when rotating outward.

    vertices : (n, 3) float, m, pose frame hull vertices
    tolerance : float, m, base tolerance
    returns : (E,) float, rad, in (0, pi]
    """
    raised = vertices[vertices[:, 2] >= tolerance]  # (m, 3), the vertices above the base
    if len(raised) == 0:
        # A flat hull (nothing above the base) lands on its other side after a half turn.
        return np.full(len(geometry.start), np.pi)
    offset = raised[None, :, :2] - geometry.start[:, None, :2]  # (1, m, 2) - (E, 1, 2) -> (E, m, 2)
    u = np.einsum("enk,ek->en", offset, geometry.outward[:, :2])  # (E, m), outward offset per (edge, vertex)
    w = np.broadcast_to(raised[None, :, 2], u.shape)  # (E, m), heights
    return np.arctan2(w, u).min(axis=1)  # (E,), the first vertex to reach the table


def landing_down(geometry: EdgeGeometry, angles: np.ndarray) -> np.ndarray:
    """Down direction, in the pose frame before the topple, once rotated by ``angles`` about each edge.

    returns : (E, 3) float, unit
    """
    back = axis_angle_matrices(geometry.direction, -angles)  # (E, 3, 3)
    return back @ DOWN  # (E, 3, 3) @ (3,) -> (E, 3)


def rolled_down(
    vertices: np.ndarray, center_mass: np.ndarray, start: np.ndarray, direction: np.ndarray, tolerance: float
) -> np.ndarray | None:
    """Down direction after the finger rolls the object on over a blocked edge (MODEL.md C.6).

    The object turns about +e (``direction``) through ``start``; each time another part of the
    hull meets the table before the centre of mass has passed the pivot (a blocked topple,
    4.2.4), the finger keeps turning it the same way about the landed point farthest outward
    (a line parallel to e), until the centre of mass passes a pivot before the next landing:
    from there gravity finishes the topple.  Quasi-static, the finger stroke assumed long enough.

    vertices : (n, 3) float, m, pose frame hull vertices;  center_mass : (3,) float, m, pose frame
    start : (3,) float, m, a point of the edge on the table;  direction : (3,) unit, horizontal
    tolerance : float, m, base tolerance
    returns : (3,) float, unit, down in the pose frame before the topple, where the object lands
      after passing the last pivot; None when the roll makes no progress (no landed point
      lies outward of the pivot) or does not end within n steps
    """
    outward = np.array([direction[1], -direction[0], 0.0])  # o = e x z
    points, com, pivot = vertices.astype(float), np.asarray(center_mass, float), np.asarray(start, float)
    turned = np.eye(3)  # rotation applied so far, pose frame before -> now
    for _ in range(len(vertices)):
        offset = (points - pivot) @ outward  # (n,), u per vertex
        raised = points[:, 2] >= tolerance
        if not raised.any():
            return None
        landing = float(np.arctan2(points[raised, 2], offset[raised]).min())  # rad, first vertex down
        apex = float(np.arctan2(-(com - pivot) @ outward, com[2]))  # rad, the COM above the pivot
        step = axis_angle_matrices(direction[None], np.array([landing]))[0]  # (3, 3)
        points = (points - pivot) @ step.T + pivot
        com = step @ (com - pivot) + pivot
        turned = step @ turned
        if landing >= apex:
            return turned.T @ DOWN  # the world's down seen in the pose frame before the topple
        touching = points[:, 2] < tolerance
        ahead = (points[touching] - pivot) @ outward  # (m,), landed points' outward offsets
        if ahead.max() <= tolerance:
            return None
        pivot = points[touching][np.argmax(ahead)] * np.array([1.0, 1.0, 0.0])
    return None
