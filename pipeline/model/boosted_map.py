"""P(topple) from a gradient-boosted map of what the model computes (docs/MODEL.md C.19).

Every earlier map of P(topple) was a logistic regression on a few features (C.7, C.13, C.15,
C.16), and what is left of the model's error is shared by a pose's pushes (docs/VALIDATION.md,
stop 37): it depends on the pose and the object, and on how they combine with the push, which a
sum of a few weighted features cannot carry.  Boosted trees over the same kinds of features and
some of the object's shape can.  The map

    q(u) = sigmoid(b + sum_t tree_t(g(u)))                                                   (C.19.1)

replaces the push's P(topple) after every other map, and its row keeps where it lands (C.13.2,
``feature_map.landing_rows``): q times the landing, 1 - q stays; a push the model knows no landing
for keeps its row.  g(u) is ``FEATURES``, all from the model and the geometry, none from physics.

The trees are fitted elsewhere (``fit_trees``, scikit-learn's ``HistGradientBoostingClassifier``,
on logged pushes) and read here from a JSON file: the engine needs numpy only.  A file is named by
``topple.boosted_map``: a packaged map by its name (``presets/<name>.json``) or a path to one.
"""

from __future__ import annotations

import hashlib
import json
import sys
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .feature_map import (
    FORCE_RATIO_RANGE,
    LOGIT_FLOOR,
    down_features,
    landing_rows,
    needed_force_ratio,
    pose_features,
    toppled_rows,
)

if TYPE_CHECKING:  # the service imports the config, which names this module's files, without the geometry
    from schema.neighbourhood import Neighbours

    from .edges import EdgeGeometry
    from .mesh import ObjectModel

PRESETS = Path(__file__).with_name("presets")

FEATURES = (
    "logit_p", "logit_p_unmapped", "logit_neighbourhood", "log_force_ratio", "no_own_topple", "direction_z",
    "down_direction_z", "overhang", "height", "normal_z", "stability", "offset",
    "log_needed_force_ratio", "drop_probability", "log_poses", "base_edges", "widest_edge", "height_over_size",
    "flatness", "middle_over_size", "log_mass", "log_size", "horizontal", "contact_height_over_size",
)
"""g(u) of (C.19.1), in the column order the trees read.  P is the push's P(topple) after the other
maps, "unmapped" before any (C.12's smoothed counts); the next four are C.13's f(u) without its
bias and P; the next six C.15's g(u) without its bias and P; then log F*/mg (C.16, clipped to
``FORCE_RATIO_RANGE``); the start pose's drop probability, the log of the number of poses, the
number of base edges and the largest d_e over the centre of mass's height; the object: that height
over its longest extent, its shortest and middle extents over the longest, log mass (kg) and log
longest extent (m); the push: its direction's horizontal length and the contact's height over the
longest extent."""
MIN_HEIGHT = 1e-3
"""m, the centre of mass's height is taken at least this in the ratios (a marginal pose's can be 0)."""


class BoostedMapError(ValueError):
    """A file that is no boosted map; one line."""


@dataclass(frozen=True)
class BoostedTrees:
    """The trees of (C.19.1), their nodes in one array, each tree's after the one before.

    baseline : float, b (logit);  roots : (T,) int, each tree's first node
    feature : (N,) int, the column of ``FEATURES`` a node splits on;  threshold : (N,) float, x <= threshold
      goes left;  left, right : (N,) int, child nodes (indices into the same arrays)
    missing_left : (N,) bool, where NaN goes;  leaf : (N,) bool;  value : (N,) float, a leaf's logit
    sha256 : str, of the file it was read from
    """

    baseline: float
    roots: np.ndarray
    feature: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    right: np.ndarray
    missing_left: np.ndarray
    leaf: np.ndarray
    value: np.ndarray
    sha256: str = ""


