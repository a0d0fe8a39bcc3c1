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
pushes: drawn ones and ones a policy chose, so the map learns what selection does.  numpy only.
"""

from __future__ import annotations

import numpy as np

from schema.neighbourhood import MAX_ANGLE, RADIUS, neighbour_mean

from .recalibration import logistic_regression
from .recalibration import logit as clipped_logit

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


def check_weights(weights) -> None:
    """Raise ``FeatureMapError`` unless ``weights`` is empty (no map) or one finite weight per feature."""
    w = np.asarray(weights, dtype=float)
    if w.size == 0:
        return
    if w.shape != (len(FEATURES),) or not np.all(np.isfinite(w)):
        raise FeatureMapError(
            f"topple.feature_map needs {len(FEATURES)} finite weights ({', '.join(FEATURES)}) or none, got {w.size}")


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
                  weight: float, pool: int | None = None, rows: np.ndarray | None = None) -> np.ndarray:
    """f(u) of (C.13.1) for ``rows`` of one pose's pushes (default all), N taken over the pose's
    pool as ``map_rows`` takes it: what the map is fitted on (``Scorer.features``).

    p_topple : (A,) float;  points, directions : (A, 3) float, pose frame;  mean_force : (A,) float, N
    weight : float, N, mg;  pool, rows : as ``neighbour_mean``
    returns : (R, F) float
    """
    rows = np.arange(len(p_topple)) if rows is None else np.asarray(rows)
    neighbourhood, _ = neighbour_mean(points, directions, p_topple, RADIUS, MAX_ANGLE, rows=rows, pool=pool)
    return push_features(p_topple[rows], neighbourhood, mean_force[rows], weight, directions[rows])


def mapped_probability(features: np.ndarray, weights) -> np.ndarray:
    """q = sigmoid(w . f), (A,) float from features (A, F); NaN rows stay NaN."""
    return 1.0 / (1.0 + np.exp(-(np.asarray(features, dtype=float) @ np.asarray(weights, dtype=float))))


def landing_rows(next_pose: np.ndarray, start: int, points: np.ndarray, directions: np.ndarray,
                 pool: int | None = None) -> np.ndarray:
    """Where each push lands when it topples (C.13.2): a distribution over the poses other than
    ``start``, or zeros where the model knows of no landing.

    The push's own row when any of it leaves ``start``; else the mean of its neighbourhood's
    leaving parts (``schema.neighbourhood`` limits, over the first ``pool`` rows and itself);
    else the mean over the pose's pool.  Each normalised to sum to 1.

    next_pose : (A, P) float, rows sum to 1, NaN rows not ok;  start : the pose the rows leave
    points, directions : (A, 3) float, pose frame;  pool : the pose's candidates (default all)
    returns : (A, P) float, column ``start`` zero; rows sum to 1 or to 0
    """
    leaving = _leaving(next_pose, start)
    near, _ = neighbour_mean(points, directions, leaving, RADIUS, MAX_ANGLE, pool=pool)
    return _landing(leaving, near, pool)


def _leaving(next_pose: np.ndarray, start: int) -> np.ndarray:
    """(A, P) float, the part of each row that leaves ``start`` (NaN rows stay NaN)."""
    leaving = np.array(next_pose, dtype=float)
    leaving[:, start] = np.where(np.isfinite(leaving).all(axis=1), 0.0, np.nan)
    return leaving


def _landing(leaving: np.ndarray, near: np.ndarray, pool: int | None) -> np.ndarray:
    """``landing_rows`` from the leaving parts (A, P) and their neighbourhood means (A, P)."""
    ok = np.isfinite(leaving).all(axis=1)
    in_pool = ok.copy()
    if pool is not None:
        in_pool[pool:] = False
    whole = leaving[in_pool].mean(axis=0) if in_pool.any() else np.zeros(leaving.shape[1])  # (P,)
    landing = np.zeros_like(leaving)
    for source in (np.broadcast_to(whole, leaving.shape), np.nan_to_num(near), np.nan_to_num(leaving)):
        mass = source.sum(axis=1)
        known = mass > 0
        landing[known] = source[known] / mass[known, None]  # later sources (more local) overwrite
    landing[~ok] = np.nan
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
) -> tuple[np.ndarray, np.ndarray]:
    """Apply the feature map to one pose's rows, keeping them distributions.

    next_pose : (A, P) float, rows sum to 1, NaN rows not ok;  start : the pose the rows leave
    points, directions : (A, 3) float, pose frame;  mean_force : (A,) float, N (NaN: none toppled)
    weight : float, N, mg;  weights : (F,) or empty (the rows come back as they are)
    pool : the first ``pool`` rows are the pose's candidates, the rest probes (``neighbour_mean``)
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
    near, _ = neighbour_mean(points, directions, np.column_stack([p, leaving]), RADIUS, MAX_ANGLE, pool=pool)
    q = mapped_probability(push_features(p, near[:, 0], mean_force, weight, directions), weights)  # (A,)
    landing = _landing(leaving, near[:, 1:], pool)  # (A, P)
    ok = np.isfinite(p)
    q = np.where(landing.sum(axis=1) > 0, q, 0.0)
    next_pose[ok] = q[ok, None] * landing[ok]
    next_pose[ok, start] = 1.0 - q[ok]
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
