"""P(topple) from what the model knows of a push, not from its count alone (docs/MODEL.md C.13).

The recalibration of C.7 maps P(topple) through one monotone function, and every map of P
alone fails the same way: the model under-predicts the pushes the thesis's rule draws and
over-predicts the pushes a policy chooses at the same P (docs/VALIDATION.md, "Measured, then
built"), so lifting P for the first lifts the second.  Other things the model computes tell
the two apart: whether the push's neighbourhood agrees with it, how hard the push must be,
whether the finger pushes up or down.  The feature map is a logistic regression on them,

    q(u) = sigmoid(w . f(u)),   f(u) = (1, logit P, logit N, log F / mg, [no own topple], d_z)   (C.13.1)

with P the push's P(topple) as counted and smoothed (C.12), N the mean P over its neighbourhood
(``schema.neighbourhood``: contacts within 2 cm, directions within 0.5 rad), F its mean topple
force (9.3) over the object's weight mg (0 when no trial of its own toppled, which the
indicator marks), d_z the push direction's vertical component in the pose frame.  The row
keeps its shape: q goes to where the push lands (C.13.2, ``landing_rows``), 1 - q stays.

The weights are fitted by ``fit_weights`` (``toppledb recalibrate --features``) on observed
pushes: drawn ones and ones a policy chose, so the map learns what selection does.  numpy, and
``schema.neighbourhood``'s KD-tree (scipy) for a pose's neighbourhoods.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from schema.horizon import choosable_pushes
from schema.neighbourhood import MAX_ANGLE, RADIUS, Neighbours, neighbour_mean

from .recalibration import logistic_regression
from .recalibration import logit as clipped_logit

if TYPE_CHECKING:  # the service imports the config without the geometry (scipy)
    from .edges import EdgeGeometry

FEATURES = ("bias", "logit_p", "logit_neighbourhood", "log_force_ratio", "no_own_topple", "direction_z")
"""The entries of f(u) in (C.13.1), in the order of ``topple.feature_map``'s weights."""
LOGIT_FLOOR = 1e-3
"""P and N are clipped to [LOGIT_FLOOR, 1 - LOGIT_FLOOR] before the logit, which keeps it finite
at 0 and 1: a tenth of one trial in the default 100."""
FORCE_FLOOR = 1e-3
"""Smallest F / mg taken before the log: a marginal pose's trials topple with no force (C.3)."""
RIDGE = 1e-4
"""Weight of the L2 penalty on the non-bias weights, per unit of total repeat weight: keeps the
fit finite when a feature separates the pushes (all P = 0 pushes of a set never toppling)."""


class FeatureMapError(ValueError):
    """Weights that are no feature map; one line."""


def check_weights(weights, features: tuple[str, ...] = FEATURES, field: str = "feature_map") -> None:
    """Raise ``FeatureMapError`` unless ``weights`` is empty (no map) or one finite weight per
    entry of ``features`` (the map ``topple.<field>`` weighs)."""
    w = np.asarray(weights, dtype=float)
    if w.size == 0:
        return
    if w.shape != (len(features),) or not np.all(np.isfinite(w)):
        raise FeatureMapError(
            f"topple.{field} needs {len(features)} finite weights ({', '.join(features)}) or none, got {w.size}")


def logit(p: np.ndarray) -> np.ndarray:
    """``recalibration.logit`` at this map's floor."""
    return clipped_logit(p, LOGIT_FLOOR)