def map_file(name: str) -> Path:
    """The file ``topple.boosted_map`` names: a path when it ends in .json, else a packaged map."""
    return Path(name) if name.endswith(".json") else PRESETS / f"{name}.json"


@lru_cache(maxsize=4)
def load_trees(name: str) -> BoostedTrees:
    """Read and check the map ``name`` names (``map_file``), once per process (cached by name: a file
    changed under a running job is not re-read).  Raises ``BoostedMapError``."""
    path = map_file(name)
    where = f"topple.boosted_map {name!r}"
    try:
        raw = path.read_bytes()
    except FileNotFoundError:
        packaged = f"any other value names a packaged map ({', '.join(packaged_maps())}); '' sets none"
        if name.endswith(".json"):
            raise BoostedMapError(f"{where}: no such file {path.resolve()}; a value ending in .json is a file's path, "
                                  f"{packaged}") from None
        raise BoostedMapError(f"{where}: no packaged map of that name; a value ending in .json is a file's path, "
                              f"{packaged}") from None
    except OSError as err:
        raise BoostedMapError(f"{where}: cannot read {path}: {err.strerror}") from None
    try:
        data = json.loads(raw)
    except ValueError as err:
        raise BoostedMapError(f"{where}: {path} is not valid JSON ({err})") from None
    return trees_from_dict(data, hashlib.sha256(raw).hexdigest(), name)


def packaged_maps() -> list[str]:
    """The names of the maps shipped in ``presets/`` (what ``topple.boosted_map`` may name without a path)."""
    return sorted(p.stem for p in PRESETS.glob("*.json"))


NODE_FIELDS = (("feature", int), ("threshold", float), ("left", int), ("right", int),
               ("missing_left", bool), ("leaf", bool), ("value", float))
"""A tree's lists in the JSON layout and the type of their entries (``trees_from_dict``)."""


def trees_from_dict(data: dict, sha256: str = "", name: str = "") -> BoostedTrees:
    """``BoostedTrees`` from the JSON layout ``fit_trees`` writes: {"features": [...], "baseline": b,
    "trees": [{"feature", "threshold", "left", "right", "missing_left", "leaf", "value"}, ...]}, each
    tree's seven lists one entry per node, root first, its child indices counted within the tree.
    Raises ``BoostedMapError`` on anything else, naming the tree."""
    where = f"topple.boosted_map {name!r}"
    if not isinstance(data, dict):
        raise BoostedMapError(f"{where}: not a JSON object")
    features = data.get("features")
    if not isinstance(features, (list, tuple)) or list(features) != list(FEATURES):
        raise BoostedMapError(f"{where}: its features are not this version's ({len(FEATURES)}, from {FEATURES[0]})")
    baseline, trees = data.get("baseline"), data.get("trees")
    # abs(b) <= the largest float: finite, and a float holds it (np.isfinite raises on a JSON integer past that)
    if isinstance(baseline, bool) or not isinstance(baseline, (int, float)) or not abs(baseline) <= sys.float_info.max:
        raise BoostedMapError(f"{where}: the baseline is not a finite number")
    if not isinstance(trees, list) or not trees:
        raise BoostedMapError(f"{where}: no list of trees")
    columns = {key: [] for key, _ in NODE_FIELDS}
    for i, tree in enumerate(trees):
        for key, values in _tree_lists(tree, f"{where}: tree {i}").items():
            columns[key].append(values)
    sizes = np.array([len(v) for v in columns["value"]])  # (T,)
    roots = np.concatenate([[0], np.cumsum(sizes)[:-1]])  # (T,)
    fields = {key: np.concatenate(columns[key]) for key, _ in NODE_FIELDS}  # (N,) each
    inner, offset, size = ~fields["leaf"], np.repeat(roots, sizes), np.repeat(sizes, sizes)
    for child in ("left", "right"):
        if np.any(inner & ((fields[child] < 0) | (fields[child] >= size))):
            raise BoostedMapError(f"{where}: a node points outside its tree")
        fields[child] = np.where(inner, fields[child] + offset, np.arange(len(offset)))  # a leaf points at itself
    if np.any(inner & ((fields["feature"] < 0) | (fields["feature"] >= len(FEATURES)))):
        raise BoostedMapError(f"{where}: a node splits on no feature")
    if np.any(inner & ~np.isfinite(fields["threshold"])):
        raise BoostedMapError(f"{where}: a node's threshold is not finite")
    if not np.all(np.isfinite(fields["value"][fields["leaf"]])):
        raise BoostedMapError(f"{where}: a leaf's value is not finite")
    fields["feature"] = np.where(inner, fields["feature"], 0)
    _check_paths(roots, fields["left"], fields["right"], fields["leaf"], where)
    return BoostedTrees(baseline=float(baseline), roots=roots, sha256=sha256, **fields)


