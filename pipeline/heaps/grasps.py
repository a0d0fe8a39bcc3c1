"""Grasp confidence of a heap, per gripper, in [0, 1]: the robust quality of the best
accessible grasp on any object (thesis 2.2: V_s and V_j of a heap state).

Two grippers:

* suction (Dex-Net 3.0, the toppling model's V_s of ``pipeline.model.suction``): a cup seals on
  the surface and holds the object against gravity; robust quality = the fraction of perturbed
  samples (position, approach axis, friction, mass) that seal and hold.  Approach from above
  (within ``max_approach_angle`` of straight down).  Accessible when the cup and the gripper
  body behind it touch neither a neighbour nor the bin, and the body misses the object itself.
* parallel jaw (Dex-Net 2.0's analytic robust force closure): two point contacts with Coulomb
  friction are in force closure when the line between them lies inside both friction cones
  (the antipodal test of dex-net's ``PointGraspMetrics3D.force_closure``); robust quality =
  the fraction of perturbed samples (grasp centre, object position, grasp axis, friction) in
  force closure with a width the jaws open to.  Jaws close along a near-horizontal axis and
  approach from above; accessible when both open fingers and the palm touch nothing.

Speed: what does not depend on the object's pose is computed once per object id, in the
object frame, and cached (candidates, their perturbations, seals, jaw contacts, force
closure).  Per heap, the candidates are moved to the world, the pose-dependent parts (gravity
wrench, floor, approach cone) are vectorised numpy, and collision checks (python-fcl, after a
numpy bounding-box prefilter) run best-first and stop at the first accessible grasp.
"""

from __future__ import annotations

from dataclasses import dataclass

import fcl
import numpy as np
import trimesh

from clutter.state import HeapState
from schema.frames import tangent_frames, transform_points, unit, z_to_axes

from ..model.config import SuctionConfig
from ..model.suction import perturb, sample_candidates, seal_contacts, table_collisions, wrench_resisted
from .config import GRAVITY, HeapConfig, JawConfig
from .objects import HeapObject, ObjectLibrary
from .seeds import heap_stream
from .world import bin_boxes, library_for

GRIPPERS = ("suction", "parallel_jaw")
ALL_FACES = np.pi
"""An approach-angle limit that keeps every face: candidates are sampled over the whole surface
in the object frame, and the pose decides which face up."""


@dataclass(frozen=True)
class Grasp:
    """The best accessible grasp of one gripper on a heap (world frame).

    gripper : "suction" or "parallel_jaw"
    target : int, index of the grasped object in the heap
    quality : float in [0, 1], robust quality
    point : (3,) float, m, suction contact, or the jaws' centre between the contacts
    axis : (3,) float, unit; suction: approach (gripper -> object); jaws: closing axis
    approach : (3,) float, unit, the direction the gripper moves in along (suction: = axis)
    width : float, m, jaw contact width (0 for suction)
    """

    gripper: str
    target: int
    quality: float
    point: np.ndarray
    axis: np.ndarray
    approach: np.ndarray
    width: float = 0.0


@dataclass(frozen=True)
class HeapConfidence:
    """Per gripper the best accessible grasp (None when there is none: confidence 0)."""

    suction: Grasp | None
    parallel_jaw: Grasp | None

    def quality(self, gripper: str) -> float:
        grasp = getattr(self, gripper)
        return 0.0 if grasp is None else grasp.quality

    @property
    def overall(self) -> float:
        """The better gripper's confidence (the thesis's overall grasp confidence)."""
        return max(self.quality(g) for g in GRIPPERS)

    @property
    def best(self) -> Grasp | None:
        """The best grasp of either gripper (suction on ties), None when neither has one."""
        grasps = [g for g in (self.suction, self.parallel_jaw) if g is not None]
        return max(grasps, key=lambda g: g.quality) if grasps else None


# ============================================================================ per-object caches


@dataclass
class SuctionCandidates:
    """Suction candidates of one object, object frame, pose independent.

    points : (C, 3) m; axes : (C, 3) unit approach (= -outward normal)
    sample_axes : (C, S, 3) perturbed approach axes; friction, mass : (C, S)
    sealed : (C, S) bool; contacts : (C, S, 3) m (the sample's point where not sealed)
    """

    points: np.ndarray
    axes: np.ndarray
    sample_axes: np.ndarray
    friction: np.ndarray
    mass: np.ndarray
    sealed: np.ndarray
    contacts: np.ndarray


