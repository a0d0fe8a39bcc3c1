"""The five planar push policies of thesis 3.2 (Danielczuk et al. 2018, "Linear Push Policies
to Increase Grasp Access for Robot Bin Picking"): which object to push, along which line.

    push = plan_push("boundary_shear", state, hulls, centers_mass)          # Push or None
    push = plan_push("quasi_random", state, hulls, centers_mass, rng=np.random.default_rng(7))

Every policy reasons in the plane of the bin floor (thesis 3.1.1): each object is its
footprint (``clutter.footprints``) and its centre of mass projected on z = 0.  A push is a
straight finger stroke through the target's centre of mass: the finger comes down from
above ``approach_offset`` outside the footprint behind the centre of mass, moves through it
and goes on ``push_length`` past the point where it meets the footprint.  Every policy:

- clips the stroke to the bin: the finger's axis stays ``finger_radius`` inside the walls;
  a stroke that would then move its target less than ``min_push`` is dropped;
- needs the finger's start to be free: at least ``finger_radius`` from every footprint
  (it comes down there) and inside the bin;
- except the quasi-random baseline (which the thesis only clips to the bin), needs the
  approach to be collision-free: the finger swept from its start to the target (a capsule
  of ``finger_radius``) touches no other footprint.

``plan_push`` answers None when no candidate passes these checks ("no collision-free
push"), as the thesis's conservative policies do (3.4).

Two notions the thesis takes from the paper, reconstructed here (the paper's own text was
not at hand; see docs/SERVICE.md "Heap planning"):

- the *free space point* p_i of object i: the point of the bin floor farthest from the walls
  and from every other object's footprint (object i itself ignored), found on a grid of
  ``grid_resolution``; ties go to the point nearest c_i;
- the *direction of most free space* of object i: the unit vector from c_i to p_i (none when
  p_i is within half a grid cell of c_i: the object already sits in its freest spot).

numpy only: the service's heap planner imports this module.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from . import footprints as fp
from .state import HeapState, Push

POLICIES = ("quasi_random", "boundary_shear", "free_space", "max_clearance", "cluster_diffusion")
"""The policies of thesis 3.2, in its order; ``quasi_random`` is the baseline."""

FLAT_AREA = 1e-8
"""m^2; a footprint smaller than this (1 mm x 0.01 mm) is a flat hull, not an object."""


@dataclass(frozen=True)
class PushConfig:
    """The planner's numbers: m unless said otherwise.  The thesis gives none of them; the
    sources are said per field."""

    finger_radius: float = 0.01
    """Radius of the finger, which is the closed parallel-jaw gripper of the physical
    experiments (thesis 3.3.2; the YuMi's closed fingers are about 2 cm across)."""
    push_length: float = 0.05
    """How far the finger goes on after meeting the target: the thesis's "fixed length" (3.2.1),
    here half a typical corpus object (5-15 cm), enough to open a finger-wide gap."""
    approach_offset: float = 0.02
    """The finger's axis starts this far outside the target's footprint (behind its centre of
    mass): a finger radius plus 1 cm for perception error.  At least ``finger_radius``."""
    directions: int = 16
    """Uniform push directions tried per object: 16 in the maximum clearance policy (thesis
    3.2.4); the free space policy turns its ideal direction by the same steps.  Even, so that
    every direction's opposite is also tried."""
    grid_resolution: float = 0.01
    """Cell size of the floor grid on which the free space points are found: 1 cm, below the
    finger's size, so a finer grid would not change a push."""
    max_grid_points: int = 20_000
    """The grid grows coarser on a bin so large that it would have more cells (bounds the
    planner's time whatever bin a request describes)."""
    cluster_size: int = 3
    """Largest cluster of the cluster diffusion policy ("clusters of one to three objects",
    thesis 3.2.5)."""
    cluster_distance: float = 0.15
    """Centres of mass further apart than this are never linked into one cluster: about the
    largest corpus object, so objects that cannot touch are not a cluster (our choice; the
    thesis clusters "based on their position" without a number)."""
    random_attempts: int = 16
    """Draws of (object, direction) the quasi-random baseline makes until the finger's start
    is free; none free: no push."""
    min_push: float = 0.005
    """A stroke clipped so short that it moves its target less than this is no push."""
    min_clearance: float = 0.001
    """Backward clearance below this counts as this in the clearance ratio (a ratio over zero
    would rank every object pressed against something alike)."""

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"PushConfig.{f.name} must be a positive number, got {value!r}")
        if self.approach_offset < self.finger_radius:
            raise ValueError(
                f"PushConfig.approach_offset ({self.approach_offset} m) must be at least finger_radius "
                f"({self.finger_radius} m): the finger would start on the object"
            )
        if self.directions < 4 or self.directions % 2:
            raise ValueError(f"PushConfig.directions must be even and at least 4, got {self.directions}")
        for name in ("directions", "max_grid_points", "cluster_size", "random_attempts"):
            if not isinstance(getattr(self, name), int):
                raise TypeError(f"PushConfig.{name} must be an integer, got {getattr(self, name)!r}")