def _tree_lists(tree, where: str) -> dict[str, np.ndarray]:
    """One tree's seven lists as arrays, each of one length of at least 1 and of its entries' type
    (``NODE_FIELDS``; JSON's true and false for the flags, numbers for the rest).  Raises ``BoostedMapError``."""
    if not isinstance(tree, dict) or any(key not in tree for key, _ in NODE_FIELDS):
        raise BoostedMapError(f"{where} is not an object with the lists {', '.join(k for k, _ in NODE_FIELDS)}")
    out = {}
    for key, kind in NODE_FIELDS:
        values = tree[key]
        if not isinstance(values, list) or not values:
            raise BoostedMapError(f"{where}: {key} is not a list of nodes")
        if kind is bool:
            ok = all(isinstance(v, bool) for v in values)
        elif kind is int:
            ok = all(isinstance(v, int) and not isinstance(v, bool) for v in values)
        else:
            ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values)
        if not ok:
            raise BoostedMapError(f"{where}: {key} holds entries that are not {kind.__name__}")
        try:
            out[key] = np.array(values, dtype=np.int64 if kind is int else kind)
        except OverflowError:  # a JSON integer past int64 (or past any float)
            raise BoostedMapError(f"{where}: {key} holds entries out of range") from None
    if len({len(v) for v in out.values()}) != 1:
        raise BoostedMapError(f"{where}: its lists differ in length")
    return out


def _check_paths(roots: np.ndarray, left: np.ndarray, right: np.ndarray, leaf: np.ndarray, where: str) -> None:
    """Raise unless every tree is a tree: no node reached twice from its root (so every walk ends)."""
    for tree, root in enumerate(roots):
        seen, stack = set(), [int(root)]
        while stack:
            node = stack.pop()
            if node in seen:
                raise BoostedMapError(f"{where}: tree {tree} reaches node {node - root} twice")
            seen.add(node)
            if not leaf[node]:
                stack += [int(left[node]), int(right[node])]


