"""Probability recalibration of P(topple) (docs/MODEL.md C.7).

The Monte Carlo engine's P(topple) is over-confident where it matters: the pushes a
policy chooses, the best of ~1,000 candidates, are those where the model most over-
estimates toppling.  A monotone map g: [0, 1] -> [0, 1], fitted on observed pushes
(``pipeline.studies.recalibrate``), corrects the probability without changing the order
of the pushes (a strictly increasing g leaves AP unchanged).

g is stored as knots (``topple.recalibration_x``, ``topple.recalibration_y``) and read by
linear interpolation, clamped to the end knots.  It is applied to a transition table
(``recalibrate_rows``) so that P(topple) and the next-pose distribution stay consistent:

    P'(x | x, u)  = 1 - g(p)                          (x the start pose, p = 1 - P(x | x, u))
    P'(x' | x, u) = P(x' | x, u) g(p) / p             (x' != x, p > 0)

Rows with p = 0 are left as they are even when g(0) > 0: the engine saw no trial topple,
so there is no next pose to give the mass to.

Three fitters, all over pushes weighted by their repeats (observed frequency as target):
``fit_isotonic`` (pool adjacent violators), ``fit_centred`` (the same, strictly increasing
between block centres) and ``fit_logistic`` (g(p) = sigmoid(a logit(p)
+ b), two parameters, by Newton's method on the binomial likelihood).  numpy only.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

LOGIT_FLOOR = 1e-4
"""p is clipped to [LOGIT_FLOOR, 1 - LOGIT_FLOOR] before the logit: the engine's P(topple)
is a multiple of 1 / n_trials (0.01 by default), so this is below any nonzero value it gives
and keeps logit(1) finite (9.2)."""
LOGISTIC_GRID = 101
"""Knots that store a fitted logistic map: every multiple of 0.01, the engine's resolution
at the default 100 trials, so the stored map is exact there."""
NEWTON_STEPS = 100
NEWTON_TOLERANCE = 1e-10


class RecalibrationError(ValueError):
    """Knots that are no monotone map of [0, 1] into [0, 1]; one line."""


@dataclass(frozen=True)
class Knots:
    """A monotone piecewise-linear map: x (k,) strictly increasing, y (k,) non-decreasing, both in [0, 1]."""

    x: tuple[float, ...]
    y: tuple[float, ...]


def check_knots(x, y) -> None:
    """Raise ``RecalibrationError`` unless (x, y) are knots of a monotone map [0, 1] -> [0, 1].

    x, y : (k,) float.  Empty (k = 0) is the identity and is accepted.
    """
    x, y = np.asarray(x, dtype=float), np.asarray(y, dtype=float)
    if x.ndim != 1 or y.ndim != 1 or len(x) != len(y):
        raise RecalibrationError(f"topple.recalibration_x and _y need as many values each, got {x.size} x and {y.size} y")
    if len(x) == 0:
        return
    if len(x) < 2:
        raise RecalibrationError("topple.recalibration_x/_y need at least 2 knots (or none for the identity)")
    for name, v in (("x", x), ("y", y)):
        if not np.all(np.isfinite(v)) or v.min() < 0.0 or v.max() > 1.0:
            raise RecalibrationError(f"topple.recalibration_{name} must be in [0, 1], got {v.min():.6g} .. {v.max():.6g}")
    if np.any(np.diff(x) <= 0):
        raise RecalibrationError("topple.recalibration_x must be strictly increasing")
    if np.any(np.diff(y) < 0):
        raise RecalibrationError("topple.recalibration_y must be non-decreasing (the map must be monotone)")


def apply_map(p: np.ndarray, x, y) -> np.ndarray:
    """g(p) by linear interpolation between the knots, clamped to the end knots.

    p : (...) float in [0, 1], NaN passes through;  x, y : (k,) knots, k = 0: identity
    returns : p's shape
    """
    p = np.asarray(p, dtype=float)
    if len(x) == 0:
        return p.copy()
    return np.where(np.isnan(p), np.nan, np.interp(np.nan_to_num(p), x, y))


def recalibrate_rows(next_pose: np.ndarray, start: int, x, y) -> tuple[np.ndarray, np.ndarray]:
    """Apply g to the transition rows of one pose, keeping them distributions.

    next_pose : (A, P) float, rows sum to 1, NaN rows (actions that are not ``ok``) stay NaN
    start : the pose the rows leave from;  x, y : knots (empty: the input is returned unchanged)
    returns : next_pose (A, P), p_topple (A,) = 1 - next_pose[:, start]
    """
    p = 1.0 - np.asarray(next_pose, dtype=float)[:, start]  # (A,)
    if len(x) == 0:
        return np.array(next_pose, dtype=float), p
    return rows_toppling(next_pose, start, apply_map(p, x, y))


def rows_toppling(next_pose: np.ndarray, start: int, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Transition rows whose P(topple) is moved to ``g``, keeping where they land: each row that leaves
    ``start`` has its leaving part scaled to g; a row that never leaves (no landing to scale), or a NaN row,
    stays as it is.

    next_pose : (A, P) float, rows sum to 1;  g : (A,) float, the new P(topple)
    returns : next_pose (A, P), a copy;  p_topple (A,) = 1 - next_pose[:, start]
    """
    next_pose = np.array(next_pose, dtype=float)
    p = 1.0 - next_pose[:, start]  # (A,)
    moves = p > 0  # (A,), False for NaN rows and rows that never topple
    scale = np.where(moves, g / np.where(moves, p, 1.0), 1.0)  # (A,)
    others = np.ones(next_pose.shape[1], dtype=bool)
    others[start] = False
    rows = np.flatnonzero(moves)
    next_pose[np.ix_(rows, np.flatnonzero(others))] *= scale[rows, None]
    next_pose[rows, start] = 1.0 - g[rows]
    return next_pose, 1.0 - next_pose[:, start]


