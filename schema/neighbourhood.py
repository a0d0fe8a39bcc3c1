"""The neighbourhood of a candidate push: how much its P(topple) can be trusted.

A policy that takes the best of ~1,000 candidate pushes picks, among candidates with equal
estimates, the ones whose estimate is most wrong (docs/VALIDATION.md, "Robust push
choice"): value iteration's chosen pushes are predicted to topple 0.50 of the time and
topple 0.35 in pybullet.  The mean P(topple) of the candidates around a push (contacts
within ``RADIUS``, directions within ``MAX_ANGLE``, itself included) is an estimate that
selection has not inflated: for those same pushes it is 0.38 on corpus objects and 0.38
against 0.35 physical on held-out objects.  The service reports it beside every chosen
push (``p_topple_neighbourhood``); the robust-choice study ranks by it.

numpy, and scipy's KD-tree where every candidate's neighbourhood is searched at once (the pipeline's
path; without scipy, as in the service's install, the same pairs are found by brute force): the
service and the pipeline's studies share it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .vocabulary import NO_OP

RADIUS = 0.02
"""m, largest distance between two neighbours' contact points (chosen on corpus objects only)."""
MAX_ANGLE = 0.5
"""rad, largest angle between two neighbours' push directions (chosen with RADIUS)."""
TOLERANCE = 1e-9
"""Slack on the distance (m) and cosine limits, so that rounding does not split a boundary case."""
BRUTE_FORCE_ROWS = 32
"""Up to this many rows a mean searches their neighbourhoods by brute force (R x A pairs); more rows go
through ``neighbour_pairs``' KD-tree.  Both decide every pair alike: this sets the speed only."""