def suction_candidates(obj: HeapObject, config: SuctionConfig, seed: int, object_id: str) -> SuctionCandidates:
    """Sample and seal-test the object's suction candidates once (cached on the object)."""
    key = ("suction", config, seed)
    if key not in obj.cache:
        rng = heap_stream(seed, -1, "grasps", f"suction\x00{object_id}")
        mesh = obj.model.mesh
        points, axes = sample_candidates(mesh, config.n_candidates, ALL_FACES, rng)
        s_points, s_axes, friction, mass = perturb(points, axes, obj.model.mass, config, rng)
        sealed, contacts = seal_contacts(mesh, s_points, s_axes, config)
        contacts = np.where(sealed[..., None], contacts, s_points)
        obj.cache[key] = SuctionCandidates(points, axes, s_axes, friction, mass, sealed, contacts)
    return obj.cache[key]


@dataclass
class JawCandidates:
    """Parallel-jaw candidates of one object, object frame, pose independent.

    centres : (C, 3) m, midpoint of the two contacts; axes : (C, 3) unit, contact 1 -> contact 2
    widths : (C,) m; quality : (C,) robust force-closure quality in [0, 1]
    Only candidates with quality > 0 are kept.
    """

    centres: np.ndarray
    axes: np.ndarray
    widths: np.ndarray
    quality: np.ndarray


