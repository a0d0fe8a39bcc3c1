"""Objects seen from above: convex footprints in the bin plane and the planar geometry of pushing.

An object's footprint is the 2D convex hull of its hull vertices carried into the world by its
pose and projected on the floor z = 0 (thesis 3.1.1: the policies reason in the plane of the bin
bottom).  Polygons are (K, 2) float arrays of metres, counter-clockwise, in the world frame;
a heap's footprints are stacked into one (n, K, 2) array by ``pad_polygons``, the shorter ones
repeating their last vertex (a zero-length edge changes no distance, containment or sum).

Every function broadcasts over leading dimensions, so one call answers all (point, polygon)
or (candidate, polygon) pairs: the planner's speed comes from never looping in Python over
objects, edges or candidates.  numpy only.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

TOLERANCE = 1e-9
"""m; closer than this counts as touching, not overlapping (float noise on metre-scale coordinates)."""


# --- footprints ----------------------------------------------------------------------


def world_points(vertices: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(V, 3) float, m, world frame: ``vertices`` (V, 3) object frame carried by ``pose`` (4, 4)."""
    return vertices @ pose[:3, :3].T + pose[:3, 3]


def convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """(k, 2) float: the convex hull of ``points`` (m, 2), counter-clockwise, no collinear vertex.

    Andrew's monotone chain.  The scan is sequential by nature; on the few tens of
    vertices of a projected hull a plain-float loop is faster than any numpy formulation.
    """
    points = np.asarray(points, dtype=np.float64)
    if len(points) > 16:
        points = points[~strictly_inside_octagon(points)]
    return monotone_chain(points)