def boosted_probability(features: np.ndarray, trees: BoostedTrees) -> np.ndarray:
    """q of (C.19.1): every (tree, push) pair walks down one level a step, until all are at a leaf.

    features : (A, len(FEATURES)) float (NaN follows each node's ``missing_left``)
    returns : (A,) float in (0, 1)
    """
    features = np.asarray(features, dtype=float)
    if features.ndim != 2 or features.shape[1] != len(FEATURES):
        raise ValueError(f"features must be (A, {len(FEATURES)}), got {features.shape}")
    n_pushes = len(features)
    if n_pushes == 0:
        return np.empty(0)
    old, roots, n_inner, child, threshold, offset = _walk_tables(features, trees)
    n_trees = len(roots)
    columns = np.ascontiguousarray(features.T)  # (F, A): pair t A + a reads feature f at f A + a + offset
    values = columns.ravel()
    missing = np.isnan(values).any()  # an ok push has no NaN feature: the check is skipped for the engine
    node = np.repeat(roots, n_pushes).reshape(n_trees, n_pushes)  # (T, A), new numbers, tree-major
    # The first step, from the roots, a tree at a time: all its pushes read one column against one threshold.
    walk = np.flatnonzero(node[:, 0] < n_inner)  # (t,), the trees whose root is no leaf
    at = node[walk, 0]
    x = columns[trees.feature[old[at]]]  # (t, A)
    go_left = x <= threshold[at, None]  # False for NaN, which goes where missing_left says
    if missing:
        go_left = np.where(np.isnan(x), trees.missing_left[old[at], None], go_left)
    node[walk] = at = child[2 * at[:, None] + go_left]
    node, pair = node.ravel(), (walk[:, None] * n_pushes + np.arange(n_pushes)).ravel()
    # Then the pairs still above a leaf, a level a step: trees stop at depths from 1 to about 15.
    keep = np.flatnonzero(at.ravel() < n_inner)
    pair, at = pair.take(keep), at.ravel().take(keep)
    while pair.size:
        x = values[pair + offset[at]]
        go_left = x <= threshold[at]
        if missing:
            nan = np.isnan(x)
            go_left[nan] = trees.missing_left[old[at[nan]]]
        node[pair] = at = child[2 * at + go_left]
        keep = np.flatnonzero(at < n_inner)  # inner nodes are numbered first
        pair, at = pair.take(keep), at.take(keep)
    raw = trees.baseline + trees.value[old][node].reshape(n_trees, n_pushes).sum(axis=0)  # (A,)
    return 1.0 / (1.0 + np.exp(-raw))


def _walk_tables(features: np.ndarray, trees: BoostedTrees) -> tuple[np.ndarray, np.ndarray, int, np.ndarray, np.ndarray,
                                                                      np.ndarray]:
    """The nodes renumbered for ``boosted_probability``'s walk: the inner ones first (a walk ends where the
    number reaches n_inner, a comparison instead of a lookup), each with what a step reads, shared splits
    resolved (``_skip_shared_splits``).

    features : (A, F) float
    returns : old (N,) int, each new number's node;  roots (T,) int, new numbers;  n_inner : int;
      child (2 n_inner,) int, new number 2 i + (x <= threshold) is inner node i's next;
      threshold (n_inner,) float;  offset (n_inner,) int, added to pair t A + a to read its feature at f A + a
    """
    roots, left, right = _skip_shared_splits(features, trees)
    n_nodes = len(trees.leaf)
    old = np.argsort(trees.leaf, kind="stable")  # (N,): new number -> node
    new = np.empty(n_nodes, dtype=np.int64)
    new[old] = np.arange(n_nodes)
    n_inner = n_nodes - int(np.count_nonzero(trees.leaf))
    inner = old[:n_inner]
    child = new[np.column_stack([right[inner], left[inner]])].ravel()
    tree = np.repeat(np.arange(len(trees.roots)), np.diff(np.append(trees.roots, n_nodes)))  # (N,)
    offset = (trees.feature[inner] - tree[inner]) * len(features)
    return old, new[roots], n_inner, child, trees.threshold[inner], offset