def cast_first(mesh: trimesh.Trimesh, origins: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First hit of each ray on the mesh (one batched embree call).

    origins, directions : (N, 3) float, m and unit
    returns : points (N, 3) m (NaN on a miss), outward face normals (N, 3) (NaN on a miss)
    """
    tri = mesh.ray.intersects_first(origins, directions)
    hit = tri >= 0
    points = np.full(origins.shape, np.nan)
    normals = np.full(origins.shape, np.nan)
    if hit.any():
        normal = mesh.face_normals[tri[hit]]
        # The hit triangle's plane, in float64 (embree works in float32).
        along = np.sum(directions[hit] * normal, axis=1)
        depth = np.sum((mesh.triangles[tri[hit], 0] - origins[hit]) * normal, axis=1) / np.where(along == 0, np.nan, along)
        points[hit] = origins[hit] + depth[:, None] * directions[hit]
        normals[hit] = normal
    return points, normals


def jaw_contacts(
    mesh: trimesh.Trimesh, centres: np.ndarray, axes: np.ndarray, reach: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Where two jaws closing along each line meet the surface: from ``reach`` before the
    centre along +axis (contact 1) and from ``reach`` past it along -axis (contact 2).

    centres, axes : (..., 3) float, a point on each line (m) and its unit direction
    reach : float, m, more than the object's diameter
    returns : c1, n1, c2, n2, each (..., 3): contact points (m) and outward normals; NaN on a miss
    """
    lead = centres.shape[:-1]
    flat_c, flat_a = centres.reshape(-1, 3), axes.reshape(-1, 3)
    origins = np.concatenate([flat_c - reach * flat_a, flat_c + reach * flat_a])
    directions = np.concatenate([flat_a, -flat_a])
    points, normals = cast_first(mesh, origins, directions)
    n = len(flat_c)
    return (
        points[:n].reshape(lead + (3,)), normals[:n].reshape(lead + (3,)),
        points[n:].reshape(lead + (3,)), normals[n:].reshape(lead + (3,)),
    )


def force_closure(
    c1: np.ndarray, n1: np.ndarray, c2: np.ndarray, n2: np.ndarray, friction: np.ndarray, min_width: float
) -> np.ndarray:
    """Two-contact force closure under Coulomb friction (the antipodal test).

    The grasp is in force closure when the line joining the contacts lies in both friction
    cones: the angle between it and each contact's normal is at most atan(mu).  Normals are
    taken up to sign, as dex-net does, so a mesh with flipped faces still works.

    c1, n1, c2, n2 : (..., 3) float, contacts (m) and unit normals (NaN: no contact)
    friction : (...,) float, coefficient mu >= 0
    returns : (...,) bool
    """
    diff = c2 - c1
    dist = np.linalg.norm(diff, axis=-1)
    cos_limit = 1.0 / np.sqrt(1.0 + np.square(friction))  # cos(atan(mu))
    with np.errstate(invalid="ignore"):
        in_1 = np.abs(np.sum(n1 * diff, axis=-1)) >= cos_limit * dist
        in_2 = np.abs(np.sum(n2 * diff, axis=-1)) >= cos_limit * dist
        closed = (dist > min_width) & in_1 & in_2
    return np.where(np.isfinite(dist), closed, False)


def tilt_within(axes: np.ndarray, max_angle: float, rng: np.random.Generator) -> np.ndarray:
    """Each unit axis tilted by an angle uniform in [0, max_angle] about a random perpendicular.

    axes : (n, 3) float, unit;  returns : (n, 3) float, unit
    """
    u, v = tangent_frames(axes)
    spin = rng.uniform(0.0, 2 * np.pi, len(axes))[:, None]
    angle = rng.uniform(0.0, max_angle, len(axes))[:, None]
    side = np.cos(spin) * u + np.sin(spin) * v
    return unit(np.cos(angle) * axes + np.sin(angle) * side)


def jaw_candidates(obj: HeapObject, config: JawConfig, seed: int, object_id: str) -> JawCandidates:
    """Sample antipodal grasps and their robust force-closure quality once (cached on the object).

    Dex-Net 2.0's antipodal sampler in short: a surface point, a closing axis in the friction
    cone about its inward normal, and the jaws' contacts where they close along that line.
    """
    key = ("jaw", config, seed)
    if key in obj.cache:
        return obj.cache[key]
    rng = heap_stream(seed, -1, "grasps", f"jaw\x00{object_id}")
    mesh = obj.model.mesh
    reach = float(np.linalg.norm(mesh.extents)) + 0.01
    points, inward = sample_candidates(mesh, config.n_candidates, ALL_FACES, rng)
    lines = tilt_within(inward, config.cone_spread * np.arctan(config.friction), rng)
    c1, n1, c2, n2 = jaw_contacts(mesh, points, lines, reach)
    centres, axes = 0.5 * (c1 + c2), unit(c2 - c1)
    widths = np.linalg.norm(c2 - c1, axis=-1)
    nominal = force_closure(c1, n1, c2, n2, np.full(len(points), config.friction), config.min_width)
    nominal &= widths <= config.max_opening
    centres, axes, widths = centres[nominal], axes[nominal], widths[nominal]

    shape = (len(centres), config.n_samples)
    offsets = rng.normal(0.0, config.grasp_position_std, shape + (3,)) + rng.normal(
        0.0, config.object_position_std, shape + (3,)
    )
    tilt = rng.normal(0.0, config.axis_std, shape + (3,))
    friction = np.maximum(rng.normal(config.friction, config.friction_std, shape), 0.0)
    nominal_axes = np.broadcast_to(axes[:, None, :], shape + (3,))
    tilt = tilt - np.sum(tilt * nominal_axes, axis=-1, keepdims=True) * nominal_axes
    s_axes = unit(nominal_axes + tilt)
    s1, m1, s2, m2 = jaw_contacts(mesh, centres[:, None, :] + offsets, s_axes, reach)
    held = force_closure(s1, m1, s2, m2, friction, config.min_width)
    held &= np.linalg.norm(s2 - s1, axis=-1) <= config.max_opening
    quality = held.mean(axis=1) if len(centres) else np.zeros(0)
    keep = quality > 0
    obj.cache[key] = JawCandidates(centres[keep], axes[keep], widths[keep], quality[keep])
    return obj.cache[key]


# ============================================================================ collision scene


@dataclass
class Scene:
    """The heap's obstacles for the gripper checks: the bin's five boxes, then one fcl object
    per heap object, with world axis-aligned bounding boxes for a numpy prefilter.

    owners : (O,) int, heap index of each obstacle, -1 for the bin
    lower, upper : (O, 3) float, m, world bounding boxes
    """

    objects: list[fcl.CollisionObject]
    owners: np.ndarray
    lower: np.ndarray
    upper: np.ndarray


def build_scene(state: HeapState, heap_objects: list[HeapObject]) -> Scene:
    objects, owners, lower, upper = [], [], [], []
    for centre, half in bin_boxes(state.bin):
        objects.append(fcl.CollisionObject(fcl.Box(*(2 * half)), fcl.Transform(np.eye(3), centre)))
        owners.append(-1)
        lower.append(centre - half)
        upper.append(centre + half)
    for k, (obj, pose) in enumerate(zip(heap_objects, state.poses)):
        objects.append(fcl.CollisionObject(obj.collision_geometry, fcl.Transform(pose[:3, :3], pose[:3, 3])))
        owners.append(k)
        hull = transform_points(pose, obj.model.hull.vertices)
        lower.append(hull.min(axis=0))
        upper.append(hull.max(axis=0))
    return Scene(objects, np.array(owners), np.array(lower).reshape(-1, 3), np.array(upper).reshape(-1, 3))


def box_bounds(centres: np.ndarray, rotations: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World bounding boxes of oriented boxes.

    centres : (n, 3) m; rotations : (n, 3, 3), box -> world; half : (3,) or (n, 3) m
    returns : lower, upper, each (n, 3)
    """
    extent = np.einsum("nij,nj->ni", np.abs(rotations), np.broadcast_to(half, centres.shape))
    return centres - extent, centres + extent


def part_hits(
    scene: Scene, shape: fcl.CollisionGeometry, centre: np.ndarray, rotation: np.ndarray,
    lower: np.ndarray, upper: np.ndarray, skip: int | None,
) -> bool:
    """Whether one gripper part (a box or cylinder placed at centre/rotation, world bounding box
    lower/upper) touches any obstacle except the heap object ``skip``."""
    near = np.flatnonzero(np.all(scene.lower <= upper, axis=1) & np.all(scene.upper >= lower, axis=1))
    if not len(near):
        return False
    placed = fcl.CollisionObject(shape, fcl.Transform(rotation, centre))
    request = fcl.CollisionRequest()
    for o in near:
        if skip is not None and scene.owners[o] == skip:
            continue
        if fcl.collide(placed, scene.objects[o], request, fcl.CollisionResult()) > 0:
            return True
    return False


# ============================================================================ suction


def suction_options(
    state: HeapState, heap_objects: list[HeapObject], config: HeapConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every object's suction candidates in the world with their pose-dependent robust quality.

    returns : owner (M,) int, quality (M,), points (M, 3) m, approach axes (M, 3) unit
    """
    sc = config.suction
    owners, qualities, points, axes = [], [], [], []
    for k, (obj, pose) in enumerate(zip(heap_objects, state.poses)):
        cand = suction_candidates(obj, sc, config.seed, state.object_ids[k])
        if not len(cand.points):
            continue
        rotation, shift = pose[:3, :3], pose[:3, 3]
        world_axes = cand.axes @ rotation.T
        up = -world_axes[:, 2] >= np.cos(sc.max_approach_angle)
        if not up.any():
            continue
        s_axes = cand.sample_axes[up] @ rotation.T
        contacts = transform_points(pose, cand.contacts[up])
        com = rotation @ obj.model.center_mass + shift
        held = wrench_resisted(contacts, s_axes, com, cand.mass[up], cand.friction[up], sc, GRAVITY)
        ok = cand.sealed[up] & held & ~table_collisions(contacts, s_axes, sc)
        quality = ok.mean(axis=1)
        owners.append(np.full(int(up.sum()), k))
        qualities.append(quality)
        points.append(transform_points(pose, cand.points[up]))
        axes.append(world_axes[up])
    if not owners:
        return np.zeros(0, int), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3))
    return np.concatenate(owners), np.concatenate(qualities), np.concatenate(points), np.concatenate(axes)