def push_features(
    p_topple: np.ndarray,
    neighbourhood: np.ndarray,
    mean_force: np.ndarray,
    weight: float,
    directions: np.ndarray,
) -> np.ndarray:
    """f(u) of (C.13.1) for every push.

    p_topple : (A,) float, P(topple) as counted and smoothed;  neighbourhood : (A,) float, N
    mean_force : (A,) float, N, NaN where no trial of the push's own toppled
    weight : float, N, the object's weight mg;  directions : (A, 3) float, unit, pose frame
    returns : (A, F) float, NaN rows where P is NaN (actions that are not ok)
    """
    p_topple = np.asarray(p_topple, dtype=float)
    mean_force = np.asarray(mean_force, dtype=float)
    none_own = ~np.isfinite(mean_force)
    ratio = np.where(none_own, 1.0, np.maximum(np.nan_to_num(mean_force) / weight, FORCE_FLOOR))
    features = np.column_stack([
        np.ones_like(p_topple),
        logit(p_topple),
        logit(neighbourhood),
        np.log(ratio),  # 0 where none toppled (ratio 1 there)
        none_own.astype(float),
        np.asarray(directions, dtype=float)[:, 2],
    ])  # (A, F)
    features[~np.isfinite(p_topple)] = np.nan
    return features


def pose_features(p_topple: np.ndarray, points: np.ndarray, directions: np.ndarray, mean_force: np.ndarray,
                  weight: float, pool: int | None = None, rows: np.ndarray | None = None,
                  near: Neighbours | None = None) -> np.ndarray:
    """f(u) of (C.13.1) for ``rows`` of one pose's pushes (default all), N taken over the pose's
    pool as ``map_rows`` takes it: what the map is fitted on (``Scorer.features``).

    p_topple : (A,) float;  points, directions : (A, 3) float, pose frame;  mean_force : (A,) float, N
    weight : float, N, mg;  pool, rows, near : as ``neighbour_mean``
    returns : (R, F) float
    """
    rows = np.arange(len(p_topple)) if rows is None else np.asarray(rows)
    neighbourhood, _ = neighbour_mean(points, directions, p_topple, RADIUS, MAX_ANGLE, rows=rows, pool=pool, near=near)
    return push_features(p_topple[rows], neighbourhood, mean_force[rows], weight, directions[rows])


def mapped_probability(features: np.ndarray, weights) -> np.ndarray:
    """q = sigmoid(w . f), (A,) float from features (A, F); NaN rows stay NaN."""
    return 1.0 / (1.0 + np.exp(-(np.asarray(features, dtype=float) @ np.asarray(weights, dtype=float))))


def landing_rows(next_pose: np.ndarray, start: int, points: np.ndarray, directions: np.ndarray,
                 pool: int | None = None, rows: np.ndarray | None = None, near: Neighbours | None = None) -> np.ndarray:
    """Where each push lands when it topples (C.13.2): a distribution over the poses other than
    ``start``, or zeros where the model knows of no landing.

    The push's own row when any of it leaves ``start``; else the mean of its neighbourhood's
    leaving parts (``schema.neighbourhood`` limits, over the first ``pool`` rows and itself);
    else the mean over the pose's pool.  Each normalised to sum to 1.

    next_pose : (A, P) float, rows sum to 1, NaN rows not ok;  start : the pose the rows leave
    points, directions : (A, 3) float, pose frame;  pool : the pose's candidates (default all)
    rows : (R,) int, the pushes to give a landing (default all);  near : as ``neighbour_mean``
    returns : (R, P) float, column ``start`` zero; rows sum to 1 or to 0
    """
    leaving = _leaving(next_pose, start)
    mean, _ = neighbour_mean(points, directions, leaving, RADIUS, MAX_ANGLE, rows=rows, pool=pool, near=near)
    return _landing(leaving, mean, pool, rows)


def _leaving(next_pose: np.ndarray, start: int) -> np.ndarray:
    """(A, P) float, the part of each row that leaves ``start`` (NaN rows stay NaN)."""
    leaving = np.array(next_pose, dtype=float)
    leaving[:, start] = np.where(np.isfinite(leaving).all(axis=1), 0.0, np.nan)
    return leaving


def toppled_rows(q: np.ndarray, landing: np.ndarray, start: int) -> np.ndarray:
    """(C.13.2): rows that stay in ``start`` with 1 - q and land as ``landing`` with q.
    q : (R,) float;  landing : (R, P) float, column ``start`` zero, rows sum to 1 (or 0 with q = 0)
    returns : (R, P) float"""
    rows = q[:, None] * landing
    rows[:, start] = 1.0 - q
    return rows