def monotone_chain(points: np.ndarray) -> np.ndarray:
    """(k, 2): ``convex_hull_2d`` without the octagon filter (for points already filtered)."""
    order = np.lexsort((points[:, 1], points[:, 0]))  # by x, then y
    ordered = points[order]
    keep = np.ones(len(ordered), dtype=bool)
    keep[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    unique = ordered[keep]
    if len(unique) <= 2:
        return unique
    pts = unique.tolist()

    def chain(sequence):
        out: list[list[float]] = []
        for p in sequence:
            while len(out) >= 2:
                (ox, oy), (ax, ay) = out[-2], out[-1]
                if (ax - ox) * (p[1] - oy) - (ay - oy) * (p[0] - ox) > 0:
                    break
                out.pop()
            out.append(p)
        return out

    lower, upper = chain(pts), chain(reversed(pts))
    return np.array(lower[:-1] + upper[:-1], dtype=np.float64)


OCTAGON = np.stack([np.cos(np.arange(8) * np.pi / 4), np.sin(np.arange(8) * np.pi / 4)], axis=1)


def strictly_inside_octagon(points: np.ndarray) -> np.ndarray:
    """(..., m) bool: ``points`` (..., m, 2) strictly inside the polygon of their extreme points
    in eight directions, so none of them is a hull vertex (Akl-Toussaint: the scan then sees
    a third of a projected hull's points).  Batched over leading dimensions."""
    extreme = np.argmax(points @ OCTAGON.T, axis=-2)  # (..., 8), counter-clockwise around the hull
    corners = np.take_along_axis(points, extreme[..., None], axis=-2)
    normals, offsets = edge_normals(corners)
    slack = normals[..., None, :, 0] * points[..., :, None, 0] + normals[..., None, :, 1] * points[..., :, None, 1]
    slack = slack - offsets[..., None, :]
    # Repeated corners make zero-length edges, which constrain nothing.
    slack = np.where(np.any(normals != 0.0, axis=-1)[..., None, :], slack, -np.inf)
    return slack.max(axis=-1) < -TOLERANCE


def footprint(vertices: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(k, 2) float, m: the footprint of an object with hull ``vertices`` (V, 3, object frame)
    at ``pose`` (4, 4, object -> world), counter-clockwise."""
    return convex_hull_2d(world_points(vertices, pose)[:, :2])


def footprints(hulls: Sequence[np.ndarray], poses: np.ndarray) -> list[np.ndarray]:
    """The footprints (k_i, 2) of a heap: hulls n arrays (V_i, 3) object frame, poses (n, 4, 4).
    As ``footprint`` per object, with the interior points dropped for all objects in one
    batch (numpy's per-call cost is most of the time on a few tens of points)."""
    sizes = [len(h) for h in hulls]
    padded = pad_polygons(hulls)
    world = (np.einsum("nij,nvj->nvi", poses[:, :2, :3], padded) + poses[:, None, :2, 3])  # (n, V, 2)
    inside = strictly_inside_octagon(world)
    return [monotone_chain(world[i, :size][~inside[i, :size]]) for i, size in enumerate(sizes)]


def pad_polygons(polygons: Sequence[np.ndarray]) -> np.ndarray:
    """(n, K, d) float: the polygons (k_i, d) stacked, K = max k_i, each padded by repeating its
    last vertex (a heap's footprints, d = 2, or its hull vertices, d = 3)."""
    size = max(len(p) for p in polygons)
    return np.stack([np.concatenate([p, np.repeat(p[-1:], size - len(p), axis=0)]) for p in polygons])


def polygon_areas(polygons: np.ndarray) -> np.ndarray:
    """(...,) float, m^2: shoelace areas of counter-clockwise ``polygons`` (..., K, 2)."""
    nxt = np.roll(polygons, -1, axis=-2)
    return 0.5 * np.sum(polygons[..., 0] * nxt[..., 1] - nxt[..., 0] * polygons[..., 1], axis=-1)


def edge_normals(polygons: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Outward unit normals (..., K, 2) of the edges v_k -> v_k+1 of counter-clockwise
    ``polygons`` (..., K, 2), and their offsets n_k . v_k (..., K), m.  A zero-length edge
    (padding) has normal 0 and offset 0: a half-plane that holds every point."""
    edges = np.roll(polygons, -1, axis=-2) - polygons
    length = np.sqrt(edges[..., :1] ** 2 + edges[..., 1:] ** 2)
    normals = np.divide(np.stack([edges[..., 1], -edges[..., 0]], axis=-1), length,
                        out=np.zeros_like(edges), where=length > TOLERANCE)
    return normals, normals[..., 0] * polygons[..., 0] + normals[..., 1] * polygons[..., 1]


# --- points, segments and polygons -----------------------------------------------------


def segment_sq_distance(px, py, ax, ay, bx, by) -> np.ndarray:
    """Squared distance, m^2, from points (px, py) to segments (ax, ay) -> (bx, by): x and y
    components as separate broadcastable arrays (numpy is several times faster on them than
    on a trailing axis of length 2).  In place on three full-size arrays: fresh temporaries
    of the free-space grid's size cost more in page faults than in arithmetic."""
    abx, aby = bx - ax, by - ay
    denom = abx * abx + aby * aby
    inverse = 1.0 / np.where(denom > 0, denom, np.inf)  # a zero-length edge: t = 0, its start
    dx = np.subtract(px, ax)
    dy = np.subtract(py, ay)
    t = dx * abx
    scratch = np.multiply(dy, aby, out=np.empty_like(t))
    t += scratch
    t *= inverse
    np.clip(t, 0.0, 1.0, out=t)
    dx -= np.multiply(t, abx, out=scratch)
    dy -= np.multiply(t, aby, out=scratch)
    dx *= dx
    dy *= dy
    dx += dy
    return dx


def edge_slack(points: np.ndarray, polygons: np.ndarray) -> np.ndarray:
    """(..., K) m: signed distance of ``points`` (..., 2) outside each edge line of the convex
    counter-clockwise ``polygons`` (..., K, 2); all <= 0 inside (0 for padding edges)."""
    normals, offsets = edge_normals(polygons)
    return normals[..., 0] * points[..., None, 0] + normals[..., 1] * points[..., None, 1] - offsets


def points_in_polygons(points: np.ndarray, polygons: np.ndarray, tolerance: float = TOLERANCE) -> np.ndarray:
    """(...,) bool: ``points`` (..., 2) inside or within ``tolerance`` m of the boundary of the
    convex counter-clockwise ``polygons`` (..., K, 2), broadcast."""
    return edge_slack(points, polygons).max(axis=-1) <= tolerance


def point_polygon_distance(points: np.ndarray, polygons: np.ndarray) -> np.ndarray:
    """(...,) m: distance from ``points`` (..., 2) to the convex ``polygons`` (..., K, 2); 0 inside."""
    nxt = np.roll(polygons, -1, axis=-2)
    px, py = points[..., None, 0], points[..., None, 1]
    outside = np.sqrt(segment_sq_distance(px, py, polygons[..., 0], polygons[..., 1], nxt[..., 0], nxt[..., 1]).min(axis=-1))
    return np.where(points_in_polygons(points, polygons, 0.0), 0.0, outside)


def segment_polygon_distance(starts: np.ndarray, ends: np.ndarray, polygons: np.ndarray) -> np.ndarray:
    """(...,) m: distance from the segments ``starts`` -> ``ends`` (..., 2) to the convex
    ``polygons`` (..., K, 2), broadcast; 0 when a segment meets a polygon."""
    sx0, sy0, sx1, sy1 = starts[..., None, 0], starts[..., None, 1], ends[..., None, 0], ends[..., None, 1]
    nxt = np.roll(polygons, -1, axis=-2)
    ex0, ey0, ex1, ey1 = polygons[..., 0], polygons[..., 1], nxt[..., 0], nxt[..., 1]
    # Two segments that are apart are nearest at an endpoint of one of them.
    apart = np.minimum(
        np.minimum(segment_sq_distance(sx0, sy0, ex0, ey0, ex1, ey1), segment_sq_distance(sx1, sy1, ex0, ey0, ex1, ey1)),
        np.minimum(segment_sq_distance(ex0, ey0, sx0, sy0, sx1, sy1), segment_sq_distance(ex1, ey1, sx0, sy0, sx1, sy1)),
    )
    dx, dy, ex, ey = sx1 - sx0, sy1 - sy0, ex1 - ex0, ey1 - ey0
    side_e0 = dx * (ey0 - sy0) - dy * (ex0 - sx0)
    side_e1 = dx * (ey1 - sy0) - dy * (ex1 - sx0)
    side_s0 = ex * (sy0 - ey0) - ey * (sx0 - ex0)
    side_s1 = ex * (sy1 - ey0) - ey * (sx1 - ex0)
    crossing = (side_e0 * side_e1 < 0) & (side_s0 * side_s1 < 0)
    nearest = np.sqrt(np.where(crossing, 0.0, apart).min(axis=-1))
    # A segment wholly inside a polygon crosses no edge: its start point says so.
    return np.where(points_in_polygons(starts, polygons, 0.0), 0.0, nearest)


def capsule_hits(starts: np.ndarray, ends: np.ndarray, radius: float, polygons: np.ndarray) -> np.ndarray:
    """(...,) bool: a finger of ``radius`` m swept from ``starts`` to ``ends`` (..., 2) (a capsule)
    overlaps the ``polygons`` (..., K, 2); touching (distance == radius) is not overlapping."""
    return segment_polygon_distance(starts, ends, polygons) < radius - TOLERANCE


# --- rays and translations -----------------------------------------------------------


def ray_interval(origins: np.ndarray, directions: np.ndarray, polygons: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where the rays ``origins + t directions`` ((..., 2) each) cross the convex ``polygons``
    (..., K, 2) (Cyrus-Beck clipping): ``(t_in, t_out)`` (...,) with the ray inside for
    t_in <= t <= t_out; t_in > t_out (both possibly infinite) when it misses.  Units of t:
    m per unit of ``directions``.  A ray grazing an edge misses it."""
    normals, offsets = edge_normals(polygons)
    along = normals[..., 0] * directions[..., None, 0] + normals[..., 1] * directions[..., None, 1]
    slack = offsets - normals[..., 0] * origins[..., None, 0] - normals[..., 1] * origins[..., None, 1]  # >= 0 inside
    parallel = np.abs(along) <= TOLERANCE
    with np.errstate(divide="ignore", invalid="ignore"):
        t = slack / along
    t_in = np.where(~parallel & (along < 0), t, -np.inf).max(axis=-1)
    t_out = np.where(~parallel & (along > 0), t, np.inf).min(axis=-1)
    # Parallel to an edge: inside its half-plane for every t, or for none.  Padding edges
    # (normal 0) are parallel to everything and hold every point.
    real = np.any(normals != 0.0, axis=-1)
    blocked = np.any(parallel & real & (slack <= TOLERANCE), axis=-1)
    return t_in, np.where(blocked, -np.inf, t_out)


def minkowski_difference(moving: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
    """(..., 2K, 2) float: ``obstacles - moving`` = {b - a}, the translations t at which
    ``moving + t`` meets ``obstacles``; both convex counter-clockwise (..., K, 2), result
    counter-clockwise.

    The edges of both polygons merged by angle from the lowest vertex (the classic
    Minkowski-sum construction, vectorised: one argsort over all pairs at once).
    """
    moving, obstacles = np.broadcast_arrays(moving, obstacles)
    negated = -moving
    edges = np.concatenate([np.roll(obstacles, -1, axis=-2) - obstacles, np.roll(negated, -1, axis=-2) - negated], axis=-2)
    angle = np.arctan2(edges[..., 1], edges[..., 0])
    angle = np.where(angle < -TOLERANCE, angle + 2 * np.pi, np.maximum(angle, 0.0))
    order = np.argsort(angle, axis=-1, kind="stable")
    edges = np.take_along_axis(edges, order[..., None], axis=-2)
    start = _lowest(obstacles) + _lowest(negated)
    return start[..., None, :] + np.concatenate([np.zeros_like(edges[..., :1, :]), np.cumsum(edges[..., :-1, :], axis=-2)], axis=-2)


def _lowest(polygons: np.ndarray) -> np.ndarray:
    """(..., 2): the lowest vertex (least y, then least x) of each polygon (..., K, 2)."""
    key = np.lexsort((polygons[..., 0], polygons[..., 1]), axis=-1)[..., :1]
    return np.take_along_axis(polygons, key[..., None], axis=-2)[..., 0, :]


def signed_distances(polygons: np.ndarray) -> np.ndarray:
    """(n, n) float, m: distance between every two of the convex ``polygons`` (n, K, 2); negative
    when they overlap (minus the penetration depth: the shortest translation that separates
    them); 0 on the diagonal."""
    n = len(polygons)
    diff = minkowski_difference(polygons[:, None], polygons[None, :])
    depth = _depth(diff)
    gap = point_polygon_distance(np.zeros((n, n, 2)), diff)
    out = np.where(depth > 0, -depth, gap)
    np.fill_diagonal(out, 0.0)
    return out


def _depth(polygons: np.ndarray) -> np.ndarray:
    """(...,) m: how deep the origin lies inside each convex polygon (..., K, 2); <= 0 outside."""
    normals, offsets = edge_normals(polygons)
    real = np.any(normals != 0.0, axis=-1)
    return np.where(real, offsets, np.inf).min(axis=-1)


def translation_clearance(polygons: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """(n, D) float, m: how far each footprint (n, K, 2) can slide along each unit direction
    (D, 2) before it touches another footprint (inf: never).

    Two footprints that already overlap (stacked objects, seen from above) do not stop a
    slide that makes their overlap shallower (a component along the shortest separating
    translation), and stop any other at once.
    """
    n = len(polygons)
    diff = minkowski_difference(polygons[:, None], polygons[None, :])  # (n, n, 2K, 2): i moving, j obstacle
    normals, offsets = edge_normals(diff)  # the origin is inside edge k's half-plane when offsets[k] >= 0
    real = np.any(normals != 0.0, axis=-1)
    # Cyrus-Beck clipping of the rays t * d from the origin, every pair and direction at once
    # (ray_interval, with the edges shared by all directions).
    along = normals @ directions.T  # (n, n, 2K, D)
    parallel = np.abs(along) <= TOLERANCE
    with np.errstate(divide="ignore", invalid="ignore"):
        t = offsets[..., None] / along
    t_in = np.where(~parallel & (along < 0), t, -np.inf).max(axis=-2)
    t_out = np.where(~parallel & (along > 0), t, np.inf).min(axis=-2)
    blocked = np.any(parallel & (real & (offsets <= TOLERANCE))[..., None], axis=-2)
    hits = ~blocked & (t_out - t_in > TOLERANCE) & (t_out > TOLERANCE)  # a slide that only grazes does not collide
    clear = np.where(hits, np.maximum(t_in, 0.0), np.inf)  # (n, n, D)
    # Overlapping pairs: the origin is inside diff; its nearest edge's outward normal is the
    # shortest way out.
    inner = np.where(real, offsets, np.inf)
    nearest = np.argmin(inner, axis=-1)
    depth = np.take_along_axis(inner, nearest[..., None], axis=-1)[..., 0]
    escape = np.take_along_axis(normals, nearest[..., None, None], axis=-2)[..., 0, :]  # (n, n, 2)
    separating = escape @ directions.T > TOLERANCE
    overlapping = (depth > TOLERANCE)[..., None]
    clear = np.where(overlapping, np.where(separating, np.inf, 0.0), clear)
    clear[np.arange(n), np.arange(n)] = np.inf
    return clear.min(axis=1)


def wall_clearance(polygons: np.ndarray, directions: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """(n, D) float, m: how far each footprint (n, K, 2) can slide along each unit direction
    (D, 2) before a vertex reaches a wall of the floor |x| <= half_extents[0], |y| <= half_extents[1];
    0 for a footprint already past a wall in that direction."""
    along = directions[None, None, :, :]  # (1, 1, D, 2)
    v = polygons[:, :, None, :]  # (n, K, 1, 2)
    wall = np.where(along > 0, half_extents, -half_extents)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(np.abs(along) > TOLERANCE, (wall - v) / along, np.inf)
    return np.maximum(t.min(axis=(1, 3)), 0.0)


def overhang(points: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """(...,) float, m: how far the farthest of ``points`` (..., V, 2) lies beyond the walls of the
    floor |x| <= half_extents[0], |y| <= half_extents[1]; <= 0 when all are inside."""
    return (np.abs(points) - half_extents).max(axis=(-2, -1))


def inside_box(points: np.ndarray, half_extents: np.ndarray) -> np.ndarray:
    """(...,) bool: ``points`` (..., 2) within |x| <= half_extents[0], |y| <= half_extents[1] (+ TOLERANCE)."""
    return np.all(np.abs(points) <= half_extents + TOLERANCE, axis=-1)


def clip_to_box(starts: np.ndarray, directions: np.ndarray, half_extents: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stretch of the lines ``starts + t directions`` ((m, 2) each, unit directions) inside
    the box |x| <= half_extents[0], |y| <= half_extents[1]: (t_low, t_high) (m,), m, empty
    when t_low > t_high (Liang-Barsky)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (-half_extents - starts) / directions
        b = (half_extents - starts) / directions
    parallel = np.abs(directions) <= TOLERANCE
    low = np.where(parallel, np.where(np.abs(starts) <= half_extents + TOLERANCE, -np.inf, np.inf), np.minimum(a, b))
    high = np.where(parallel, np.where(np.abs(starts) <= half_extents + TOLERANCE, np.inf, -np.inf), np.maximum(a, b))
    return low.max(axis=-1), high.min(axis=-1)