def suction_blocked(scene: Scene, target: int, point: np.ndarray, axis: np.ndarray, config: SuctionConfig) -> bool:
    """Whether a suction gripper at ``point`` approaching along ``axis`` (world) is obstructed.

    Two cylinders: the cup and body as one cylinder of the larger radius from the contact back
    along the approach, checked against the neighbours and the bin (the cup may touch only the
    object it grasps); and the rigid body alone, from ``max_deflection`` behind the contact,
    against the grasped object too (an overhang of the object itself)."""
    rotation = z_to_axes(axis[None])[0]
    radius = max(config.cup_radius, config.gripper_radius)
    length = config.max_deflection + config.gripper_length
    parts = [
        (fcl.Cylinder(radius, length), point - 0.5 * length * axis, radius, length, target),
        (
            fcl.Cylinder(config.gripper_radius, config.gripper_length),
            point - (config.max_deflection + 0.5 * config.gripper_length) * axis,
            config.gripper_radius, config.gripper_length, None,
        ),
    ]
    for shape, centre, r, h, skip in parts:
        lower, upper = box_bounds(centre[None], rotation[None], np.array([r, r, h / 2]))
        if part_hits(scene, shape, centre, rotation, lower[0], upper[0], skip):
            return True
    return False


# ============================================================================ parallel jaw