def _skip_shared_splits(features: np.ndarray, trees: BoostedTrees) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The trees' roots and child pointers with every split on a column all pushes share resolved.

    A pose's pushes share nine of the 24 features (its drop probability, the object's shape, ...), and
    two fifths of the packaged map's splits are on them: every push takes the same branch there, so the
    walk jumps past those nodes instead of stepping each push through them.  The leaves reached, and the
    sum over them, are the plain walk's.
    features : (A, F) float;  returns : roots (T,), left (N,), right (N,) int
    """
    first = features[0]
    shared = np.all(features == first, axis=0)  # (F,); NaN != NaN, so a column with a NaN is never shared
    split = ~trees.leaf & shared[trees.feature]  # (N,)
    taken = np.where(first[trees.feature] <= trees.threshold, trees.left, trees.right)  # (N,), read where split
    jump = np.where(split, taken, np.arange(len(split)))  # (N,): a shared split's node -> the branch all take
    # Pointer jumping: a chain of shared splits resolves in about log2(its length) rounds.  Stopping early
    # would still be right (the walk steps through a shared split like any other), only slower.
    while True:
        further = jump[jump]
        if np.array_equal(further, jump):
            break
        jump = further
    return jump[trees.roots], jump[trees.left], jump[trees.right]


def boosted_features(
    p_topple: np.ndarray,
    unmapped_p: np.ndarray,
    mean_force: np.ndarray,
    actions,
    edges: EdgeGeometry,
    center_mass: np.ndarray,
    drop_probabilities: np.ndarray,
    start: int,
    obj: ObjectModel,
    gravity: float,
    pool: int | None = None,
    near: Neighbours | None = None,
) -> np.ndarray:
    """g(u) (``FEATURES``) of every push of one pose.

    p_topple : (A,) float, P after the other maps;  unmapped_p : (A,) float, before any (NaN: not ok)
    mean_force : (A,) float, N, (9.3) of the push's own topples, NaN where none
    actions : the pose's pushes (points, normals, directions (A, 3), pose frame)
    edges : ``edges.edge_geometry`` of the pose;  center_mass : (3,) float, m, pose frame
    drop_probabilities : (P,) float, the pose set's;  start : the pose's index;  obj : the object
    gravity : m/s^2;  pool : the pose's candidates, over which N is taken (``pose_features``)
    near : ``neighbour_pairs`` with ``pool`` when at hand (else found here)
    returns : (A, len(FEATURES)) float, NaN rows where ``unmapped_p`` is NaN
    """
    n = len(p_topple)
    points, directions = np.asarray(actions.points, dtype=float), np.asarray(actions.directions, dtype=float)
    push = pose_features(unmapped_p, points, directions, mean_force, obj.mass * gravity, pool=pool, near=near)  # (A, 6)
    down = down_features(unmapped_p, points, actions.normals, directions, edges, center_mass)  # (A, 8)
    height = max(float(center_mass[2]), MIN_HEIGHT)  # m
    extents = np.sort(np.asarray(obj.mesh.extents, dtype=float))[::-1]  # (3,), m, longest first

    def each(value: float) -> np.ndarray:
        return np.full(n, value)

    features = np.column_stack([
        fitted_logit(p_topple),
        fitted_logit(unmapped_p),
        push[:, 2:],
        down[:, 2:],
        np.log(np.clip(needed_force_ratio(points, directions, edges), *FORCE_RATIO_RANGE)),
        each(drop_probabilities[start]),
        each(np.log(len(drop_probabilities))),
        each(len(edges.com_distance)),
        each(edges.com_distance.max() / height),
        each(height / extents[0]),
        each(extents[2] / extents[0]),
        each(extents[1] / extents[0]),
        each(np.log(obj.mass)),
        each(np.log(extents[0])),
        np.hypot(directions[:, 0], directions[:, 1]),
        points[:, 2] / extents[0],
    ])  # (A, F)
    features[~np.isfinite(np.asarray(unmapped_p, dtype=float))] = np.nan
    return features


def fitted_logit(p: np.ndarray) -> np.ndarray:
    """logit of P clipped to [LOGIT_FLOOR, 1 - LOGIT_FLOOR], as log(p / (1 - p)): the form
    ``boosted_map_s41``'s ``logit_p`` was fitted on.  A third of pushes sit at the floor, and that map has
    thresholds exactly at the floor's value, so ``feature_map.logit``'s form, one rounding (1 ulp) higher,
    sends them down the other branch.  (Its ``logit_p_unmapped`` was fitted on ``feature_map.logit``'s
    form; this one is 1 ulp lower, so those pushes still go left of its floor thresholds, as in the fit.
    ``logit_neighbourhood`` is ``feature_map.logit``'s, as fitted.)"""
    p = np.clip(np.asarray(p, dtype=float), LOGIT_FLOOR, 1.0 - LOGIT_FLOOR)
    return np.log(p / (1.0 - p))


def map_boosted_rows(next_pose: np.ndarray, features: np.ndarray, start: int, actions, trees: BoostedTrees,
                     pool: int | None = None, near: Neighbours | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Apply (C.19.1) to every ok row of one pose.

    next_pose : (A, P) float, the rows after the other maps (NaN rows: not ok)
    features : (A, len(FEATURES)) float, ``boosted_features``;  pool, near : as ``landing_rows``
    returns : next_pose (A, P), an ok row (1 - q) at ``start`` plus q times its landing (C.13.2),
      a row with no known landing unchanged;  p_topple (A,)
    """
    next_pose = np.array(next_pose, dtype=float)
    ok = np.flatnonzero(np.isfinite(next_pose[:, start]))  # (K,)
    if len(ok) == 0:
        return next_pose, 1.0 - next_pose[:, start]
    landing = landing_rows(next_pose, start, actions.points, actions.directions, pool=pool, rows=ok, near=near)  # (K, P)
    lands = landing.sum(axis=1) > 0
    next_pose[ok[lands]] = toppled_rows(boosted_probability(features[ok[lands]], trees), landing[lands], start)
    return next_pose, 1.0 - next_pose[:, start]


def fit_trees(features: np.ndarray, observed: np.ndarray, repeats: np.ndarray, seed: int = 0, **params) -> dict:
    """Fit (C.19.1) on logged pushes and return it in the layout ``trees_from_dict`` reads.

    features : (n, len(FEATURES)) float;  observed : (n,) float, each push's topple rate
    repeats : (n,) int, its repeats (each push is two weighted rows: the toppled and the stayed)
    params : ``HistGradientBoostingClassifier``'s, over ``FIT_PARAMS``
    Needs scikit-learn (the ``pipeline`` extra); the engine does not.
    """
    from sklearn.ensemble import HistGradientBoostingClassifier

    features = np.asarray(features, dtype=float)
    repeats = np.asarray(repeats, dtype=float)
    toppled = np.round(np.asarray(observed, dtype=float) * repeats)
    weight = np.concatenate([toppled, repeats - toppled])
    keep = weight > 0
    x = np.vstack([features, features])[keep]
    y = np.concatenate([np.ones(len(features)), np.zeros(len(features))])[keep]
    model = HistGradientBoostingClassifier(**{**FIT_PARAMS, **params, "random_state": seed})
    model.fit(x, y, sample_weight=weight[keep])
    trees = []
    for (predictor,) in model._predictors:  # sklearn's fitted nodes: the only place its trees are kept
        nodes = predictor.nodes
        trees.append({"feature": nodes["feature_idx"].tolist(), "threshold": nodes["num_threshold"].tolist(),
                      "left": nodes["left"].tolist(), "right": nodes["right"].tolist(),
                      "missing_left": nodes["missing_go_to_left"].astype(bool).tolist(),
                      "leaf": nodes["is_leaf"].astype(bool).tolist(), "value": nodes["value"].tolist()})
    return {"features": list(FEATURES), "baseline": float(np.ravel(model._baseline_prediction)[0]), "trees": trees}


FIT_PARAMS = {"max_leaf_nodes": 20, "max_depth": None, "learning_rate": 0.03, "max_iter": 300,
              "min_samples_leaf": 200, "l2_regularization": 1.0, "early_stopping": "auto"}
"""Candidate B's setting (reports/boosted_map_rule_s41.md): the best of five on the corpus logs'
object-grouped cross-validation; scikit-learn's defaults otherwise.  ``early_stopping="auto"`` (the
default, spelled out) stops adding trees when a random tenth of the rows, held out, stops improving, on
fits of more than 10,000 rows (the corpus's 8,261 pushes are about 16,000): B's fit ran all 300."""