# --- the heap in the plane -----------------------------------------------------------


@dataclass(frozen=True)
class Scene:
    """A heap as the policies see it.

    half_extents : (2,) m, half the bin floor; polygons : (n, K, 2) footprints (padded);
    centers : (n, 2) m, centres of mass projected; heights : (n,) m, their height above the floor.
    """

    half_extents: np.ndarray
    polygons: np.ndarray
    centers: np.ndarray
    heights: np.ndarray
    config: PushConfig

    def __len__(self) -> int:
        return len(self.centers)


def scene(state: HeapState, hulls: Sequence[np.ndarray], centers_mass: np.ndarray, config: PushConfig) -> Scene:
    """The heap in the floor plane; ValueError naming the object for malformed or non-finite input.

    hulls : n arrays (V_i, 3) float, m, object frame (hull vertices); centers_mass : (n, 3) m, object frame.
    """
    n = len(state)
    if len(hulls) != n:
        raise ValueError(f"got {len(hulls)} hulls for a heap of {n} objects")
    centers_mass = np.asarray(centers_mass, dtype=np.float64)
    if centers_mass.shape != (n, 3):
        raise ValueError(f"centers_mass must be ({n}, 3), got {centers_mass.shape}")
    if not np.isfinite(state.poses).all():
        bad = int(np.flatnonzero(~np.isfinite(state.poses).all(axis=(1, 2)))[0])
        raise ValueError(f"object {bad} ('{state.object_ids[bad]}'): its pose holds a NaN or infinite entry")
    if not np.isfinite(centers_mass).all():
        bad = int(np.flatnonzero(~np.isfinite(centers_mass).all(axis=1))[0])
        raise ValueError(f"object {bad} ('{state.object_ids[bad]}'): its centre of mass is not finite")
    arrays = []
    for i, hull in enumerate(hulls):
        hull = np.asarray(hull, dtype=np.float64)
        if hull.ndim != 2 or hull.shape[1] != 3 or len(hull) < 3:
            raise ValueError(f"object {i} ('{state.object_ids[i]}'): hull vertices must be (V >= 3, 3), got {hull.shape}")
        if not np.isfinite(hull).all():
            raise ValueError(f"object {i} ('{state.object_ids[i]}'): its hull vertices are not all finite")
        arrays.append(hull)
    padded = fp.pad_polygons(fp.footprints(arrays, state.poses))
    flat = fp.polygon_areas(padded) < FLAT_AREA
    if flat.any():
        bad = int(np.flatnonzero(flat)[0])
        raise ValueError(f"object {bad} ('{state.object_ids[bad]}'): its footprint has no area (a flat hull seen edge-on)")
    world_com = np.einsum("nij,nj->ni", state.poses[:, :3, :3], centers_mass) + state.poses[:, :3, 3]
    return Scene(state.bin.half_extents, padded, world_com[:, :2], world_com[:, 2], config)