def jaw_options(
    state: HeapState, heap_objects: list[HeapObject], config: HeapConfig
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every object's jaw candidates in the world whose axis is near horizontal.

    returns : owner (M,) int, quality (M,), centres (M, 3) m, axes (M, 3) unit, widths (M,) m
    """
    jc = config.jaw
    owners, qualities, centres, axes, widths = [], [], [], [], []
    for k, (obj, pose) in enumerate(zip(heap_objects, state.poses)):
        cand = jaw_candidates(obj, jc, config.seed, state.object_ids[k])
        if not len(cand.quality):
            continue
        world_axes = cand.axes @ pose[:3, :3].T
        level = np.abs(world_axes[:, 2]) <= np.sin(jc.max_axis_tilt)
        owners.append(np.full(int(level.sum()), k))
        qualities.append(cand.quality[level])
        centres.append(transform_points(pose, cand.centres[level]))
        axes.append(world_axes[level])
        widths.append(cand.widths[level])
    if not owners:
        return np.zeros(0, int), np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0)
    return tuple(np.concatenate(x) for x in (owners, qualities, centres, axes, widths))


def jaw_approach(axes: np.ndarray) -> np.ndarray:
    """The most vertical downward direction perpendicular to each closing axis.

    axes : (n, 3) float, unit, not vertical;  returns : (n, 3) float, unit
    """
    down = np.array([0.0, 0.0, -1.0])
    return unit(down - (axes @ down)[:, None] * axes)


def jaw_parts(centre: np.ndarray, axis: np.ndarray, approach: np.ndarray, width: float, config: JawConfig):
    """The open gripper at a grasp: two finger boxes and the palm, world frame.

    Frame: x the closing axis, z the approach (into the object), y = z cross x.  Fingers open to
    the contact width plus ``clearance`` on each side (at most ``max_opening``); their tips reach
    ``tip_depth`` past the grasp centre; the palm spans both fingers above them.
    returns : [(half extents (3,), centre (3,))], rotation (3, 3) box -> world
    """
    side = np.cross(approach, axis)
    rotation = np.stack([axis, side, approach], axis=1)
    opening = min(width + 2 * config.clearance, config.max_opening)
    finger_half = np.array([config.finger_thickness, config.finger_width, config.finger_length]) / 2
    down = config.tip_depth - config.finger_length / 2
    offset = opening / 2 + config.finger_thickness / 2
    palm_half = np.array([opening / 2 + config.finger_thickness, config.finger_width / 2, config.palm_thickness / 2])
    palm_down = config.tip_depth - config.finger_length - config.palm_thickness / 2
    return [
        (finger_half, centre + offset * axis + down * approach),
        (finger_half, centre - offset * axis + down * approach),
        (palm_half, centre + palm_down * approach),
    ], rotation


def jaw_blocked(scene: Scene, centre: np.ndarray, axis: np.ndarray, approach: np.ndarray, width: float, config: JawConfig) -> bool:
    """Whether the open jaws at this grasp touch anything: the bin, a neighbour, or the grasped object."""
    parts, rotation = jaw_parts(centre, axis, approach, width, config)
    for half, part_centre in parts:
        lower, upper = box_bounds(part_centre[None], rotation[None], half)
        if part_hits(scene, fcl.Box(*(2 * half)), part_centre, rotation, lower[0], upper[0], None):
            return True
    return False


# ============================================================================ heap confidence


def best_first(owner: np.ndarray, quality: np.ndarray, objects: list[int] | None) -> np.ndarray:
    """Candidate order for the accessibility checks: highest quality first (stable, so ties
    keep the object order and the sampling order), zero-quality and excluded objects dropped."""
    keep = quality > 0
    if objects is not None:
        keep &= np.isin(owner, objects)
    index = np.flatnonzero(keep)
    return index[np.argsort(-quality[index], kind="stable")]


def heap_confidence(
    state: HeapState, config: HeapConfig, library: ObjectLibrary | None = None, objects: list[int] | None = None
) -> HeapConfidence:
    """The best accessible suction and parallel-jaw grasp of the heap.

    objects : heap indices to consider (all when None), e.g. to score one object's grasps
    returns : HeapConfidence; a gripper's grasp is None when no candidate is accessible
    """
    library = library_for(config, library)
    heap_objects = [library[k] for k in state.object_ids]
    scene = build_scene(state, heap_objects)

    suction = None
    owner, quality, points, axes = suction_options(state, heap_objects, config)
    for i in best_first(owner, quality, objects):
        if not suction_blocked(scene, int(owner[i]), points[i], axes[i], config.suction):
            suction = Grasp("suction", int(owner[i]), float(quality[i]), points[i].copy(), axes[i].copy(), axes[i].copy())
            break

    jaw = None
    owner, quality, centres, axes, widths = jaw_options(state, heap_objects, config)
    approaches = jaw_approach(axes) if len(axes) else np.zeros((0, 3))
    for i in best_first(owner, quality, objects):
        if not jaw_blocked(scene, centres[i], axes[i], approaches[i], float(widths[i]), config.jaw):
            jaw = Grasp(
                "parallel_jaw", int(owner[i]), float(quality[i]), centres[i].copy(), axes[i].copy(),
                approaches[i].copy(), float(widths[i]),
            )
            break
    return HeapConfidence(suction, jaw)