# ---------------------------------------------------------------- fitting


def pool_adjacent_violators(y: np.ndarray, w: np.ndarray, strict: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Weighted isotonic (non-decreasing) least squares fit of ``y`` in the given order.

    y : (n,) float, targets sorted by their x;  w : (n,) float > 0, weights
    strict : pool equal neighbouring blocks too, so the block values strictly increase
    returns : fitted (n,) float, non-decreasing; block (n,) int, the pooled block of each point
    """
    means: list[float] = []
    weights: list[float] = []
    sizes: list[int] = []
    for value, weight in zip(np.asarray(y, dtype=float), np.asarray(w, dtype=float)):
        means.append(value)
        weights.append(weight)
        sizes.append(1)
        # Merge backwards while the last two blocks violate the order.
        while len(means) > 1 and (means[-2] > means[-1] or (strict and means[-2] == means[-1])):
            total = weights[-2] + weights[-1]
            means[-2] = (means[-2] * weights[-2] + means[-1] * weights[-1]) / total
            weights[-2] = total
            sizes[-2] += sizes[-1]
            del means[-1], weights[-1], sizes[-1]
    block = np.repeat(np.arange(len(sizes)), sizes)
    return np.asarray(means)[block], block


def pooled_by_p(p: np.ndarray, observed: np.ndarray, weight: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One point per distinct p: its total weight and weighted mean observed frequency.

    p, observed, weight : (n,) float
    returns : xs (m,) distinct p, sorted;  w (m,) summed weights;  y (m,) mean observed
    """
    p, observed, weight = (np.asarray(a, dtype=float) for a in (p, observed, weight))
    xs, inverse = np.unique(p, return_inverse=True)
    w = np.bincount(inverse, weights=weight)
    return xs, w, np.bincount(inverse, weights=weight * observed) / w


def fit_isotonic(p: np.ndarray, observed: np.ndarray, weight: np.ndarray) -> Knots:
    """Isotonic regression of observed frequency on predicted P(topple), as knots.

    p : (n,) float, predicted;  observed : (n,) float, observed topple frequency;  weight : (n,) repeats
    Points with equal p are pooled first (one value per distinct p).  Each fitted block
    gives knots at its smallest and largest p (a flat step), and the map is anchored at
    (0, 0) and extended flat to x = 1.
    """
    xs, w, y = pooled_by_p(p, observed, weight)
    fitted, block = pool_adjacent_violators(y, w)
    kx, ky = [], []
    for b in range(block[-1] + 1):
        members = np.flatnonzero(block == b)
        for i in (members[0], members[-1]) if len(members) > 1 else (members[0],):
            kx.append(xs[i])
            ky.append(fitted[i])
    return anchored(kx, ky)


def fit_centred(p: np.ndarray, observed: np.ndarray, weight: np.ndarray) -> Knots:
    """Centred isotonic regression (Oron and Flournoy 2017) of observed frequency on P(topple).

    p, observed, weight : (n,) float as ``fit_isotonic``
    The isotonic blocks, with equal neighbours pooled too, each give one knot: their
    weight-averaged p and their observed frequency.  The map is linear between knots, constant
    from the smallest fitted p to the first centre and from the last centre to the largest (as
    the authors' ``cirPAVA``), anchored at (0, 0) and flat to x = 1, so it strictly increases
    from the first block's centre to the last's: it keeps the model's order of those pushes,
    where isotonic's flat steps tie them.  Unlike the paper, equality of blocks is exact (no
    rounding), and blocks at p = 0 or 1 pool like any other.
    """
    xs, w, y = pooled_by_p(p, observed, weight)
    fitted, block = pool_adjacent_violators(y, w, strict=True)
    first = np.flatnonzero(np.diff(block, prepend=-1))  # (blocks,) index of each block's first point
    last = np.append(first[1:] - 1, len(xs) - 1)  # (blocks,) and of its last
    centres = np.bincount(block, weights=w * xs) / np.bincount(block, weights=w)  # (blocks,)
    # (w x) / w can miss x in the last bit: clipping to the block's own p keeps centres increasing.
    centres = np.clip(centres, xs[first], xs[last])
    kx, ky = list(centres), list(fitted[first])
    if xs[0] < kx[0]:
        kx, ky = [xs[0], *kx], [ky[0], *ky]
    if xs[-1] > kx[-1]:
        kx, ky = [*kx, xs[-1]], [*ky, ky[-1]]
    return anchored(kx, ky)


def anchored(kx: list[float], ky: list[float]) -> Knots:
    """Knots (kx, ky) of a fitted map, anchored at (0, 0) and extended flat to x = 1."""
    if kx[0] > 0.0:
        kx, ky = [0.0, *kx], [0.0, *ky]
    if kx[-1] < 1.0:
        kx, ky = [*kx, 1.0], [*ky, ky[-1]]
    return Knots(tuple(map(float, kx)), tuple(map(float, ky)))


def logit(p: np.ndarray, floor: float = LOGIT_FLOOR) -> np.ndarray:
    """log(p / (1 - p)) with p clipped to [floor, 1 - floor], so 0 and 1 stay finite."""
    p = np.clip(np.asarray(p, dtype=float), floor, 1.0 - floor)
    return np.log(p) - np.log1p(-p)


def logistic_regression(design: np.ndarray, target: np.ndarray, weight: np.ndarray, start: np.ndarray,
                        penalty: np.ndarray | None = None) -> np.ndarray:
    """Maximum binomial likelihood of sigmoid(design @ theta) by Newton's method.

    design : (n, k) float;  target : (n,) float, observed frequency;  weight : (n,) repeats
    start : (k,) float, the first theta;  penalty : (k, k) float, an L2 penalty theta' R theta / 2
    on the likelihood (default none)
    returns : theta (k,) float
    """
    design, target, weight = (np.asarray(a, dtype=float) for a in (design, target, weight))
    penalty = np.zeros((design.shape[1], design.shape[1])) if penalty is None else penalty
    theta = np.array(start, dtype=float)
    for _ in range(NEWTON_STEPS):
        q = 1.0 / (1.0 + np.exp(-(design @ theta)))  # (n,)
        gradient = design.T @ (weight * (target - q)) - penalty @ theta  # (k,)
        hessian = (design * (weight * q * (1 - q))[:, None]).T @ design + penalty + 1e-9 * np.eye(len(theta))  # (k, k)
        step = np.linalg.solve(hessian, gradient)
        theta = theta + step
        if np.max(np.abs(step)) < NEWTON_TOLERANCE:
            break
    return theta


def fit_logistic(p: np.ndarray, observed: np.ndarray, weight: np.ndarray) -> tuple[float, float]:
    """Platt-style calibration g(p) = sigmoid(a logit(p) + b) by maximum binomial likelihood.

    p, observed, weight : (n,) float as ``fit_isotonic``; observed x weight toppled of weight repeats
    returns : (a, b); a < 0 (an anti-monotone fit) is clipped to 0 (a constant map)
    """
    z = logit(p)
    theta = logistic_regression(np.column_stack([z, np.ones_like(z)]), observed, weight, start=np.array([1.0, 0.0]))
    a, b = float(theta[0]), float(theta[1])
    if a < 0:
        a, b = 0.0, float(logit(np.average(observed, weights=weight)))
    return a, b


def logistic_knots(a: float, b: float, grid: int = LOGISTIC_GRID) -> Knots:
    """The logistic map sampled on ``grid`` evenly spaced p in [0, 1], anchored at (0, 0)."""
    x = np.linspace(0.0, 1.0, grid)
    y = 1.0 / (1.0 + np.exp(-(a * logit(x) + b)))
    y[0] = 0.0  # p = 0 is never moved (module docstring); the anchor keeps the knots honest about it
    return Knots(tuple(map(float, x)), tuple(map(float, np.maximum.accumulate(y))))


METHODS = ("isotonic", "logistic", "centred")


def fit(method: str, p: np.ndarray, observed: np.ndarray, weight: np.ndarray) -> Knots:
    """Knots of ``method`` (``METHODS``) fitted on pushes with p > 0 (the others are never moved)."""
    p, observed, weight = (np.asarray(a, dtype=float) for a in (p, observed, weight))
    use = p > 0
    if not use.any():
        raise RecalibrationError("no push with a predicted P(topple) > 0 to fit a recalibration on")
    if method == "isotonic":
        return fit_isotonic(p[use], observed[use], weight[use])
    if method == "logistic":
        return logistic_knots(*fit_logistic(p[use], observed[use], weight[use]))
    if method == "centred":
        return fit_centred(p[use], observed[use], weight[use])
    raise RecalibrationError(f"unknown recalibration method {method!r}; choose one of {', '.join(METHODS)}")


def predict(p: np.ndarray, knots: Knots) -> np.ndarray:
    """Recalibrated P(topple) of pushes as the engine gives it: g(p) for p > 0, 0 for p = 0.

    p : (n,) float;  returns : (n,) float
    """
    p = np.asarray(p, dtype=float)
    return np.where(p > 0, apply_map(p, knots.x, knots.y), p)
