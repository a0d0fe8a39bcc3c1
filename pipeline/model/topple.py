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

Shapes (docs/MODEL.md section 10 uses the same names).  A pose has A actions, T trials
per action, E base edges and the object P poses.  The ``ok`` actions run in blocks of
a <= ``chunk_actions``; a block's a x T trials are flattened, action-major, to n = a T
rows (row i is action i // T, trial i % T), so every per-trial array is (n, ...) and every
per-(trial, edge) array is (n, E): actions x trials x edges with the first two axes
flattened.  Per-edge arrays (``EdgeGeometry``) are (E, ...) and broadcast against
(n, 1) per-trial columns; results are reshaped back to (a, T) per block.

Vectorisation identities (numbered as in docs/MODEL.md section 10):

- batched rotation / dot: ``einsum("nij,nj->ni", R, v)`` is R_i v_i for every row,
  ``einsum("ij,ij->i", a, b)`` is a_i . b_i; ``v @ M.T`` applies one matrix M to every row;
- (10.1) cone at the apex: -u . (Rot_e n) = -sum_jk (u n^T)_jk (Rot_e)_jk, so all E
  apex cosines of a trial are one (n, 9) @ (9, E) product of flattened outer products;
- (10.2) torque identity: e . ((p - y0) x u) = e . (p x u) - u . (e x y0), so one batched
  cross product p x u (n, 3) serves all edges: (n, 3) @ (3, E) - (n, 3) @ (3, E);
- (10.3) tau_z about O_e: ((p - O_e) x u)_z = (p x u)_z - u . (-O_y, O_x, 0);
- (10.4) the limit-surface ellipse (7.9) divided through by F*^2, so it needs no f = F* u;
- (10.5) tan(beta) <= mu as sin(beta) <= mu cos(beta), no acos or tan;
- (10.6) least-force edge: argmin over E of where(pass, F*, inf);
- (10.7) P(x'|x,u) as one bincount of (action row * P + landed pose).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from schema.frames import axis_angle_matrices, transform_points, unit
from schema.neighbourhood import neighbour_mean, neighbour_pairs
from schema.vocabulary import OUTCOME_NO_EDGE, OUTCOME_NOT_EVALUATED, STATUS_OK

from .boosted_map import boosted_features, load_trees, map_boosted_rows
from .config import FROM_ABOVE_U_Z, ToppleConfig
from .edges import EdgeGeometry, edge_geometry, push_torques
from .feature_map import map_down_rows, map_rows, map_side_rows
from .landing_onward import onward_shares
from .landing_spread import landing_prior, spread_landings
from .mesh import ObjectModel
from .outcomes import Actions, StablePose, ToppleTable
from .poses import stability_margin
from .recalibration import recalibrate_rows

MIN_PUSH_TORQUE = 1e-12
"""m (torque per newton of push), (7.4): a push rotates the object outward over an edge
only if e . ((p - y0) x u) exceeds this.  Not zero, because a push through the edge
line (or parallel to it) gives a torque that is zero up to rounding (|p| ~ 0.1 m,
float64 eps ~ 2e-16, so rounding is ~1e-17 m), and F* = m g d / tau would then be a
huge force of arbitrary sign.  1e-12 m is far below any physical lever arm (a 1 um
lever arm is 1e-6 m) and far above rounding.  ``pipeline.model.reference`` uses the
same constant so both models cut at the same place."""

TILE_ELEMENTS = 65536
"""Entries per row tile: (trial, edge) entries in ``trial_outcomes``, (trial, xyz) entries
in ``noisy_trials``' rotations.  A whole block (n ~ 25 000 trials x E edges) in one pass
would make each of the conditions' temporaries several MB; tiles bound that.  The size
weighs cache against Python's cost per numpy call: the corrected model made about 150
calls per tile (C.2's balance, C.14's two points, C.11; since stop 54 C.14 and C.11 run once
per block, and C.2 on the pairs that can tip), and at 8192 entries (64 kB per
array, stop 8's choice for the thesis's few passes) that overhead was a seventh of the
engine's time.  On 8 bench objects, four interleaved rounds (``reports/bench.json``,
``tile_sizes``), the median took 9.25 s at 8192, 8.24 s at 32768, 7.57 s at 65536 and
7.72 s at 131072; ``make bench`` measured 0.132 s per pose right before 0.161 s at 8192.
Every operation is row-wise, so the tile size should never change a result (checked, not
guaranteed by BLAS: identical outcomes and forces on the 20 bench objects, 19 million trials,
and on the whole default dataset; ``tests/test_topple.py`` holds a 97-entry tiling to the
default's table); it is not a model parameter."""

ENGINE_REVISION = 2
"""Bumped by every change to the engine that changes a table's numbers for the same parameters and
object (not by speed-ups that keep every bit): part of each shard's identity (``shards.shard_inputs``),
so a resumed build never mixes shards of two engines.  1: stop 42, neighbourhood means summed in index
order (``schema.neighbourhood.neighbour_mean``), the same bits whatever BLAS's thread count.  2: stop 48,
a pose too sparse for any push to have (12.15)'s neighbourhood takes the argmax instead of grasping
(``mdp.choice_by_means``; no pose of the default dataset is, so its tables are unchanged)."""

NO_ROTATION_AXIS = (0.0, 0.0, 1.0)
"""Rotation axis of the noise-free variants, whose rotation angle is 0: any unit axis
gives the identity; a fixed one keeps ``TrialNoise`` valid (unit axes) in every variant."""


@dataclass
class TrialNoise:
    """Noise draws for A actions x T trials (zeros and means for noise-free variants).

    mu_table, mu_finger : (A, T) float, friction coefficients (mu_finger clipped at 0)
    contact_offset : (A, T, 3) float, m
    direction_offset : (A, T, 3) float
    rotation_axis : (A, T, 3) float, unit; rotation_angle : (A, T) float, rad
    stuck_draw : (A, T) float in [0, 1), decides the ``stuck_finger`` topples (drawn last, so
      adding it changed no other draw; zeros for noise-free variants)
    """

    mu_table: np.ndarray
    mu_finger: np.ndarray
    contact_offset: np.ndarray
    direction_offset: np.ndarray
    rotation_axis: np.ndarray
    rotation_angle: np.ndarray
    stuck_draw: np.ndarray


def sample_noise(rng: np.random.Generator, n_actions: int, config: ToppleConfig) -> TrialNoise:
    """Draw every trial's noise for ``n_actions`` actions, in a fixed order."""
    shape = (n_actions, config.trials)
    if not config.robust:
        return TrialNoise(
            mu_table=np.full(shape, config.mu_table_mean),
            mu_finger=np.full(shape, config.mu_finger_mean),
            contact_offset=np.zeros(shape + (3,)),
            direction_offset=np.zeros(shape + (3,)),
            rotation_axis=np.tile(NO_ROTATION_AXIS, shape + (1,)),
            rotation_angle=np.zeros(shape),
            stuck_draw=np.zeros(shape),
        )
    return TrialNoise(
        mu_table=rng.normal(config.mu_table_mean, config.mu_table_std, shape),
        mu_finger=np.maximum(rng.normal(config.mu_finger_mean, config.mu_finger_std, shape), 0.0),
        contact_offset=rng.normal(0.0, config.contact_std, shape + (3,)),
        direction_offset=rng.normal(0.0, config.direction_std, shape + (3,)),
        rotation_axis=_unit_rows(rng.normal(size=shape + (3,))),
        rotation_angle=rng.normal(0.0, config.rotation_std, shape),
        stuck_draw=rng.random(shape),
    )


@dataclass
class Trials:
    """Per-trial inputs of the model, flattened over (action, trial); pose frame.

    contact : (n, 3) float, m;  normal : (n, 3) float, unit outward;  push : (n, 3) float, unit
    mu_table, mu_finger : (n,) float;  valid : (n,) bool, the finger found the surface from outside
    stuck_draw : (n,) float in [0, 1) (``TrialNoise``)
    """

    contact: np.ndarray
    normal: np.ndarray
    push: np.ndarray
    mu_table: np.ndarray
    mu_finger: np.ndarray
    valid: np.ndarray
    stuck_draw: np.ndarray

    def take(self, rows) -> Trials:
        """The trials at ``rows`` (an index array, boolean mask or slice) of every field."""
        if isinstance(rows, slice):
            return Trials(*(getattr(self, f)[rows] for f in Trials.__dataclass_fields__))  # views
        rows = np.asarray(rows)
        if rows.dtype == bool:
            rows = np.flatnonzero(rows)  # ``take`` would read a mask as indices 0 and 1
        # ``take`` along the rows: the same copy as fancy indexing, several times faster for (n, 3) arrays.
        return Trials(*(getattr(self, f).take(rows, axis=0) for f in Trials.__dataclass_fields__))


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
    # (a, T, k) -> (n, k), n = a T, action-major: row i is action i // T, trial i % T.
    flat = lambda v: v.reshape(a * t, -1)  # noqa: E731
    # (a, 1, 3) + (a, T, 3): each action's nominal direction broadcast over its trials.
    push = _unit_rows(directions[:, None, :] + noise.direction_offset)  # (a, T, 3), u0 of (8.2)
    if not config.robust:
        return Trials(
            contact=flat(np.broadcast_to(points[:, None], (a, t, 3))).copy(),
            normal=flat(np.broadcast_to(normals[:, None], (a, t, 3))).copy(),
            push=flat(push),
            mu_table=noise.mu_table.ravel(),
            mu_finger=noise.mu_finger.ravel(),
            valid=np.ones(a * t, dtype=bool),
            stuck_draw=noise.stuck_draw.ravel(),
        )
    axes, angles = flat(noise.rotation_axis), noise.rotation_angle.ravel()  # (n, 3), (n,)
    # (a, 1, 3) + (a, T, 3) + (a, 1, 3): p + dp + ray_offset n of (8.2), then relative to the COM
    start = flat(points[:, None] + noise.contact_offset + config.ray_offset * normals[:, None]) - center_mass  # (n, 3)
    inward = flat(np.broadcast_to(-normals[:, None], (a, t, 3)))  # (n, 3), -n
    nominal = flat(push)  # (n, 3), u0
    origin, ray, push = np.empty((a * t, 3)), np.empty((a * t, 3)), np.empty((a * t, 3))
    # Row tiles of about TILE_ELEMENTS / 3 trials keep each tile's (r, 3, 3) rotations in
    # cache for their three products (row-wise, so the same numbers as one pass over the block).
    for rows in _row_tiles(a * t, 3):
        rotation = axis_angle_matrices(axes[rows], angles[rows])  # (r, 3, 3), R
        # Batched R_i v_i ("nij,nj->ni"), about the centre of mass: o = c + R (. - c).
        origin[rows] = np.einsum("nij,nj->ni", rotation, start[rows]) + center_mass  # (r, 3)
        ray[rows] = np.einsum("nij,nj->ni", rotation, inward[rows])  # (r, 3), R(-n)
        push[rows] = np.einsum("nij,nj->ni", rotation, nominal[rows])  # (r, 3), u = R u0

    # One embree cast per block, in the object frame (the mesh's frame).  Directions take
    # only the rotation: rows times its transpose, ``v @ M.T`` = (M v^T)^T.
    to_object = np.linalg.inv(transform)  # (4, 4), pose -> object
    faces, rays, hits = obj.mesh.ray.intersects_id(
        transform_points(to_object, origin), ray @ to_object[:3, :3].T, multiple_hits=False, return_locations=True
    )  # (h,) face index, (h,) row index into n, (h, 3) hit point (object frame); h <= n hits
    contact = np.full((a * t, 3), np.nan)  # (n, 3), NaN where the ray missed
    normal = np.full((a * t, 3), np.nan)  # (n, 3)
    contact[rays] = transform_points(transform, hits)
    hit_normal = obj.mesh.face_normals.take(faces, axis=0) @ transform[:3, :3].T  # (h, 3), pose frame
    normal[rays] = hit_normal  # each ray hits at most once (first hits only)
    valid = np.zeros(a * t, dtype=bool)  # (n,)
    # Front face iff n' . r < 0 (8.3): an exact sign test, a grazing hit (n' . r ~ 0) is
    # as good as any other, so no tolerance.
    valid[rays] = np.einsum("ij,ij->i", hit_normal, ray.take(rays, axis=0)) < 0.0
    return Trials(contact, normal, push, noise.mu_table.ravel(), noise.mu_finger.ravel(), valid, noise.stuck_draw.ravel())


def trial_outcomes(trials: Trials, edges: EdgeGeometry, mass: float, config: ToppleConfig) -> tuple[np.ndarray, np.ndarray]:
    """Edge each trial topples over, and the force it takes.

    mass : kg;  config : the variant, its corrections (``applied_corrections``; none: the
      thesis's model, section 7) and their parameters (``max_finger_force``,
      ``finger_friction_scale``, ``stroke``, ``tip_path_points``, ``stuck_finger_share``) and ``gravity``
    returns : edge (n,) int (``OUTCOME_NO_EDGE`` when none), required_force (n,) float, N (inf when none)

    Rows are trials (n), columns edges (E): per-trial columns (n, 1) broadcast against
    per-edge rows (E,) into (n, E).  An invalid trial passes no edge ((7.10) and C.2 both
    require ``valid``), so only the valid rows are computed and the others keep "no edge"
    at infinite force, which is exactly what the conditions give them; the rows' contacts and
    normals are made finite (``nan_to_num``) wherever some are not.  The least-force edge is
    found in ``_row_tiles`` of about ``TILE_ELEMENTS`` (trial, edge) entries, the corrections that
    follow it once for the whole block (every operation is row-wise, so neither the row
    selection nor the tiling changes a result).
    """
    n = len(trials.mu_table)
    corrections = config.applied_corrections  # parsed once, not once per tile
    spin_stops = _spin_stops(config, corrections)
    edge = np.full(n, OUTCOME_NO_EDGE, dtype=np.intp)  # (n,)
    required = np.full(n, np.inf)  # (n,), N
    live, kept, kept_edge, kept_required = _least_force_block(trials, edges, mass, config, corrections, spin_stops)
    # The corrections below look at one edge per trial, or at few trials: whole-block arrays, one
    # pass each instead of one per tile (all row-wise, so the same numbers).
    _check_corrections(kept, edges, kept_edge, kept_required, mass, config, corrections, spin_stops)
    edge[live] = np.where(np.isfinite(kept_required), kept_edge, OUTCOME_NO_EDGE)
    required[live] = kept_required
    return edge, required


def _spin_stops(config: ToppleConfig, corrections: frozenset[str]) -> bool:
    """Whether the slip check (7.9) counts the moment about the vertical: the variants that predict
    rotations, unless C.9 (``edge_spin``), where that moment turns the object without stopping the
    topple and the limit surface keeps only its force term."""
    return config.predicts_rotations and "edge_spin" not in corrections


def _least_force_block(
    trials: Trials, edges: EdgeGeometry, mass: float, config: ToppleConfig, corrections: frozenset[str], spin_stops: bool
) -> tuple[np.ndarray, Trials, np.ndarray, np.ndarray]:
    """The least-force passing edge (10.6) of the rows ``trial_outcomes`` computes, before the corrections
    that follow it: live (m,) int, those rows of the n trials; kept, their trials (contacts and normals
    made finite); edge (m,) int and required (m,) float, N (inf where no edge passes).

    Only the valid rows are computed (an invalid trial passes no edge: (7.10) and C.2 both require
    ``valid``), unless fewer than two are valid, in tiles of about ``TILE_ELEMENTS`` (trial, edge) entries."""
    live = np.flatnonzero(trials.valid)  # (m,) valid rows
    if len(live) < 2:
        # A lone valid row would make the tile's matrix products 1-row ones (a gemv, not the
        # block's gemm); compute every row instead, the invalid ones fail on ``valid``.
        live = np.arange(len(trials.mu_table))
    kept = trials.take(live)  # (m, ...)
    if not (np.isfinite(kept.contact).all() and np.isfinite(kept.normal).all()):
        # Only where needed (the engine's valid rows hit the mesh, so they are finite): a copy each.
        kept = replace(kept, contact=np.nan_to_num(kept.contact), normal=np.nan_to_num(kept.normal))  # (m, 3) each
    kept_edge, kept_required = np.empty(len(live), dtype=np.intp), np.empty(len(live))  # (m,) each
    for rows in _row_tiles(len(live), len(edges.com_distance)):
        kept_edge[rows], kept_required[rows] = _least_force_edges(kept.take(rows), edges, mass, config, corrections,
                                                                    spin_stops)
    return live, kept, kept_edge, kept_required


TRIAL_STAGES = ("invalid", "face_never_recedes", "friction_holds", "table_slides", "over_force_limit",
                "stops_before_apex", "tips", "carried_finger_tips", "stuck_finger_tips")
"""Where ``trial_stages`` finds each trial of the C.2 family decided, in the order the balance checks
them: the finger missed the object; no base edge's face recedes from the advancing finger; the finger's
friction leaves no edge a tipping moment; every edge that would turn needs more grip than the table
has; every edge that passes needs more than the finger's force limit (C.1); the least-force edge
passes but the object stops on the way to its apex (C.14) or short of the finger's stroke (C.10); the
object tips (C.2); nothing of the above tips it, but the carried finger does (C.23); nor that, but the
stuck finger does (C.11)."""


def trial_stages(trials: Trials, edges: EdgeGeometry, mass: float, config: ToppleConfig) -> np.ndarray:
    """Where each trial's topple is decided, as ``trial_outcomes`` decides it: a study's account of why the
    model says a push stays (docs/VALIDATION.md, "Where the model says no").

    trials : n trials;  mass : kg;  config : a variant with ``finger_friction`` (C.2), whose balance has
      the stages; the thesis's conditions (section 7) are checked all at once and have none
    returns : (n,) int8, index into ``TRIAL_STAGES``.  A trial ``trial_outcomes`` topples is at "tips" or a
      later stage (the carried or the stuck finger's) and every other trial at an earlier one: how far its
      best edge got.
    """
    corrections = config.applied_corrections
    if "finger_friction" not in corrections:
        raise ValueError("trial_stages follows C.2's balance: the variant must apply finger_friction "
                         f"(it applies {', '.join(sorted(corrections)) or 'none'})")
    spin_stops = _spin_stops(config, corrections)
    stage = np.zeros(len(trials.mu_table), dtype=np.int8)  # "invalid" until a stage is reached
    live, kept, edge, required = _least_force_block(trials, edges, mass, config, corrections, spin_stops)
    shape, pair, force, passes = sliding_pairs(kept, edges, mass, config.gravity, config.finger_friction_scale, spin_stops)
    # How far each (trial, edge) pair gets: 2 its face recedes (every pair listed), 3 it turns, 4 the table
    # holds, 5 within the force limit; a valid trial with no pair stops at 1.
    level = 2 + np.isfinite(force).astype(np.int8) + passes
    if "force_limit" in corrections:
        level = level + (passes & (force > 0.0) & (force <= config.max_finger_force))
    else:
        level = level + passes
    row = pair // shape[1]
    counted = kept.valid[row]  # every row is computed when fewer than two are valid: those stay "invalid"
    reached = kept.valid.astype(np.int8)  # (m,)
    np.maximum.at(reached, row[counted], level[counted].astype(np.int8))
    # The least-force edge passed where ``required`` is finite.  ``trial_outcomes``' corrections follow in
    # its order on the same arrays: first those that stop a passing trial (C.10, C.14), then each that tips
    # a stopped one (C.23, C.11) alone, its new topples labelled; tip_back only re-aims, so it is left out.
    _check_corrections(kept, edges, edge, required, mass, config, corrections - {"carried_finger", "stuck_finger", "tip_back"},
                       spin_stops)
    reached[np.isfinite(required)] = TRIAL_STAGES.index("tips")
    for name, tipped in (("carried_finger", "carried_finger_tips"), ("stuck_finger", "stuck_finger_tips")):
        if name in corrections:
            stopped = ~np.isfinite(required)
            _check_corrections(kept, edges, edge, required, mass, config, frozenset({name}) | corrections & {"force_limit"},
                               spin_stops)
            reached[stopped & np.isfinite(required)] = TRIAL_STAGES.index(tipped)
    stage[live] = reached
    return stage


def _row_tiles(n: int, per_row: int) -> list[slice]:
    """ceil(n per_row / ``TILE_ELEMENTS``) nearly equal row ranges covering range(n), as
    ``np.array_split``; one (empty) range when n = 0.  A tile has at least min(n, 2) rows
    (so a matrix product or einsum never degenerates to a 1-row case the block would not use)."""
    n_tiles = max(1, min(n // 2, -(-n * per_row // TILE_ELEMENTS)))  # ceil(n per_row / TILE_ELEMENTS)
    bounds = [n * i // n_tiles for i in range(n_tiles + 1)]
    return [slice(start, stop) for start, stop in zip(bounds[:-1], bounds[1:])]


def _unit_rows(vectors: np.ndarray) -> np.ndarray:
    """``schema.frames.unit`` bit for bit, without its masked division: the same norm
    (``np.linalg.norm`` sums x^2 + y^2 + z^2 in this order), then a plain division unless
    some vector is zero (or NaN), which goes to ``unit`` itself.

    vectors : (..., 3) float;  returns : (..., 3) float
    """
    x, y, z = vectors[..., 0], vectors[..., 1], vectors[..., 2]
    norm = x * x
    norm += y * y
    norm += z * z
    norm = np.sqrt(norm, out=norm)[..., None]  # (..., 1)
    if not (norm > 0.0).all():
        return unit(vectors)
    return vectors / norm


def _least_force_edges(
    trials: Trials, edges: EdgeGeometry, mass: float, config: ToppleConfig, corrections: frozenset[str], spin_stops: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The least-force passing edge (10.6) of each trial of one tile of r trials (contact and normal
    finite): edge (r,) int (any index where none passes), required_force (r,) float, N (inf where
    none).  corrections : ``config.applied_corrections``;  spin_stops : as ``trial_outcomes`` finds it"""
    gravity, max_force = config.gravity, config.max_finger_force
    # A finger pushes (F* > 0: a negative F* means the centre of mass is already past the edge,
    # not a push) and no harder than the arm can (MODEL.md C.1).
    limited = "force_limit" in corrections
    if "finger_friction" in corrections:
        # C.2's pairs that can tip, as 1-D arrays: the least force per trial from those alone.
        shape, pair, force, passes = sliding_pairs(trials, edges, mass, gravity, config.finger_friction_scale, spin_stops)
        if limited:
            passes &= (force > 0.0) & (force <= max_force)
        return _least_passing(shape, pair[passes], force[passes])
    force, passes = _thesis_conditions(trials, edges, mass, gravity, spin_stops)  # (n, E) each
    if limited:
        passes &= (force > 0.0) & (force <= max_force)
    candidate = np.where(passes, force, np.inf)  # (n, E)
    # (10.6): the least-force passing edge; a row of all inf means no edge passes.
    edge = np.argmin(candidate, axis=1)  # (n,)
    return edge, candidate[np.arange(len(edge)), edge]


def _least_passing(shape: tuple[int, int], pair: np.ndarray, force: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(10.6) from the passing pairs alone: ``argmin(where(passes, force, inf), axis=1)`` and its value.

    shape : (n, E), the grid;  pair : (K,) int, passing places in the row-major grid, ascending
    force : (K,) float, N, theirs
    returns : edge (n,) int (argmin's: the first of the least, or the first NaN; 0 where none passes),
      required_force (n,) float, N (inf where none)
    """
    edge = np.zeros(shape[0], dtype=np.intp)
    required = np.full(shape[0], np.inf)
    if len(pair) == 0:
        return edge, required
    row, column = np.divmod(pair, shape[1])  # (K,) each, rows ascending, then columns
    start = np.flatnonzero(np.r_[True, row[1:] != row[:-1]])  # (G,): each passing row's first pair
    least = np.minimum.reduceat(force, start)  # (G,), NaN where the row has a NaN force
    # argmin's rule: the first column with the least force in each row, or with NaN if the row has one.
    at_least = np.flatnonzero((force == np.repeat(least, np.diff(np.r_[start, len(row)]))) | np.isnan(force))
    first = at_least[np.r_[True, row[at_least[1:]] != row[at_least[:-1]]]]  # (G,)
    edge[row[first]], required[row[first]] = column[first], force[first]
    return edge, required


def _check_corrections(
    trials: Trials, edges: EdgeGeometry, edge: np.ndarray, required: np.ndarray, mass: float, config: ToppleConfig,
    corrections: frozenset[str], spin_stops: bool,
) -> None:
    """Apply the corrections that follow the least-force edge (C.10, C.14, C.23, C.11, C.22, in this order)
    to a block of n trials, in place: ``required`` (n,) float, N, becomes inf where the topple does not
    happen, ``edge`` (n,) int and ``required`` take the carried or the stuck finger's edge and force where
    it tips a trial, and ``edge`` the line's edge where C.22 tips a hard press from above back.  A row with
    ``required`` inf carries an arbitrary edge (0), which the checks read harmlessly and
    ``trial_outcomes`` replaces by ``OUTCOME_NO_EDGE``."""
    gravity, max_force = config.gravity, config.max_finger_force
    if "stroke" in corrections:
        # C.10: the object tips over the least-force edge, and falls back unless the finger's
        # stroke carries it to that edge's apex.  Only the chosen edge is checked.
        short = ~(finger_travel(trials, edges, edge) <= config.stroke)  # (n,); NaN or inf: out of reach
        required[short] = np.inf
    if "tip_path" in corrections:
        # C.14: the balance that let the finger start the tip must hold on the way to the
        # apex too; where it fails the object stops, and does not tip over another edge instead
        # (the stuck finger below may still tip a stalled trial, as any trial nothing tips).
        rows = np.flatnonzero(np.isfinite(required))
        if len(rows):
            limit = max_force if "force_limit" in corrections else np.inf
            holds = holds_along_tip(trials.take(rows), edges, edge[rows], mass, gravity, config.finger_friction_scale,
                                    limit, spin_stops, config.tip_path_points)
            required[rows[~holds]] = np.inf
    if "carried_finger" in corrections:
        # C.23: where nothing above tips a push from above, the finger presses on to its force limit and gives
        # way sideways; a tip whose face slides only a short way along the fingertip before the apex carries
        # it along, pressing along the normal without friction.  Before C.11, whose finger holds while the
        # base slides.
        rows = np.flatnonzero(~np.isfinite(required) & trials.valid & (trials.push[:, 2] < FROM_ABOVE_U_Z))
        limit = max_force if "force_limit" in corrections else np.inf
        _tip_stopped(trials, edges, edge, required, rows,
                     lambda block: carried_finger(block, edges, mass, gravity, limit, config.carried_slide, spin_stops))
    if "stuck_finger" in corrections:
        # C.11: where nothing tips the object, a push down onto a part beyond a base edge may,
        # the finger holding on and the base sliding (a share of such trials, by the last draw).
        # Only the trials that stay, drew under the share and push down hard enough sideways to
        # drag the base are looked at (a few in ten of a pose's trials): the same result as all
        # of them, for less work.
        rows = np.flatnonzero(~np.isfinite(required) & (trials.stuck_draw < config.stuck_finger_share)
                              & drags_base(trials.push, trials.mu_table) & trials.valid)
        _tip_stopped(trials, edges, edge, required, rows, lambda block: stuck_finger(block, edges, mass, gravity, max_force))
    if "tip_back" in corrections:
        # C.22: a push from above that needs a hard press to tip the object presses the part beyond the base down
        # instead, and the object tips back over the edge the line from the centre of mass's foot through the
        # contact crosses.  After C.11, so the stuck finger's topples, most of the hard presses', are re-aimed too;
        # the force stays the trial's.
        rows = np.flatnonzero(np.isfinite(required) & (required > config.tip_back_force) & (trials.push[:, 2] < FROM_ABOVE_U_Z))
        if len(rows):
            back = line_edges(trials.contact.take(rows, axis=0), edges)  # (r,)
            crossed = back >= 0
            edge[rows[crossed]] = back[crossed]


def _tip_stopped(trials: Trials, edges: EdgeGeometry, edge: np.ndarray, required: np.ndarray, rows: np.ndarray,
                 tip: Callable[[Trials], tuple[np.ndarray, np.ndarray]]) -> None:
    """Where a correction that tips stopped trials (C.23, C.11) tips ``rows`` of the block, in place: ``tip`` maps
    a block of trials to (edge (r,) int, force (r,) float, N, inf where it does not tip them), evaluated in tiles
    of about ``TILE_ELEMENTS``; ``edge`` and ``required`` take its edge and force where the force is finite."""
    if not len(rows):
        return
    # A lone row would make the matrix products 1-row ones (a gemv, other last bits than the gemm of a block,
    # as in ``trial_outcomes``): evaluate it twice, keep the first.
    both = np.append(rows, rows) if len(rows) == 1 else rows
    block = trials.take(both)
    tipped_edge, tipped_force = np.empty(len(both), dtype=np.intp), np.empty(len(both))
    for tile in _row_tiles(len(both), len(edges.com_distance)):
        tipped_edge[tile], tipped_force[tile] = tip(block.take(tile))
    tipped_edge, tipped_force = tipped_edge[: len(rows)], tipped_force[: len(rows)]
    takes = np.isfinite(tipped_force)
    edge[rows[takes]], required[rows[takes]] = tipped_edge[takes], tipped_force[takes]


def carried_finger(
    trials: Trials, edges: EdgeGeometry, mass: float, gravity: float, max_force: float, slide_limit: float, spin_stops: bool
) -> tuple[np.ndarray, np.ndarray]:
    """The ``carried_finger`` correction (MODEL.md C.23): the edge a finger carried with the face tips.

    C.2's finger follows its path, so a tipping face slides along the fingertip at v_rel = v_e - s_e u
    per radian (``sliding_contact``) and the finger's friction opposes it.  Pressing from above onto an
    object nothing tips, a real finger, and the push player's, presses on to its force limit and gives
    way sideways (the caller picks those trials): where the face would slide at most ``slide_limit``
    before the apex, |v_rel| theta_e <= slide_limit (to first order in theta_e), the finger is carried
    with it and presses along the normal alone.  The trial tips over the edge of least force among those whose
    frictionless balance (C.2 with k = 0: table grip, weight, the moment about the vertical unless
    ``spin_stops`` is off) passes with 0 < |f| <= ``max_force`` and whose slide is that short.

    trials : r trials;  max_force : N (inf without ``force_limit``);  slide_limit : m
    returns : edge (r,) int (any index where none qualifies), force (r,) float, N (inf where none)
    """
    shape, pair, force, passes = sliding_pairs(trials, edges, mass, gravity, 0.0, spin_stops)
    # The slide only of the pairs whose frictionless balance passes within the limit (still ascending).
    within = passes & (force > 0.0) & (force <= max_force)
    pair, force = pair[within], force[within]  # (K,) each
    row, edge = np.divmod(pair, shape[1])  # (K,) each
    contact, normal, u = (a.take(row, axis=0) for a in (trials.contact, trials.normal, trials.push))  # (K, 3) each
    velocity = _cross_rows(edges.direction.take(edge, axis=0), contact - edges.start.take(edge, axis=0))  # (K, 3), v_e
    advance = np.einsum("kj,kj->k", velocity, normal) / np.einsum("kj,kj->k", u, normal)  # (K,), s_e (u . n < 0 on pairs)
    slide = np.linalg.norm(velocity - advance[:, None] * u, axis=1) * edges.apex_angle.take(edge)  # (K,), m
    short = slide <= slide_limit
    return _least_passing(shape, pair[short], force[short])


def line_edges(contact: np.ndarray, edges: EdgeGeometry) -> np.ndarray:
    """The base edge that the line from the centre of mass's foot through each contact's foot leaves the
    base by (``tip_back``, MODEL.md C.22): the edge line it meets first.

    The ray c + t (p - c) meets edge e's line at t = d_e / ((p - c) . o_e), and (p - c) . o_e = L_e + d_e
    with L_e = (p - y0) . o_e, so nothing but the edges' own quantities is needed.
    contact : (r, 3) float, m, pose frame;  returns : (r,) int, -1 where the foot is the centre of mass's
    """
    overhang = contact @ edges.outward.T - np.einsum("ek,ek->e", edges.start, edges.outward)  # (r, E), L_e
    towards = overhang + edges.com_distance  # (r, E), (p - c) . o_e
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = edges.com_distance / towards  # (r, E)
    reach = np.where((towards > 0.0) & (reach >= 0.0), reach, np.inf)
    return np.where(np.isfinite(reach).any(axis=1), np.argmin(reach, axis=1), -1)


def stuck_finger(
    trials: Trials, edges: EdgeGeometry, mass: float, gravity: float, max_force: float
) -> tuple[np.ndarray, np.ndarray]:
    """The ``stuck_finger`` correction (MODEL.md C.11): the edge a push down onto an overhang tips.

    A trial qualifies over base edge e when the push moves down (u_z < 0) yet can drag the
    base along the table (|u_xy| > mu_T |u_z|: a force along u pressing the object down
    overcomes the friction it adds), the contact lies beyond the edge's line (L_e =
    (p - y0) . o_e > 0, so tipping over e lowers it), the centre of mass is inside (d_e > 0),
    and the force along u whose moment about e matches gravity's, the thesis's (7.5)
    F*_e = m g d_e / (e . ((p - y0) x u)), is positive and at most ``max_force``.  The object
    tips over the qualifying edge with the least F*_e.

    returns : edge (n,) int (any index where none qualifies), force (n,) float, N (inf where none)
    """
    u, contact = trials.push, trials.contact  # (n, 3) each
    descends = drags_base(u, trials.mu_table) & trials.valid  # (n,)
    # L_e = p . o_e - y0 . o_e: (n, 3) @ (3, E) - (E,), no (n, E, 3) array.
    overhang = contact @ edges.outward.T - np.einsum("ek,ek->e", edges.start, edges.outward)  # (n, E), m
    rotates, force = _push_force(_cross_rows(contact, u), u, edges, mass, gravity)  # (n, E) each
    qualifies = descends[:, None] & (overhang > 0.0) & (edges.com_distance > 0.0) & rotates & (force <= max_force)
    candidate = np.where(qualifies, force, np.inf)  # (n, E)
    edge = np.argmin(candidate, axis=1)  # (n,)
    return edge, candidate[np.arange(len(edge)), edge]


def holds_along_tip(
    trials: Trials,
    edges: EdgeGeometry,
    edge: np.ndarray,
    mass: float,
    gravity: float,
    friction_scale: float,
    max_force: float,
    spin_stops: bool,
    points: int,
) -> np.ndarray:
    """The ``tip_path`` correction (MODEL.md C.14): whether C.2's balance holds on the way to the apex.

    The object turned by theta about its edge (through y0, unit e, MODEL.md C.10's convention)
    has its face in the plane n_t . (x - y0) = n . (p - y0), n_t = Rot(e, theta) n; the finger,
    advanced along u, meets it at q = p + s u with s = (n - n_t) . (p - y0) / (n_t . u), and the
    centre of mass is d_e sin(theta_e - theta) / sin(theta_e) inside the edge.  At
    theta = k theta_e / (points + 1), k = 1..points, the finger must still reach the face
    (n_t . u < 0) and ``sliding_contact`` must pass there with a force of at most ``max_force``.

    trials : r trials whose least-force edge passed at the start;  edge : (r,) int, that edge
    returns : (r,) bool
    """
    if points < 1:
        return np.ones(len(edge), dtype=bool)  # no point between: nothing to check
    u, normal, contact = trials.push, trials.normal, trials.contact  # (r, 3) each
    rows_of = lambda a: a.take(edge, axis=0)  # each row's edge's entry of an (E, ...) array
    e, y0, origin = rows_of(edges.direction), rows_of(edges.start), rows_of(edges.origin)  # (r, 3) each
    offset = contact - y0  # (r, 3), p - y0
    # Every k's points for all r trials at once, k-major: (points r, ...) rows, each the same
    # numbers as one k's pass (``_sliding_pairs`` is row-wise).
    stacked = lambda v: np.concatenate([v] * points)
    # theta and what depends on it alone are per (k, edge): (points, E) tables, read per row.
    apex = edges.apex_angle  # (E,), rad
    theta = [apex * (k / (points + 1)) for k in range(1, points + 1)]  # (E,) each, rad
    turned = np.concatenate([np.einsum("rij,rj->ri", rows_of(axis_angle_matrices(edges.direction, t)), normal)
                             for t in theta])  # (points r, 3), n_t
    # d_e sin(theta_e - theta) / sin(theta_e) of each row's edge, (points r, 1), m.  The table covers every
    # edge; an edge with d_e = 0 (apex 0) gives 0 / 0 there, but no row reads it (its edge passed, so d_e > 0).
    with np.errstate(invalid="ignore", divide="ignore"):
        inside = np.concatenate([rows_of(edges.com_distance * (np.sin(apex - t) / np.sin(apex))) for t in theta])[:, None]
    u, normal, contact, offset = stacked(u), stacked(normal), stacked(contact), stacked(offset)
    approach = np.einsum("ij,ij->i", turned, u)  # (points r,), n_t . u
    reaches = approach < 0.0
    gap = np.einsum("ij,ij->i", normal - turned, offset)  # (points r,), (n - n_t) . (p - y0)
    finger = contact + (gap / np.where(reaches, approach, -1.0))[:, None] * u  # (points r, 3), q
    at_point = Trials(finger, turned, u, stacked(trials.mu_table), stacked(trials.mu_finger), stacked(trials.valid),
                      stacked(trials.stuck_draw))
    column = lambda v: stacked(v)[:, None]  # (points r, 1)
    force, passes = _on_grid(*_sliding_pairs(at_point, column(e[:, 0]), column(e[:, 1]), column(y0[:, 0]), column(y0[:, 1]),
                                             inside, column(origin[:, 0]), column(origin[:, 1]),
                                             column(rows_of(edges.half_span)), mass, gravity, friction_scale,
                                             spin_stops))  # (points r, 1) each
    holds_at = reaches & passes[:, 0] & (force[:, 0] <= max_force)  # (points r,)
    return holds_at.reshape(points, len(edge)).all(axis=0)


def drags_base(push: np.ndarray, mu_table: np.ndarray) -> np.ndarray:
    """Whether a push moves down yet drags the base along the table (MODEL.md C.11): u_z < 0
    and |u_xy| > mu_T |u_z|, a force along u pressing the object down overcoming the friction
    it adds.

    push : (n, 3) float, unit;  mu_table : (n,) float
    returns : (n,) bool
    """
    return (push[:, 2] < 0.0) & (np.hypot(push[:, 0], push[:, 1]) > mu_table * -push[:, 2])


def finger_travel(trials: Trials, edges: EdgeGeometry, edge: np.ndarray) -> np.ndarray:
    """How far past the contact the finger must advance to tip the object to the apex of ``edge``.

    The model's finger is a point on the contacted face, taken as a plane (as in C.2).  The
    face turns with the object about the edge line (through y0) and keeps its offset from
    it, so at the apex it is the plane n_a . (x - y0) = n . (p - y0) with n_a = Rot_e n, and
    the finger p + s u meets it at

        s = (n . (p - y0) - n_a . (p - y0)) / (n_a . u)        (MODEL.md C.10)

    if n_a . u < 0; otherwise the face has turned away from the finger before the apex,
    which it cannot push there (inf).

    trials : r trials;  edge : (r,) int, an edge index per trial (any index where none passed)
    returns : (r,) float, m
    """
    p, n, u = trials.contact, trials.normal, trials.push  # (r, 3) each
    offset = p - edges.start.take(edge, axis=0)  # (r, 3), p - y0 of each row's edge
    apex_normal = np.einsum("rij,rj->ri", edges.tip_rotation.take(edge, axis=0), n)  # (r, 3), n_a
    approach = np.einsum("rk,rk->r", apex_normal, u)  # (r,), n_a . u
    gap = np.einsum("rk,rk->r", n - apex_normal, offset)  # (r,), (n - n_a) . (p - y0)
    toward = approach < 0.0
    return np.where(toward, gap / np.where(toward, approach, -1.0), np.inf)


def _thesis_conditions(
    trials: Trials, edges: EdgeGeometry, mass: float, gravity: float, spin_stops: bool
) -> tuple[np.ndarray, np.ndarray]:
    """Thesis 4.2.1-4.2.3 (MODEL.md section 7): F*_e (n, E) float, N, and pass_e (n, E) bool.

    trials : contact and normal finite (``trial_outcomes`` zeroes the misses' NaN)
    spin_stops : the slip check (7.9) counts the moment about the vertical: the variants that
      predict rotations, unless ``edge_spin`` (MODEL.md C.9)
    """
    n = trials.contact.shape[0]
    u, normal, contact = trials.push, trials.normal, trials.contact  # (n, 3) each
    mu_f = trials.mu_finger[:, None]  # (n, 1)

    # 1. Contact slip (7.1)-(7.2), at the start and with the normal rotated to each edge's apex.
    cos_start = -np.einsum("ij,ij->i", u, normal)[:, None]  # (n, 1), -u . n
    # (10.1): -u . (Rot_e n) = -<u n^T, Rot_e> (Frobenius), all E edges in one product.
    outer = (u[:, :, None] * normal[:, None, :]).reshape(n, 9)  # (n, 3, 1) * (n, 1, 3) -> (n, 9)
    cos_tip = -(outer @ edges.tip_rotation.reshape(-1, 9).T)  # (n, 9) @ (9, E) -> (n, E)
    in_cone = _inside_cone(cos_start, mu_f) & _inside_cone(cos_tip, mu_f)  # (n, 1) & (n, E) -> (n, E)

    # 2. Minimum push force (7.3)-(7.5).
    p_cross_u = _cross_rows(contact, u)  # (n, 3), batched cross product
    rotates, force = _push_force(p_cross_u, u, edges, mass, gravity)  # (n, E) each

    # 3. Workspace slip on the friction limit surface (7.6)-(7.9), divided through by F*^2 (10.4):
    #    tangential: F*|u_xy| <= mu_T F_n;  F_n = m g + F* max(0, -u_z)
    # In-place steps below are the same operations in the same order, minus the temporaries.
    # F* = 0 (the centre of mass over the edge) makes the limit inf, and inf times a table draw of
    # exactly 0 is NaN: such a trial fails below on mu_T > 0 alone, so neither warns.
    with np.errstate(divide="ignore", invalid="ignore"):
        limit = np.divide(mass * gravity, force)  # (n, E), m g / F*
        limit += np.maximum(0.0, -u[:, 2:3])  # (n, E), F_n / F*
        limit *= trials.mu_table[:, None]  # (n, 1) broadcast: mu_T F_n / F*
    np.square(limit, out=limit)  # (n, E)
    load = u[:, 0:1] ** 2 + u[:, 1:2] ** 2  # (n, 1), |u_xy|^2, compared broadcast against (n, E)
    if spin_stops:
        # tau_z per newton about the COM's projection on the edge (10.3): (p x u)_z - (O x u)_z,
        # with (O x u)_z = u . (-O_y, O_x, 0).
        origin_cross = np.column_stack([-edges.origin[:, 1], edges.origin[:, 0], np.zeros(len(edges.origin))])  # (E, 3)
        tau = p_cross_u[:, 2:3] - u @ origin_cross.T  # (n, 1) - (n, 3) @ (3, E) -> (n, E), m
        tau /= edges.half_span  # (n, E) / (E,)
        load = load + np.square(tau, out=tau)  # (n, 1) + (n, E) -> (n, E)
    # mu_T <= 0 (a draw of (8.1) below zero) holds nothing; exact, not a tolerance.
    holds = (load <= limit) & (trials.mu_table[:, None] > 0.0)  # (n, E)

    passes = in_cone & rotates & holds & trials.valid[:, None]  # (n, E), (7.10)
    return force, passes


def _push_force(
    p_cross_u: np.ndarray, u: np.ndarray, edges: EdgeGeometry, mass: float, gravity: float
) -> tuple[np.ndarray, np.ndarray]:
    """The thesis's (7.3)-(7.5): whether a push along u rotates the object outward about each
    edge, and the force along u whose moment about the edge matches gravity's.

    p_cross_u : (n, 3) float, p x u;  u : (n, 3) float, unit push
    returns : rotates (n, E) bool, (7.4); force (n, E) float, F*_e = m g d_e / tau_e, N (inf where it does not rotate)
    """
    torque = push_torques(p_cross_u, u, edges)  # (n, E), tau_e, m
    rotates = torque > MIN_PUSH_TORQUE  # (n, E), (7.4)
    gravity_torque = mass * gravity * edges.com_distance  # (E,), m g d_e, N m
    # The inner where puts a harmless divisor (1) where the push does not rotate; those
    # entries are replaced by inf anyway, this only keeps division warnings away.
    force = np.where(rotates, gravity_torque / np.where(rotates, torque, 1.0), np.inf)  # (n, E), F*_e, N
    return rotates, force


def sliding_contact(
    trials: Trials, edges: EdgeGeometry, mass: float, gravity: float, friction_scale: float = 1.0, spin_stops: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """The ``finger_friction`` correction (MODEL.md C.2): the finger's force while the object tips.

    Tipping about edge e at unit rate moves the contact point with v_e = e x (p - y0).  The
    finger, advancing along u, keeps touching the face only if the face recedes along the
    push (v_e . n < 0, so the finger advances s_e = v_e . n / u . n > 0 per radian); the face
    then slides along the fingertip with v_rel = v_e - s_e u, and Coulomb friction puts the
    finger's force on its cone's edge: f = F_n (-n + k mu_f t), t = -v_rel / |v_rel|
    (k = ``friction_scale``, 1 for Coulomb's law).  Its
    torque about the edge per newton of normal force is tau_e = f_hat . v_e (triple product),
    so F_n* = m g d_e / tau_e and the finger force is F_n* |f_hat|.  The table takes the
    weight minus the push's vertical part (m g - f_z, which must stay positive) and the
    limit-surface check (7.9) uses the whole force f with tau_z about O_e (without tau_z when
    not ``spin_stops``: the ``edge_spin`` correction, MODEL.md C.9).  Replaces
    conditions 1-3 of section 7; the thesis's friction-cone checks have no role once the
    sliding is modelled.

    returns : force (n, E) float, N (finger force magnitude); passes (n, E) bool
    """
    return _on_grid(*sliding_pairs(trials, edges, mass, gravity, friction_scale, spin_stops))


def sliding_pairs(
    trials: Trials, edges: EdgeGeometry, mass: float, gravity: float, friction_scale: float = 1.0, spin_stops: bool = True
) -> tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray]:
    """``sliding_contact`` on the pairs that can tip only (``_sliding_pairs``): shape (n, E), pair (K,) int
    places in the row-major grid, force (K,) float, N, passes (K,) bool; every other pair has force inf
    and does not pass."""
    e, y0 = edges.direction, edges.start  # (E, 3) each, horizontal and on the table (e_z = y0_z = 0, section 5)
    return _sliding_pairs(trials, e[:, 0], e[:, 1], y0[:, 0], y0[:, 1], edges.com_distance, edges.origin[:, 0],
                          edges.origin[:, 1], edges.half_span, mass, gravity, friction_scale, spin_stops)


def _on_grid(shape: tuple[int, int], pair: np.ndarray, force: np.ndarray, passes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``_sliding_pairs``' results on their (n, E) grid: force inf and passes False off the pairs."""
    force_grid, passes_grid = np.full(shape, np.inf), np.zeros(shape, dtype=bool)
    force_grid.ravel()[pair] = force  # ravel of a new array: a view
    passes_grid.ravel()[pair] = passes
    return force_grid, passes_grid


def _sliding_pairs(
    trials: Trials, ex, ey, y0x, y0y, com_distance, origin_x, origin_y, half_span,
    mass: float, gravity: float, friction_scale: float, spin_stops: bool,
) -> tuple[tuple[int, int], np.ndarray, np.ndarray, np.ndarray]:
    """``sliding_contact``'s balance with its edge quantities given as arrays that broadcast against
    the trials' (n, 1) columns: (E,) each for every edge of every trial, (n, 1) each for one edge
    per trial (``holds_along_tip``).  The same operations either way, so a trial's result does not
    depend on which.

    It runs on the (trial, edge) pairs whose face recedes from the finger, the only ones that can
    tip (about a quarter of them, ``follows``), as 1-D arrays; the others have force inf and do not
    pass, which is what the conditions give them.  Each pair's numbers are the same operations in
    the same order as on the whole grid, so the same bits.

    ex, ey : e's components;  y0x, y0y : y0's;  com_distance : d_e, m;  origin_x, origin_y : O_e's, m
    half_span : h_e, m
    returns : shape (n, E) or (n, 1);  pair (K,) int, the pairs' places in the row-major grid, ascending;
      force (K,) float, N;  passes (K,) bool
    """
    u, normal, contact = trials.push, trials.normal, trials.contact  # (n, 3) each, finite (``trial_outcomes``)
    col = lambda a, k: a[:, k : k + 1]  # noqa: E731, (n, 1) column k of an (n, 3) array
    # In-place steps (+=, out=) are the same operations in the same order as the formulas in
    # the comments, without the temporaries.
    # v_e = e x (p - y0) per component, with e_z = y0_z = 0: (n, 1) x (E,) outer products, no (n, E, 3) array.
    vx = col(contact, 2) * ey  # (n, E), e_y p_z
    vy = -col(contact, 2) * ex  # (n, E), -e_x p_z
    vz = col(contact, 1) * ex
    vz -= col(contact, 0) * ey
    vz -= ex * y0y - ey * y0x  # (n, E), (p_y e_x - p_x e_y) - (e x y0)_z
    face_speed = vx * col(normal, 0)
    face_speed += vy * col(normal, 1)
    face_speed += vz * col(normal, 2)  # (n, E), v_e . n
    approach = np.einsum("nk,nk->n", u, normal)  # (n,), u . n < 0: the finger moves into the face
    # The face recedes from the advancing finger (MIN_PUSH_TORQUE: v_e . n is also the
    # frictionless torque per newton, so the same cut as (7.4)).
    follows = (approach < 0.0)[:, None] & (face_speed < -MIN_PUSH_TORQUE)  # (n, E)
    pair = np.flatnonzero(follows)  # (K,): the pairs that follow, as places in the row-major (n, E) grid
    if len(pair) == 0:
        return follows.shape, pair, np.zeros(0), np.zeros(0, dtype=bool)
    # From here on 1-D arrays over the K pairs (``take`` of flat places, the cheapest gather): a trial's
    # value at the pair's row, an edge's at its edge ((n, 1) edge columns, one edge per trial, at its row).
    row, edge = np.divmod(pair, follows.shape[1])  # (K,) each
    at_row = lambda a, k: a[:, k].take(row)  # (K,) column k of an (n, 3) array
    at_edge = lambda v: v.take(edge) if np.ndim(v) == 1 else v[:, 0].take(row)  # of (E,) or (n, 1)
    vx, vy, vz = vx.take(pair), vy.take(pair), vz.take(pair)  # (K,) each, v_e
    advance = face_speed.take(pair) / approach.take(row)  # (K,), s_e = v_e . n / u . n > 0
    # v_rel = v_e - s_e u
    rx = vx - advance * at_row(u, 0)
    ry = np.multiply(advance, at_row(u, 1))
    np.subtract(vy, ry, out=ry)
    rz = np.multiply(advance, at_row(u, 2), out=advance)
    np.subtract(vz, rz, out=rz)  # (K,) each, v_rel
    slide = rx * rx
    slide += ry * ry
    slide += rz * rz
    np.sqrt(slide, out=slide)  # (K,), |v_rel|, m per rad
    # No sliding (v_e along u): the contact sticks and friction does no work; take t = 0.
    sliding = slide > MIN_PUSH_TORQUE
    mu = (friction_scale * trials.mu_finger).take(row)  # (K,), k mu_f
    friction = np.where(sliding, slide, 1.0)
    np.divide(mu, friction, out=friction)
    friction = np.where(sliding, friction, 0.0)
    np.negative(friction, out=friction)  # (K,): f_hat = -n + friction v_rel
    fx = np.multiply(friction, rx, out=rx)
    fx -= at_row(normal, 0)
    fy = np.multiply(friction, ry, out=ry)
    fy -= at_row(normal, 1)
    fz = np.multiply(friction, rz, out=rz)
    fz -= at_row(normal, 2)  # (K,) each, f_hat = friction v_rel - n
    torque = fx * vx
    torque += fy * vy
    torque += fz * vz  # (K,), tau_e = f_hat . v_e, m
    com = at_edge(com_distance)  # (K,), d_e, m
    rotates = (torque > MIN_PUSH_TORQUE) & (com > 0.0)  # (K,)
    weight = mass * gravity
    normal_force = np.where(rotates, weight * com / np.where(rotates, torque, 1.0), 0.0)  # (K,), F_n*
    fx *= normal_force
    fy *= normal_force
    fz *= normal_force  # (K,) each, f, N
    table = weight - fz  # (K,), the edge's normal force, N
    force_xy = fx * fx
    force_xy += fy * fy  # (K,), |f_xy|^2, shared by load and |f|
    if spin_stops:
        # ((p - O_e) x f)_z
        tau_z = (at_row(contact, 0) - at_edge(origin_x)) * fy
        tau_z -= (at_row(contact, 1) - at_edge(origin_y)) * fx  # (K,)
        tau_z /= at_edge(half_span)
        load = force_xy + np.square(tau_z, out=tau_z)  # (K,), |f_xy|^2 + (tau_z / h_e)^2, N^2
    else:
        load = force_xy.copy()  # (K,), |f_xy|^2, N^2: force_xy goes on to become |f|
    mu_t = trials.mu_table.take(row)  # (K,)
    holds = (table > 0.0) & (mu_t > 0.0) & (load <= (mu_t * table) ** 2)  # (K,), (7.9) with the whole f
    passes = rotates & holds & trials.valid.take(row)
    force_xy += fz * fz
    force = np.where(rotates, np.sqrt(force_xy, out=force_xy), np.inf)  # (K,), |f|, N
    return follows.shape, pair, force, passes


def _inside_cone(cos: np.ndarray, mu: np.ndarray) -> np.ndarray:
    """tan(angle) <= mu for a push making angle acos(cos) with the inward normal (7.1).

    cos : (n, 1) or (n, E) float;  mu : (n, 1) float;  returns : cos's shape, bool
    (10.5): sin <= mu cos, with cos > 0, is tan <= mu without acos or tan; the clip at 0
    only absorbs rounding of |cos| slightly above 1.  cos > 0 is exact: a push
    perpendicular to the normal is outside every cone (tan = inf).
    """
    sin = cos * cos
    np.subtract(1.0, sin, out=sin)
    np.maximum(0.0, sin, out=sin)
    np.sqrt(sin, out=sin)  # sqrt(max(0, 1 - cos^2)), in place
    return (cos > 0.0) & (sin <= mu * cos)


def _cross_rows(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a_i x b_i for (n, 3) rows: ``np.cross``'s products and differences, without its
    per-call reshaping (it is called once per tile).  returns : (n, 3) float"""
    out = np.empty(a.shape)
    np.multiply(a[:, 1], b[:, 2], out=out[:, 0])
    out[:, 0] -= a[:, 2] * b[:, 1]
    np.multiply(a[:, 2], b[:, 0], out=out[:, 1])
    out[:, 1] -= a[:, 0] * b[:, 2]
    np.multiply(a[:, 0], b[:, 1], out=out[:, 2])
    out[:, 2] -= a[:, 1] * b[:, 0]
    return out


def landed_poses(pose: StablePose, corrections: frozenset[str]) -> np.ndarray:
    """Pose reached by toppling over each base edge (E,) int: the thesis's ``edge_final_pose``;
    with the ``rolling`` correction (MODEL.md C.6) a blocked edge's ``edge_rolled_pose``; with
    ``momentum`` (C.8) an unblocked edge's ``edge_momentum_pose``.  Per-(pose, edge) tables,
    so the corrections cost no per-trial work."""
    landed = pose.edge_final_pose
    if "momentum" in corrections:
        landed = np.where(pose.edge_blocked, landed, pose.edge_momentum_pose)
    if "rolling" in corrections:
        landed = np.where(pose.edge_blocked, pose.edge_rolled_pose, landed)
    return landed


def pose_noise(rng: np.random.Generator, n_actions: int, n_candidates: int, config: ToppleConfig) -> TrialNoise:
    """Every trial's noise for a pose's A actions, as ``evaluate_pose`` draws it: the first
    ``n_candidates`` (the candidate set) first, then the probes', so a probe never changes a candidate's
    draws.  Drawn for all A actions, ok or not, before blocking: blocking never changes a draw.

    returns : (A, T) and (A, T, 3) fields"""
    noise = sample_noise(rng, n_candidates, config)
    if n_candidates < n_actions:
        probe_noise = sample_noise(rng, n_actions - n_candidates, config)
        noise = TrialNoise(*(np.concatenate([getattr(noise, f), getattr(probe_noise, f)])
                             for f in TrialNoise.__dataclass_fields__))
    return noise


def evaluate_pose(
    obj: ObjectModel,
    pose: StablePose,
    drop_probabilities: np.ndarray,
    actions: Actions,
    config: ToppleConfig,
    rng: np.random.Generator,
    candidates: int | None = None,
) -> ToppleTable:
    """Transition table of every action of one pose.

    obj : the object;  pose : one of its stable poses
    drop_probabilities : (P,) float, the drop probability of each pose of its pose set
      (``PoseSet.probabilities``): P is the width of the rows; the probabilities themselves are
      read only when ``config`` spreads landings (``landing_spread``, MODEL.md C.17) or carries
      marginal ones on (``landing_onward``, C.18)
    actions : candidate pushes of this pose;  rng : stream for this (object, pose)
    candidates : the first ``candidates`` actions are the pose's candidate set, the rest are
      probes (pushes someone asks about, such as logged ones).  Probes draw their noise after
      every candidate, so the candidates' rows are those of the candidate set alone, and with
      ``smoothing_radius`` a probe is smoothed over the candidates and itself, never over other
      probes (MODEL.md C.12).  Default: every action is a candidate.
    """
    spread, onward_share = config.applied_landing_spread, config.applied_landing_onward
    n_poses = len(drop_probabilities)  # P
    n_actions, trials = len(actions.status), config.trials  # A, T
    n_candidates = n_actions if candidates is None else int(candidates)
    noise = pose_noise(rng, n_actions, n_candidates, config)  # (A, T), (A, T, 3) fields
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]  # (3,), pose frame
    edges = edge_geometry(pose.base_edges, center_mass)  # (E, ...) fields
    final_pose = np.append(landed_poses(pose, config.applied_corrections), pose.index)  # (E + 1,); -1: stays
    # C.18: a blocked edge's onward pose is the start pose (its edge_final_pose), so it never carries.
    onward_pose = np.append(pose.edge_onward_pose, pose.index)  # (E + 1,)
    if np.ndim(drop_probabilities) != 1 or max(final_pose.max(), onward_pose.max()) >= n_poses:
        # A row's width is the pose set's size: another set's probabilities would spill a topple into the next row.
        raise ValueError(f"drop_probabilities must be the pose set's, one per pose: pose {pose.index} lands in poses up to "
                         f"{max(final_pose.max(), onward_pose.max())}, and {np.shape(drop_probabilities)} probabilities were given")

    outcomes = np.full((n_actions, trials), OUTCOME_NOT_EVALUATED, dtype=np.int16)  # (A, T)
    forces = np.full((n_actions, trials), np.inf)  # (A, T), N
    ok = np.flatnonzero(actions.status == STATUS_OK)  # (n_ok,) action indices
    # ceil(n_ok / chunk_actions) nearly equal blocks of a <= chunk_actions actions.
    for chunk in np.array_split(ok, max(1, int(np.ceil(len(ok) / config.chunk_actions)))):
        if len(chunk) == 0:
            continue
        chunk_noise = TrialNoise(*(getattr(noise, f).take(chunk, axis=0) for f in TrialNoise.__dataclass_fields__))  # (a, T, ...)
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
        edge, force = trial_outcomes(chunk_trials, edges, obj.mass, config)  # (n,)
        outcomes[chunk] = edge.reshape(len(chunk), trials)  # (n,) -> (a, T), undoing the action-major flattening
        forces[chunk] = force.reshape(len(chunk), trials)

    if "stability_margin" in config.applied_corrections:
        margin, falls_over = stability_margin(pose, obj.center_mass)
        if margin < config.min_stability_margin:
            # A marginal pose (MODEL.md C.3) falls over its nearest edge whatever the push,
            # with no force: every trial of every ok action has that outcome.
            outcomes[ok] = falls_over
            forces[ok] = 0.0

    # (9.1) via (10.7): pose landed in per (ok action, trial), counted per (action, pose) cell.
    next_pose = np.full((n_actions, n_poses), np.nan)  # (A, P)
    edge_of_trial = outcomes[ok].ravel()  # (n_ok T,) edge or -1; -1 reads the tables' last entry (stays)
    row_start = np.repeat(np.arange(len(ok)), trials) * n_poses  # (n_ok T,), each trial's row * P
    landed_cells = row_start + final_pose[edge_of_trial]  # (n_ok T,), row * P + pose landed in
    # MODEL.md C.18: a share of each landing in a marginal pose goes one fall further.  The stay
    # entry has share 0, so the start column keeps whole counts: P(topple) is unchanged.
    edge_share = onward_shares(final_pose, onward_pose, pose.index, drop_probabilities, onward_share,
                               config.landing_onward_below)  # (E + 1,); all 0 when nothing is carried on
    if onward_share:
        share = edge_share[edge_of_trial]  # (n_ok T,)
        cells = np.concatenate([landed_cells, row_start + onward_pose[edge_of_trial]])
        counts = np.bincount(cells, weights=np.concatenate([1.0 - share, share]), minlength=len(ok) * n_poses)
    else:
        counts = np.bincount(landed_cells, minlength=len(ok) * n_poses)  # (n_ok P,)
    next_pose[ok] = counts.reshape(len(ok), n_poses) / trials
    # The maps' neighbourhood means (C.13, C.15, C.19) are over the same neighbours, and the smoothing's
    # (C.12) over some of them: found once.
    maps = config.applied_feature_map or config.applied_down_map or config.applied_boosted_map
    near = neighbour_pairs(actions.points, actions.directions, pool=n_candidates) if maps else None
    if config.applied_smoothing > 0:
        # MODEL.md C.12: a push's row is its neighbourhood's mean row. Taking the best of ~1,000
        # candidates picks those whose count is most inflated; the mean over neighbours is not.
        limits = (config.applied_smoothing, config.smoothing_angle)
        shared = near.narrower(*limits) if near is not None and near.covers(*limits) else None  # else found here
        next_pose, _ = neighbour_mean(actions.points, actions.directions, next_pose, *limits, pool=n_candidates, near=shared)
    toppled = outcomes >= 0  # (A, T), toppled over some edge (blocked ones included, section 9)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_force = np.where(toppled, forces, 0.0).sum(axis=1) / toppled.sum(axis=1)  # (A,), (9.3), N
    mean_force[toppled.sum(axis=1) == 0] = np.nan
    # MODEL.md C.7: P(topple) through the fitted monotone map g, the row rescaled to stay a
    # distribution; no knots (every thesis variant) leave the table as counted.
    unmapped = next_pose  # the down map (C.15) reads P from the rows before C.7's map, as it was fitted
    next_pose, p_topple = recalibrate_rows(next_pose, pose.index, *config.applied_recalibration)  # (A, P), (A,), (9.2)
    if config.applied_feature_map:
        # MODEL.md C.13: P(topple) from the push's features, its landing kept (or borrowed).
        next_pose, p_topple = map_rows(next_pose, pose.index, actions.points, actions.directions, mean_force,
                                       obj.mass * config.gravity, config.applied_feature_map, pool=n_candidates, near=near)
    if config.applied_down_map:
        # MODEL.md C.15: pushes that press down, which the policies never choose, from their geometry.
        next_pose, p_topple = map_down_rows(next_pose, unmapped, pose.index, actions, edges, center_mass,
                                            config.applied_down_map, config.down_map_z, pool=n_candidates, near=near)
    if config.applied_side_map:
        # MODEL.md C.16: pushes from the side the model is unsure of, sharpened along the force they need.
        next_pose, p_topple = map_side_rows(next_pose, pose.index, actions, edges, config.applied_side_map,
                                            config.side_map_band)
    if config.applied_boosted_map:
        # MODEL.md C.19: P(topple) from boosted trees over what the model computes, last of the maps.
        features = boosted_features(p_topple, 1.0 - unmapped[:, pose.index], mean_force, actions, edges, center_mass,
                                    drop_probabilities, pose.index, obj, config.gravity, pool=n_candidates, near=near)
        next_pose, p_topple = map_boosted_rows(next_pose, features, pose.index, actions,
                                               load_trees(config.applied_boosted_map), pool=n_candidates, near=near)
    if spread:
        # MODEL.md C.17: the landing, never P(topple), shared with the most stable other poses.  Last,
        # though the maps keep a row's landing in proportion or borrow its neighbours' (both commute
        # with the spread, which is linear in the toppled mass).
        prior = landing_prior(drop_probabilities, pose.index, config.landing_spread_poses)
        next_pose = spread_landings(next_pose, pose.index, prior, spread)
    return ToppleTable(next_pose=next_pose, p_topple=p_topple, mean_force=mean_force, outcomes=outcomes,
                       edge_landed_pose=final_pose[:-1], edge_onward_share=edge_share[:-1],
                       # Where nothing goes on, the landing itself: C.18's onward pose of such an edge is no landing.
                       edge_onward_pose=np.where(edge_share[:-1] > 0, onward_pose[:-1], final_pose[:-1]))