def neighbour_mean(
    points: np.ndarray,
    directions: np.ndarray,
    values: np.ndarray,
    radius: float = RADIUS,
    max_angle: float = MAX_ANGLE,
    rows: np.ndarray | None = None,
    pool: int | None = None,
    near: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``values`` over each candidate's neighbours with a finite value (itself included).

    points : (A, 3) float, m, one pose's candidate contacts;  directions : (A, 3) float, unit
    values : (A,) or (A, k) float, NaN for candidates that are not ok (they are nobody's
      neighbour; a row is finite only when all its k values are)
    rows : indices of the candidates to average for (default: all), (R,) int
    pool : only the first ``pool`` candidates are anyone's neighbours (default: all A); a row
      past them (a push that is not one of the pose's candidates, such as a logged push) is
      averaged over the pool and itself, and counts in no other row's mean
    near : ``Neighbours`` of these candidates with these limits and ``pool``, when the caller has them
      already (one pose's maps take several means over the same neighbourhoods); ``rows`` then distinct
    returns : mean (R,) or (R, k) float, NaN where the candidate itself is NaN;
      count (R,) int, its finite neighbours (0 where it is NaN)
    """
    points, directions, values = (np.asarray(a, dtype=float) for a in (points, directions, values))
    flat = values.ndim == 1
    values = values[:, None] if flat else values
    rows = np.arange(len(points)) if rows is None else np.asarray(rows, dtype=np.int64)
    finite = np.isfinite(values).all(axis=1)
    # A few rows (or repeated ones, which shared pairs cannot number) by brute force, more through the KD-tree.
    few = len(rows) <= BRUTE_FORCE_ROWS or len(np.unique(rows)) < len(rows)
    if near is None and few:
        found = _near(points, directions, rows, radius, max_angle, pool) & finite[None, :] & finite[rows, None]
        row, neighbour = np.nonzero(found)  # row-major: each row's neighbours in index order
    else:
        near = neighbour_pairs(points, directions, radius, max_angle, pool) if near is None else near
        row, neighbour = near.pairs_of(rows, finite)
    count = np.bincount(row, minlength=len(rows))
    # Summed one neighbour after another, in index order: a BLAS product's order follows its thread
    # count, and a mean one rounding off crosses a threshold of the boosted map (C.19) now and then.
    total = np.column_stack([np.bincount(row, weights=values[neighbour, j], minlength=len(rows))
                             for j in range(values.shape[1])])  # (R, k)
    mean = np.where((count > 0)[:, None], total / np.maximum(count, 1)[:, None], np.nan)
    return (mean[:, 0] if flat else mean), count


@dataclass(frozen=True)
class Neighbours:
    """Every candidate's neighbourhood as index pairs, found once for the several means of one pose.

    row, neighbour : (M,) int, candidate ``neighbour`` is in candidate ``row``'s neighbourhood (itself
      included), sorted by row and then by neighbour: the order a mean adds them in
    distance2 : (M,) float, m^2, the squared distance between their contacts as the limit read it;
      cosine : (M,) float, between their directions;  size : int, A, the candidates
    radius, max_angle : the limits they were found with (m, rad)
    """

    row: np.ndarray
    neighbour: np.ndarray
    distance2: np.ndarray
    cosine: np.ndarray
    size: int
    radius: float
    max_angle: float

    def pairs_of(self, rows: np.ndarray, finite: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The pairs of ``rows`` between finite candidates, each row numbered by its place in ``rows``.

        rows : (R,) int, distinct;  finite : (A,) bool
        returns : row (m,) int in [0, R), neighbour (m,) int, each row's neighbours in index order
        """
        place = np.full(self.size, -1)
        place[rows] = np.arange(len(rows))
        if np.count_nonzero(place >= 0) != len(rows):
            raise ValueError("rows must be distinct to be averaged over shared Neighbours")
        row = place[self.row]  # (M,)
        keep = (row >= 0) & finite[self.row] & finite[self.neighbour]
        # Kept in the pairs' order, so each row's neighbours stay in index order whatever the order of
        # ``rows``: the order a mean adds them in.
        return row[keep], self.neighbour[keep]

    def covers(self, radius: float, max_angle: float) -> bool:
        """Whether limits ``radius`` (m) and ``max_angle`` (rad) lie within these, so ``narrower`` can take them."""
        return radius <= self.radius and max_angle <= self.max_angle

    def narrower(self, radius: float, max_angle: float) -> Neighbours:
        """The neighbourhoods of limits within these (``covers``), with the same pool: what
        ``neighbour_pairs`` finds with them, without a second search."""
        if not self.covers(radius, max_angle):
            raise ValueError(f"({radius}, {max_angle}) is not within ({self.radius}, {self.max_angle})")
        keep = _limits_hold(self.distance2, self.cosine, radius, max_angle) | (self.row == self.neighbour)
        return Neighbours(self.row[keep], self.neighbour[keep], self.distance2[keep], self.cosine[keep], self.size,
                          radius, max_angle)


def neighbour_pairs(points: np.ndarray, directions: np.ndarray, radius: float = RADIUS, max_angle: float = MAX_ANGLE,
                    pool: int | None = None) -> Neighbours:
    """Which candidates are in each candidate's neighbourhood (``neighbour_mean``'s limits and
    ``pool``), whatever their values: what ``neighbour_mean`` takes as ``near``.

    points : (A, 3) float, m;  directions : (A, 3) float, unit
    returns : ``Neighbours``, found by the same arithmetic as a mean that finds its own, so every mean
      over them is that mean to the bit
    """
    points, directions = np.asarray(points, dtype=float), np.asarray(directions, dtype=float)
    size = len(points)
    row, neighbour = _pairs_within(points, radius)  # every pair as near in contact as the limit, or nearer
    distance2, cosine = _pair_geometry(points, directions, row, neighbour)
    keep = np.flatnonzero(_kept(row, neighbour, distance2, cosine, radius, max_angle, pool))
    # In row-major order: each row's neighbours in index order, the order a mean adds them in.
    order = keep[np.argsort(row.take(keep) * size + neighbour.take(keep))]
    return Neighbours(row.take(order), neighbour.take(order), distance2.take(order), cosine.take(order), size, radius,
                      max_angle)


def _pairs_within(points: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """Every ordered pair of candidates whose contacts may lie within ``radius`` of each other, each
    candidate with itself included: a superset that ``_limits_hold`` decides.

    points : (A, 3) float, m;  returns : row, neighbour (M,) int, in no particular order
    """
    size = len(points)
    finite = np.flatnonzero(np.isfinite(points).all(axis=1))  # a NaN contact is only its own neighbour
    try:
        from scipy.spatial import cKDTree
    except ImportError:  # an install without scipy (the service's): every pair, ~60 ms for 1,000 candidates
        row, neighbour = np.divmod(np.arange(len(finite) ** 2), max(len(finite), 1))
        row, neighbour = finite.take(row), finite.take(neighbour)
        apart = row != neighbour
    else:
        # The tree measures distance in its own arithmetic; a search a hair wider than the limit finds
        # every pair that ``_pair_geometry``'s arithmetic puts within it.
        limit = (radius + TOLERANCE) * (1.0 + 1e-9) + 1e-12
        found = cKDTree(points.take(finite, axis=0)).query_pairs(limit, output_type="ndarray")  # (m, 2), i < j
        row, neighbour = finite.take(found[:, 0]), finite.take(found[:, 1])
        row, neighbour = np.concatenate([row, neighbour]), np.concatenate([neighbour, row])
        apart = slice(None)
    itself = np.arange(size)
    return np.concatenate([row[apart], itself]), np.concatenate([neighbour[apart], itself])


def _pair_geometry(points: np.ndarray, directions: np.ndarray, row: np.ndarray,
                   neighbour: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared distance (m^2) between each pair's contacts and the cosine between their directions, (M,) float each.

    Written out coordinate by coordinate, in the same order whichever search asks: a pair gets the same
    bits from the KD-tree's path and from ``_near``'s, and the same both ways round.
    """
    gap = points.take(row, axis=0) - points.take(neighbour, axis=0)  # (M, 3)
    a, b = directions.take(row, axis=0), directions.take(neighbour, axis=0)
    return (gap[:, 0] * gap[:, 0] + gap[:, 1] * gap[:, 1] + gap[:, 2] * gap[:, 2],
            a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2])


def neighbours(
    points: np.ndarray,
    directions: np.ndarray,
    action: int,
    radius: float = RADIUS,
    max_angle: float = MAX_ANGLE,
) -> np.ndarray:
    """The candidates in one candidate's neighbourhood (``neighbour_mean``'s limits), itself included.

    points : (A, 3) float, m;  directions : (A, 3) float, unit;  action : index of the candidate
    returns : (A,) bool
    """
    points, directions = np.asarray(points, dtype=float), np.asarray(directions, dtype=float)
    return _near(points, directions, np.array([action]), radius, max_angle)[0]


def _near(points: np.ndarray, directions: np.ndarray, rows: np.ndarray, radius: float, max_angle: float,
          pool: int | None = None) -> np.ndarray:
    """Which candidates are in each of ``rows``' neighbourhoods, whatever their values, by brute force
    (for a few rows: every row is ``neighbour_pairs``').

    points, directions : (A, 3) float;  rows : (R,) int
    pool : only the first ``pool`` candidates are others' neighbours (``neighbour_mean``)
    returns : (R, A) bool, a candidate is its own neighbour whatever the rounding
    """
    points, directions = np.asarray(points, dtype=float), np.asarray(directions, dtype=float)
    rows = np.asarray(rows, dtype=np.int64)
    size = len(points)
    row, neighbour = np.repeat(rows, size), np.tile(np.arange(size), len(rows))  # (R A,), row-major
    return _kept(row, neighbour, *_pair_geometry(points, directions, row, neighbour), radius, max_angle,
                 pool).reshape(len(rows), size)


def _kept(row: np.ndarray, neighbour: np.ndarray, distance2: np.ndarray, cosine: np.ndarray, radius: float,
          max_angle: float, pool: int | None) -> np.ndarray:
    """(M,) bool, which pairs are neighbours: within the limits and ``neighbour`` in the pool, or a candidate with
    itself whatever the rounding (a NaN contact or a zero direction included)."""
    in_pool = True if pool is None else neighbour < pool
    return (_limits_hold(distance2, cosine, radius, max_angle) & in_pool) | (row == neighbour)


def _limits_hold(distance2: np.ndarray, cosine: np.ndarray, radius: float, max_angle: float) -> np.ndarray:
    """Contacts within ``radius`` (m) and directions within ``max_angle`` (rad), each with ``TOLERANCE``'s slack."""
    limit = radius + TOLERANCE
    return (distance2 <= limit * limit) & (cosine >= np.cos(max_angle) - TOLERANCE)


def chosen_means(
    action_offsets: np.ndarray,
    points: np.ndarray,
    directions: np.ndarray,
    p_topple: np.ndarray,
    chosen: np.ndarray,
    radius: float = RADIUS,
    max_angle: float = MAX_ANGLE,
) -> np.ndarray:
    """``neighbour_mean`` of P(topple) around the chosen pushes of each pose of one object.

    action_offsets : (P + 1,) int, pose x's candidates are rows action_offsets[x] : action_offsets[x + 1]
      of points, directions (N, 3) and p_topple (N,) (NaN unless ok)
    chosen : (P, k) int, k choices per pose (policies, budgets): action index within the pose, or NO_OP
    returns : (P, k) float, NaN where the choice is NO_OP
    """
    chosen = np.asarray(chosen)
    means = np.full(chosen.shape, np.nan)
    for x, actions in enumerate(chosen):
        pushing = np.flatnonzero(actions != NO_OP)
        if len(pushing):
            rows = slice(int(action_offsets[x]), int(action_offsets[x + 1]))
            means[x, pushing], _ = neighbour_mean(points[rows], directions[rows], p_topple[rows], radius, max_angle,
                                                  rows=actions[pushing])
    return means