def _landing(leaving: np.ndarray, near: np.ndarray, pool: int | None, rows: np.ndarray | None = None) -> np.ndarray:
    """``landing_rows`` of ``rows`` (default all) from every push's leaving part (A, P) and the
    rows' neighbourhood means (R, P)."""
    ok = np.isfinite(leaving).all(axis=1)
    in_pool = ok.copy()
    if pool is not None:
        in_pool[pool:] = False
    whole = leaving[in_pool].mean(axis=0) if in_pool.any() else np.zeros(leaving.shape[1])  # (P,)
    own = leaving if rows is None else leaving[rows]  # (R, P)
    landing = np.zeros_like(own)
    for source in (np.broadcast_to(whole, own.shape), np.nan_to_num(near), np.nan_to_num(own)):
        mass = source.sum(axis=1)
        known = mass > 0
        landing[known] = source[known] / mass[known, None]  # later sources (more local) overwrite
    landing[~(ok if rows is None else ok[rows])] = np.nan
    return landing


def map_rows(
    next_pose: np.ndarray,
    start: int,
    points: np.ndarray,
    directions: np.ndarray,
    mean_force: np.ndarray,
    weight: float,
    weights,
    pool: int | None = None,
    near: Neighbours | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the feature map to one pose's rows, keeping them distributions.

    next_pose : (A, P) float, rows sum to 1, NaN rows not ok;  start : the pose the rows leave
    points, directions : (A, 3) float, pose frame;  mean_force : (A,) float, N (NaN: none toppled)
    weight : float, N, mg;  weights : (F,) or empty (the rows come back as they are)
    pool : the first ``pool`` rows are the pose's candidates, the rest probes (``neighbour_mean``)
    near : ``neighbour_pairs`` with ``pool`` when at hand (else found here)
    returns : next_pose (A, P) with row = (1 - q) at ``start`` + q landing; p_topple (A,) = q
      (0 where the model knows of no landing for the pose at all)
    """
    next_pose = np.array(next_pose, dtype=float)
    if len(weights) == 0:
        return next_pose, 1.0 - next_pose[:, start]
    p = 1.0 - next_pose[:, start]  # (A,)
    leaving = _leaving(next_pose, start)  # (A, P)
    # One neighbourhood pass for both N and the neighbours' landing: p and the leaving parts are
    # NaN on the same rows, so their means are over the same neighbours.
    mean, _ = neighbour_mean(points, directions, np.column_stack([p, leaving]), RADIUS, MAX_ANGLE, pool=pool, near=near)
    q = mapped_probability(push_features(p, mean[:, 0], mean_force, weight, directions), weights)  # (A,)
    landing = _landing(leaving, mean[:, 1:], pool)  # (A, P)
    ok = np.isfinite(p)
    q = np.where(landing.sum(axis=1) > 0, q, 0.0)
    next_pose[ok] = toppled_rows(q[ok], landing[ok], start)
    return next_pose, 1.0 - next_pose[:, start]


def fit_weights(features: np.ndarray, observed: np.ndarray, repeats: np.ndarray) -> np.ndarray:
    """Weights of (C.13.1) by maximum binomial likelihood, a small ridge on all but the bias.

    features : (n, F) float;  observed : (n,) float, topple frequency;  repeats : (n,) float > 0
    returns : (F,) float
    """
    x = np.asarray(features, dtype=float)
    target, w = np.asarray(observed, dtype=float), np.asarray(repeats, dtype=float)
    penalty = RIDGE * w.sum() * np.eye(x.shape[1])
    penalty[0, 0] = 0.0
    start = np.zeros(x.shape[1])
    start[0] = float(logit(np.average(target, weights=w)))
    return logistic_regression(x, target, w, start, penalty)


# --- The map for pushes the planner does not choose (docs/MODEL.md C.15) -------------------------
#
# Pushes that press down onto the object (u_z below ``topple.down_map_z``) tip by mechanics the
# model lacks: the base slides and turns while the object tips (docs/VALIDATION.md, "Where the
# default model is wrong"), so P ranks them poorly (on the corpus log AP 0.58 within them, 0.85
# within the other pushes).  Their geometry says more.  Until stop 45 the policies never chose them
# (``mdp.min_direction_z`` at the cut), so a map of them could not make a chosen push over-confident;
# since then value iteration chooses among them by its neighbourhood over the boosted map, which
# maps every push after this one (docs/MODEL.md C.15, (12.15)).

DOWN_FEATURES = ("bias", "logit_p", "direction_z", "overhang", "height", "normal_z", "stability", "offset")
"""The entries of the down map's features, in the order of ``topple.down_map``'s weights; every
length is over the centre of mass's height, so the features are dimensionless (C.15.1)."""
MIN_COM_HEIGHT = 1e-6
"""m, floor of the centre of mass's height the lengths are divided by: a resting object's centre
of mass is above the table, this only keeps a degenerate pose finite."""


def check_down_weights(weights) -> None:
    """``check_weights`` for the down map."""
    check_weights(weights, DOWN_FEATURES, "down_map")


def pressed_down(direction_z: np.ndarray, cut_z: float) -> np.ndarray:
    """(A,) bool, the pushes the down map takes: exactly those a policy may not choose with
    ``mdp.min_direction_z = cut_z`` (``schema.horizon.choosable_pushes``, compared in float32 as
    it is, so no push is on both sides of the cut).  direction_z : (A,) float, pose frame"""
    return ~choosable_pushes(direction_z, cut_z)


def down_features(
    p_topple: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    directions: np.ndarray,
    edges: EdgeGeometry,
    center_mass: np.ndarray,
) -> np.ndarray:
    """g(u) of (C.15.1) for every push of one pose.

    p_topple : (A,) float, P(topple) as counted and smoothed, NaN where not ok
    points : (A, 3) float, m, contacts;  normals : (A, 3) float, unit, outward face normals
    directions : (A, 3) float, unit pushes;  edges : the pose's base edges and their distances from
      ``center_mass`` (``edges.edge_geometry``);  center_mass : (3,) float, m;  all in the pose
      frame (table at z = 0)
    returns : (A, len(DOWN_FEATURES)) float, NaN rows where P is NaN
    """
    points = np.asarray(points, dtype=float)
    p_topple = np.asarray(p_topple, dtype=float)
    height = max(float(center_mass[2]), MIN_COM_HEIGHT)  # m
    # How far the contact lies beyond the base (> 0 outside it): the largest of its distances
    # outside the edge lines, d_e of MODEL.md section 5 for the contact with the sign turned.
    beyond = np.einsum("aek,ek->ae", points[:, None, :] - edges.start[None], edges.outward)  # (A, E), m
    offset = np.linalg.norm(points[:, :2] - np.asarray(center_mass)[:2], axis=1)  # (A,), m
    features = np.column_stack([
        np.ones(len(points)),
        logit(p_topple),
        np.asarray(directions, dtype=float)[:, 2],
        beyond.max(axis=1) / height,
        points[:, 2] / height,
        np.asarray(normals, dtype=float)[:, 2],
        np.full(len(points), edges.com_distance.min() / height),
        offset / height,
    ])  # (A, F)
    features[~np.isfinite(p_topple)] = np.nan
    return features


def map_down_rows(
    next_pose: np.ndarray,
    unmapped: np.ndarray,
    start: int,
    actions,
    edges: EdgeGeometry,
    center_mass: np.ndarray,
    weights,
    cut_z: float,
    pool: int | None = None,
    near: Neighbours | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the down map (C.15) to the rows of the pushes ``pressed_down`` below ``cut_z``; the
    rest are returned as they are.

    next_pose : (A, P) float, the rows as mapped so far (C.7), NaN rows not ok
    unmapped : (A, P) float, the same rows before any map: counted and smoothed (C.12), what the
      map's P and a push's landing are read from
    start : the pose the rows leave;  actions : the pose's ``outcomes.Actions`` (points, m;
      normals; directions; pose frame);  edges, center_mass : as ``down_features``
    weights : (len(DOWN_FEATURES),) or empty;  pool, near : as ``map_rows``
    returns : next_pose (A, P), a down push's row (1 - q) at ``start`` + q times its landing
      (C.13.2); p_topple (A,)
    """
    next_pose = np.array(next_pose, dtype=float)
    down = np.flatnonzero(pressed_down(actions.directions[:, 2], cut_z) & np.isfinite(unmapped[:, start]))  # (D,)
    if len(weights) == 0 or len(down) == 0:
        return next_pose, 1.0 - next_pose[:, start]
    # Features and landings of the down rows only: the others keep their rows.
    p = 1.0 - unmapped[down, start]  # (D,)
    features = down_features(p, actions.points[down], actions.normals[down], actions.directions[down], edges, center_mass)
    q = mapped_probability(features, weights)  # (D,)
    landing = landing_rows(unmapped, start, actions.points, actions.directions, pool=pool, rows=down, near=near)  # (D, P)
    q = np.where(landing.sum(axis=1) > 0, q, 0.0)  # nowhere the model knows to land: no topple
    next_pose[down] = toppled_rows(q, landing, start)
    return next_pose, 1.0 - next_pose[:, start]


# --- The map for pushes from the side (docs/MODEL.md C.16) ---------------------------------------
#
# Physics tips a push from the side by a nearly deterministic test on the noise-free geometry: the
# force it needs to turn the object about its easiest base edge, over its weight (on the corpus
# log, 50 % of side pushes topple near F*/mg = 0.3).  The model spreads that threshold over its
# broad noise, so its P moves too slowly with F*: where it is unsure it over-predicts hard pushes
# and under-predicts easy ones.  F* is not in P; the map adds it.

SIDE_FEATURES = ("bias", "logit_p", "log_force_ratio")
"""The entries of the side map's features, in the order of ``topple.side_map``'s weights (C.16.1)."""
SIDE_Z = 0.3
"""The side map takes pushes with -SIDE_Z <= u_z < SIDE_Z (pose frame): the report's "side" class."""
SIDE_BAND = (0.05, 0.95)
"""The default ``topple.side_map_band``: the map takes only pushes with SIDE_BAND[0] < P < SIDE_BAND[1]."""
FORCE_RATIO_RANGE = (1e-3, 1e3)
"""F*/mg is clipped to this before its log: a push with no lever about any edge needs an infinite force."""


def check_side_weights(weights) -> None:
    """``check_weights`` for the side map."""
    check_weights(weights, SIDE_FEATURES, "side_map")


def check_side_band(band) -> None:
    """A band (lo, hi) of P the side map takes, lo < P < hi: 0 <= lo < hi <= 1, so every row it
    takes has a leaving part to keep (P > lo >= 0)."""
    if len(band) != 2 or not 0.0 <= band[0] < band[1] <= 1.0:
        raise ValueError(f"topple.side_map_band must be two numbers 0 <= lo < hi <= 1, got {list(band)}")


def needed_force_ratio(points: np.ndarray, directions: np.ndarray, edges: EdgeGeometry) -> np.ndarray:
    """F*/mg: the least force, over the object's weight, with which each push turns the object
    about one of its base edges, friction and noise aside: min_e d_e / tau_e, tau_e = (p - y0_e) . (u x e)
    the push's lever about edge e (the moment balance of section 7 with the push alone against
    gravity).  inf where no edge has a positive lever.

    points : (A, 3) float, m;  directions : (A, 3) float, unit;  edges : ``edges.edge_geometry``
    (pose frame)  returns : (A,) float, >= 0 for a centre of mass inside its base (d_e > 0, section 5)
    """
    from .edges import push_torques  # here, not at the top: the service imports this module without the geometry

    points, directions = np.asarray(points, dtype=float), np.asarray(directions, dtype=float)
    lever = push_torques(np.cross(points, directions), directions, edges)  # (A, E), tau_e, m
    with np.errstate(divide="ignore"):
        ratio = np.where(lever > 0, edges.com_distance[None] / np.where(lever > 0, lever, 1.0), np.inf)  # (A, E)
    return ratio.min(axis=1, initial=np.inf)


def on_the_side(direction_z: np.ndarray) -> np.ndarray:
    """(A,) bool, the pushes of the side class, -SIDE_Z <= u_z < SIDE_Z, compared in float32 as
    the served directions (``schema.horizon.choosable_pushes``)."""
    z = np.asarray(direction_z, dtype=np.float32)
    return (z >= np.float32(-SIDE_Z)) & (z < np.float32(SIDE_Z))


def side_features(p_topple: np.ndarray, points: np.ndarray, directions: np.ndarray, edges: EdgeGeometry) -> np.ndarray:
    """g(u) of (C.16.1): (A, len(SIDE_FEATURES)) float, (1, logit P, log F*/mg); NaN rows where P is NaN.
    p_topple : (A,) float;  points, directions, edges : as ``needed_force_ratio``"""
    p_topple = np.asarray(p_topple, dtype=float)
    ratio = np.clip(needed_force_ratio(points, directions, edges), *FORCE_RATIO_RANGE)
    features = np.column_stack([np.ones(len(p_topple)), logit(p_topple), np.log(ratio)])
    features[~np.isfinite(p_topple)] = np.nan
    return features


def side_rows(p_topple: np.ndarray, direction_z: np.ndarray, band=SIDE_BAND) -> np.ndarray:
    """(A,) bool, the pushes the side map takes: side class, band[0] < P < band[1] (band[0] >= 0,
    ``check_side_band``, so every one has P > 0 and a landing)."""
    check_side_band(band)  # lo >= 0 keeps P = 0, a row with nothing leaving, out
    p_topple = np.asarray(p_topple, dtype=float)
    with np.errstate(invalid="ignore"):
        return on_the_side(direction_z) & (p_topple > band[0]) & (p_topple < band[1])


def map_side_rows(next_pose: np.ndarray, start: int, actions, edges: EdgeGeometry, weights,
                  band=SIDE_BAND) -> tuple[np.ndarray, np.ndarray]:
    """Apply the side map (C.16) to the rows ``side_rows`` takes; the rest are returned as they are.

    next_pose : (A, P) float, the rows as mapped so far (C.7), NaN rows not ok
    start : the pose the rows leave;  actions : the pose's ``outcomes.Actions`` (pose frame)
    edges : the pose's ``edges.edge_geometry``;  weights : (len(SIDE_FEATURES),) or empty
    band : (lo, hi), the P it takes (``topple.side_map_band``)
    returns : next_pose (A, P), a mapped row 1 - q at ``start`` and q times its own leaving part,
      normalised (C.13.2; P > 0, so it has one); p_topple (A,)
    """
    next_pose = np.array(next_pose, dtype=float)
    p = 1.0 - next_pose[:, start]
    side = np.flatnonzero(side_rows(p, actions.directions[:, 2], band))
    if len(weights) == 0 or len(side) == 0:
        return next_pose, p
    q = mapped_probability(side_features(p[side], actions.points[side], actions.directions[side], edges), weights)  # (S,)
    leaving = _leaving(next_pose[side], start)  # (S, P); P > 0, so every row leaves
    next_pose[side] = toppled_rows(q, leaving / leaving.sum(axis=1, keepdims=True), start)  # (C.13.2), its own landing
    return next_pose, 1.0 - next_pose[:, start]