def outside_bin(state: HeapState, hulls: Sequence[np.ndarray], tolerance: float) -> tuple[int, str, float] | None:
    """The first object whose hull (V_i, 3, object frame) reaches more than ``tolerance`` m past a
    wall of the bin or below its floor: (index, "outside_bin" or "below_floor", how far, m);
    None when every object is in the bin."""
    half = state.bin.half_extents
    for index, hull in enumerate(hulls):
        world = fp.world_points(np.asarray(hull, dtype=np.float64), state.poses[index])
        past = float(fp.overhang(world[:, :2], half))
        if past > tolerance:
            return index, "outside_bin", past
        below = float(-world[:, 2].min())
        if below > tolerance:
            return index, "below_floor", below
    return None


# --- strokes -------------------------------------------------------------------------


@dataclass(frozen=True)
class Strokes:
    """Candidate pushes, m of them: target (m,) int, direction (m, 2) unit, start and end
    (m, 2) m (the finger's axis, clipped), feasible (m,) bool."""

    target: np.ndarray
    direction: np.ndarray
    start: np.ndarray
    end: np.ndarray
    feasible: np.ndarray


def unit(angles: np.ndarray) -> np.ndarray:
    """(..., 2) unit vectors at ``angles`` (...,) rad from +x."""
    return np.stack([np.cos(angles), np.sin(angles)], axis=-1)


def strokes(sc: Scene, targets: np.ndarray, directions: np.ndarray, *, check_approach: bool = True,
            clip_start: bool = False) -> Strokes:
    """The finger's stroke for each (target (m,), unit direction (m, 2)) and whether it is feasible.

    ``clip_start``: a start outside the bin moves forward into it (the baseline's clipping);
    otherwise such a stroke is infeasible (it would hit the wall).
    """
    cfg = sc.config
    targets = np.asarray(targets, dtype=np.int64)
    d = np.asarray(directions, dtype=np.float64)
    com = sc.centers[targets]
    _, behind = fp.ray_interval(com, -d, sc.polygons[targets])  # distance from the COM back out of its footprint
    behind = np.maximum(np.nan_to_num(behind, posinf=0.0), 0.0)
    origin = com - d * (behind + cfg.approach_offset)[:, None]
    contact_t = cfg.approach_offset - cfg.finger_radius  # the finger meets the footprint here
    box = sc.half_extents - cfg.finger_radius
    low, high = fp.clip_to_box(origin, d, box)
    start_t = np.maximum(low, 0.0) if clip_start else np.where(low <= fp.TOLERANCE, 0.0, np.inf)
    end_t = np.minimum(high, contact_t + cfg.push_length)
    feasible = (end_t - np.maximum(start_t, contact_t) >= cfg.min_push) & (start_t <= high)
    start_t = np.where(np.isfinite(start_t), start_t, 0.0)
    start = origin + d * start_t[:, None]
    end = origin + d * np.maximum(end_t, start_t)[:, None]
    # The finger comes down at its start: a finger radius clear of every footprint.
    clearance = fp.point_polygon_distance(start[:, None], sc.polygons[None])
    feasible &= np.all(clearance >= cfg.finger_radius - fp.TOLERANCE, axis=1)
    if check_approach and len(sc) > 1:
        contact = origin + d * np.maximum(contact_t, start_t)[:, None]
        hits = fp.capsule_hits(start[:, None], contact[:, None], cfg.finger_radius, sc.polygons[None])
        hits[np.arange(len(targets)), targets] = False  # the target is what the finger is going to
        feasible &= ~hits.any(axis=1)
    return Strokes(targets, d, start, end, feasible)


def to_push(sc: Scene, policy: str, s: Strokes, index: int) -> Push:
    """Candidate ``index`` of ``s`` as a world-frame Push at the target's centre-of-mass height
    (at least a finger radius, so the finger clears the floor)."""
    z = max(float(sc.heights[s.target[index]]), sc.config.finger_radius)
    return Push(policy, int(s.target[index]), np.array([*s.start[index], z]), np.array([*s.end[index], z]))


CHUNK = 16
"""Candidates checked at a time, best first: the checks are most of a plan's time, and the
best few candidates usually include a feasible one."""


def best_stroke(sc: Scene, policy: str, targets: np.ndarray, directions: np.ndarray, score: np.ndarray,
                **checks) -> Push | None:
    """The feasible candidate (targets (m,), unit directions (m, 2)) of highest ``score`` (m,)
    (ties: the earlier one) as a Push; None when none is feasible.  ``checks`` go to ``strokes``."""
    order = np.argsort(-np.asarray(score, dtype=np.float64), kind="stable")
    for first in range(0, len(order), CHUNK):
        pick = order[first:first + CHUNK]
        s = strokes(sc, targets[pick], directions[pick], **checks)
        if s.feasible.any():
            return to_push(sc, policy, s, int(np.argmax(s.feasible)))
    return None


# --- free space, pairs, clusters -------------------------------------------------------


TOP_BLOCK = 8
"""Cells per side of the coarsest blocks in which ``free_space_points`` starts looking (a power of two)."""
CHILDREN = np.array([[0, 0], [0, 1], [1, 0], [1, 1]])


def floor_grid(half_extents: np.ndarray, config: PushConfig) -> tuple[np.ndarray, np.ndarray]:
    """The grid over the bin floor: cell size (2,) m, ``grid_resolution`` (coarser when that would
    exceed ``max_grid_points`` cells) and cell counts (2,) int.  Cell (i, j) is centred at
    ((i, j) + 0.5) * size - half_extents."""
    extent = 2 * half_extents
    resolution = max(config.grid_resolution, math.sqrt(extent[0] * extent[1] / config.max_grid_points))
    counts = np.maximum(np.ceil(extent / resolution).astype(int), 1)
    return extent / counts, counts


def room(points: np.ndarray, sc: Scene) -> np.ndarray:
    """(G, n) m: for each point (G, 2) and object i, the distance to the nearest wall or footprint
    other than i's (object i ignored: the room it could be pushed into)."""
    walls = (sc.half_extents - np.abs(points)).min(axis=1)[:, None]  # (G, 1)
    n = len(sc)
    if n == 1:
        return walls
    to_objects = fp.point_polygon_distance(points[:, None], sc.polygons[None])  # (G, n)
    nearest = to_objects.argmin(axis=1)
    two = np.partition(to_objects, 1, axis=1)[:, :2]
    # Ignoring object i: the nearest other footprint is the second nearest where i is the nearest.
    others = np.where(nearest[:, None] == np.arange(n)[None], two[:, 1:2], two[:, :1])
    return np.minimum(walls, others)


def free_space_points(sc: Scene, objects: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The free space points p (m, 2) m of ``objects`` (m,) int: the grid cell centre of most
    ``room`` (ties: nearest the object's c), and their directions of most free space (m, 2)
    (unit; zero when p is within half a cell of c).

    Branch and bound, exact on the grid: ``room`` changes by at most the distance moved, so a
    block of cells holds nothing better than its middle cell's room plus the distance from that
    cell to its farthest one.  The search starts with blocks of TOP_BLOCK x TOP_BLOCK cells and
    quarters the blocks that may hold a maximum (for any of ``objects``) down to single cells.
    """
    objects = np.asarray(objects, dtype=np.int64)
    size, counts = floor_grid(sc.half_extents, sc.config)
    block = TOP_BLOCK
    blocks = np.stack([a.ravel() for a in np.meshgrid(*(np.arange(-(-c // block)) for c in counts), indexing="ij")], axis=1)
    while True:
        first = blocks * block
        last = np.minimum(first + block, counts) - 1  # blocks at the far walls may be cut short
        middle = (first + last) // 2
        points = (middle + 0.5) * size - sc.half_extents
        value = room(points, sc)[:, objects]  # (B, m), exact at real cells
        if block == 1:
            break
        reach = np.linalg.norm(np.maximum(middle - first, last - middle) * size, axis=1)  # (B,)
        keep = np.any(value + reach[:, None] >= value.max(axis=0) - fp.TOLERANCE, axis=1)
        block //= 2
        blocks = (blocks[keep][:, None] * 2 + CHILDREN[None]).reshape(-1, 2)
        blocks = blocks[np.all(blocks * block < counts, axis=1)]
    near = np.linalg.norm(points[:, None] - sc.centers[objects][None], axis=2)
    best = value >= value.max(axis=0) - fp.TOLERANCE
    free = points[np.argmin(np.where(best, near, np.inf), axis=0)]
    offset = free - sc.centers[objects]
    length = np.linalg.norm(offset, axis=1, keepdims=True)
    direction = np.divide(offset, length, out=np.zeros_like(offset), where=length > float(size.min()) / 2)
    return free, direction


def closest_pair(sc: Scene) -> tuple[int, int]:
    """The two objects whose projected centres of mass are nearest (thesis 3.1.1); lower indices on ties."""
    gaps = np.linalg.norm(sc.centers[:, None] - sc.centers[None], axis=2)
    gaps[np.diag_indices(len(sc))] = np.inf
    i, j = np.unravel_index(np.argmin(gaps), gaps.shape)
    return int(min(i, j)), int(max(i, j))


def clusters(centers: np.ndarray, size: int, reach: float) -> np.ndarray:
    """(n,) int cluster label per object: single linkage on centre distances (n, 2) m, nearest
    pairs first, linking only centres within ``reach`` m and never past ``size`` objects
    (thesis 3.2.5's clusters of one to three)."""
    n = len(centers)
    label = np.arange(n)
    gaps = np.linalg.norm(centers[:, None] - centers[None], axis=2)
    i, j = np.triu_indices(n, 1)
    for k in np.argsort(gaps[i, j], kind="stable"):
        if gaps[i[k], j[k]] > reach:
            break
        a, b = label[i[k]], label[j[k]]
        if a != b and np.count_nonzero(label == a) + np.count_nonzero(label == b) <= size:
            label[label == b] = a
    return label


def cosine(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(m,) cosine similarity of (m, 2) vectors; 0 where either is zero."""
    norms = np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1)
    return np.divide(np.sum(a * b, axis=1), norms, out=np.zeros(len(a)), where=norms > 0)


# --- the policies --------------------------------------------------------------------


def quasi_random(sc: Scene, rng: np.random.Generator) -> Push | None:
    """Thesis 3.2.1: a random object, a random direction, a fixed-length push through its centre of
    mass, clipped to the bin.  Redrawn (``random_attempts`` draws, all made up front so the
    answer depends on the seed alone) while the finger's start is not free."""
    attempts = sc.config.random_attempts
    targets = rng.integers(len(sc), size=attempts)
    angles = rng.uniform(0.0, 2 * np.pi, size=attempts)
    return best_stroke(sc, "quasi_random", targets, unit(angles), -np.arange(attempts), check_approach=False, clip_start=True)


def boundary_shear(sc: Scene) -> Push | None:
    """Thesis 3.2.2: the two closest objects; the line c_i c_j and its perpendicular (their boundary);
    four pushes along the perpendicular, two through each centre of mass; the collision-free
    one closest to its object's direction of most free space."""
    if len(sc) < 2:
        return None
    i, j = closest_pair(sc)
    across = sc.centers[j] - sc.centers[i]
    if np.linalg.norm(across) <= fp.TOLERANCE:
        return None  # one centre above the other: no line between them
    boundary = np.array([-across[1], across[0]]) / np.linalg.norm(across)
    targets = np.array([i, i, j, j])
    directions = np.stack([boundary, -boundary, boundary, -boundary])
    _, free = free_space_points(sc, np.array([i, j]))
    return best_stroke(sc, "boundary_shear", targets, directions, cosine(directions, free[[0, 0, 1, 1]]))


def free_space(sc: Scene) -> Push | None:
    """Thesis 3.2.3: the two closest objects; each one's free space point p; per object the
    collision-free direction closest to c p (the ideal turned by ``directions`` steps, nearest
    first, counter-clockwise before clockwise at the same size: the thesis names no order, and a fixed
    one keeps the choice reproducible); of the two, the push whose object is nearer its p."""
    if len(sc) < 2:
        return None
    pair = np.array(closest_pair(sc))
    points, free = free_space_points(sc, pair)
    usable = np.linalg.norm(free, axis=1) > 0
    pair, points, free = pair[usable], points[usable], free[usable]
    if not len(pair):
        return None
    count = sc.config.directions
    steps = np.array([0] + [s * k for k in range(1, count // 2) for s in (1, -1)] + [count // 2])  # nearest first
    ideal = np.arctan2(free[:, 1], free[:, 0])
    angles = ideal[:, None] + steps[None] * (2 * np.pi / count)  # (2, D)
    pushes = [best_stroke(sc, "free_space", np.full(len(steps), t), unit(angles[row]), -np.arange(len(steps)))
              for row, t in enumerate(pair)]
    choices = [(float(np.linalg.norm(points[row] - sc.centers[t])), row) for row, t in enumerate(pair) if pushes[row] is not None]
    return pushes[min(choices)[1]] if choices else None


def clearance_ratios(sc: Scene) -> tuple[np.ndarray, np.ndarray]:
    """(n, D) ratio of forward to backward clearance per object and direction, and the directions
    (D, 2): the footprint slid along each direction until it meets another footprint or a wall
    (thesis 3.2.4)."""
    count = sc.config.directions
    directions = unit(np.arange(count) * (2 * np.pi / count))
    forward = np.minimum(fp.translation_clearance(sc.polygons, directions),
                         fp.wall_clearance(sc.polygons, directions, sc.half_extents))
    backward = np.roll(forward, -count // 2, axis=1)  # direction k + D/2 is the opposite of k
    return forward / np.maximum(backward, sc.config.min_clearance), directions


def max_clearance(sc: Scene) -> Push | None:
    """Thesis 3.2.4 (Chang, Smith and Fox): 16 directions per object, clearance in front of and
    behind the footprint; the collision-free push of largest forward/backward ratio."""
    ratios, directions = clearance_ratios(sc)
    n, count = ratios.shape
    return best_stroke(sc, "max_clearance", np.repeat(np.arange(n), count), np.tile(directions, (n, 1)), ratios.ravel())


def cluster_diffusion(sc: Scene) -> Push | None:
    """Thesis 3.2.5: clusters of one to three objects; pushes from each cluster's centroid m through
    each member's centre of mass c; scored by the cosine of m c with the member's direction
    of most free space; the best collision-free one."""
    label = clusters(sc.centers, sc.config.cluster_size, sc.config.cluster_distance)
    members = np.flatnonzero(np.bincount(label)[label] >= 2)  # a lone object has no centroid to leave
    if not len(members):
        return None
    centroids = np.stack([sc.centers[label == label[m]].mean(axis=0) for m in members])
    away = sc.centers[members] - centroids
    length = np.linalg.norm(away, axis=1)
    members, away = members[length > fp.TOLERANCE], away[length > fp.TOLERANCE]
    if not len(members):
        return None
    directions = away / np.linalg.norm(away, axis=1, keepdims=True)
    _, free = free_space_points(sc, members)
    return best_stroke(sc, "cluster_diffusion", members, directions, cosine(directions, free))


DEFAULT = PushConfig()


def plan_push(policy: str, state: HeapState, hulls: Sequence[np.ndarray], centers_mass: np.ndarray,
              rng: np.random.Generator | None = None, config: PushConfig = DEFAULT) -> Push | None:
    """The push ``policy`` chooses for the heap, or None when it finds no collision-free push.

    policy : one of POLICIES
    state : the heap (bin, object ids, poses object -> world (n, 4, 4))
    hulls : n arrays (V_i, 3) float, m, object frame: each object's convex hull vertices
    centers_mass : (n, 3) float, m, object frame
    rng : the random stream of ``quasi_random`` (required by it, unused by the others)
    config : the planner's numbers (``PushConfig``)

    ValueError (one line, naming the object) for an unknown policy, mismatched shapes or
    non-finite input.  An empty heap has no push (None).
    """
    if policy not in POLICIES:
        raise ValueError(f"unknown push policy {policy!r}; known: {', '.join(POLICIES)}")
    if policy == "quasi_random" and rng is None:
        raise ValueError("the quasi_random policy needs rng (a numpy Generator)")
    if len(state) == 0:
        if len(hulls):
            raise ValueError(f"got {len(hulls)} hulls for an empty heap")
        return None
    sc = scene(state, hulls, centers_mass, config)
    if policy == "quasi_random":
        return quasi_random(sc, rng)
    return {"boundary_shear": boundary_shear, "free_space": free_space, "max_clearance": max_clearance,
            "cluster_diffusion": cluster_diffusion}[policy](sc)
