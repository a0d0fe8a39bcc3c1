"""Validation of the toppling model against a physics engine (thesis 4.4.2, table 4.3).

The thesis compared the model with 700 physical pushes; here ``pushsim`` plays the
pushes in pybullet.  Repeating a push under the model's noise gives an empirical
next-pose distribution, compared with each model variant's prediction by the
thesis's metrics (mean total variation in sup form, mAP of "it topples").

    toppledb validate --objects 4 --actions 5 --repeats 10 --plot docs/physics_validation.png
"""


from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schema.vocabulary import STATUS_OK

from ..model.config import VARIANTS, Config
from ..model.evaluation import evaluate
from ..model.mesh import MeshError, ObjectModel, load_mesh, model_from_mesh
from ..model.poses import PoseSet, stable_poses
from .pushsim import BodyModel, body_model, empirical_distribution, simulate_push

THESIS_TABLE_4_3 = {
    "baseline": {"tv": 0.424, "map": 0.412},
    "rotations": {"tv": 0.494, "map": 0.381},
    "robustness": {"tv": 0.247, "map": 0.568},
    "robust": {"tv": 0.211, "map": 0.589},
}
"""Thesis table 4.3: final-pose predictions against 700 physical pushes (6-fold cross-validated)."""

# ---------------------------------------------------------------- metrics


def total_variation(predicted: np.ndarray, empirical: np.ndarray) -> float:
    """The thesis's sup form: max over next poses of |P_hat(x') - P(x')|.

    predicted, empirical : (P,) float, distributions over the same buckets
    returns : float in [0, 1]
    """
    return float(np.max(np.abs(np.asarray(predicted, dtype=float) - np.asarray(empirical, dtype=float))))


def average_precision(scores: np.ndarray, labels: np.ndarray) -> float:
    """Average precision of ranking by ``scores`` against binary ``labels``.

    Tied scores form one threshold (as scikit-learn's ``average_precision_score``), so a
    0/1 score is not credited for an arbitrary order inside a tie.
    scores : (n,) float;  labels : (n,) bool
    returns : float in [0, 1]; NaN without positive labels
    """
    scores = np.asarray(scores, dtype=float)
    labels = np.asarray(labels, dtype=bool)
    if not labels.any():
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    scores, labels = scores[order], labels[order]
    # Last index of each block of equal scores: the thresholds.
    last = np.flatnonzero(np.r_[scores[1:] != scores[:-1], True])
    true_positives = np.cumsum(labels)[last]
    precision = true_positives / (last + 1)
    recall = true_positives / labels.sum()
    return float(np.sum(np.diff(np.r_[0.0, recall]) * precision))


# ---------------------------------------------------------------- validation


@dataclass
class ActionRecord:
    """One validated action: where, what physics did, what each variant predicted.

    object, pose, action : identifiers;  point, direction : (3,) float, pose frame
    empirical : (P + 1,) float, simulated next-pose frequencies (last: outside the pose set)
    predicted : dict variant -> (P + 1,) float
    """

    object: str
    pose: int
    action: int
    point: np.ndarray
    direction: np.ndarray
    empirical: np.ndarray
    predicted: dict[str, np.ndarray]

    @property
    def empirical_topple(self) -> float:
        """Fraction of repeats that ended in another pose (outside the set counts as toppled)."""
        return 1.0 - float(self.empirical[self.pose])


def choose_actions(p_topple: np.ndarray, status: np.ndarray, k: int, rng: np.random.Generator, eps: float = 0.05) -> np.ndarray:
    """Up to ``k`` distinct ``ok`` actions, drawn with probability proportional to P(topple) + eps (thesis 4.4.2).

    p_topple : (A,) float (NaN for actions that are not ok);  status : (A,) int8
    returns : (min(k, #ok),) int, action indices
    """
    ok = np.flatnonzero(status == STATUS_OK)
    if len(ok) == 0:
        return ok
    weights = np.nan_to_num(p_topple[ok]) + eps
    return np.sort(rng.choice(ok, size=min(k, len(ok)), replace=False, p=weights / weights.sum()))


def validate_pose(
    obj: ObjectModel,
    pose_set: PoseSet,
    pose: int,
    n_actions: int,
    n_repeats: int,
    config: Config,
    seed: int,
    body: BodyModel,
    n_contacts: int = 200,
    n_trials: int = 50,
) -> list[ActionRecord]:
    """Pick actions of one pose from the robust model's table, simulate them, predict them with every variant."""
    rng = np.random.default_rng([seed, pose, _name_key(obj.name)])
    table = evaluate(obj, pose_set, pose, n_contacts=n_contacts, n_trials=n_trials, variant="robust", seed=seed, config=config)
    chosen = choose_actions(table.table.p_topple, table.actions.status, n_actions, rng)
    if len(chosen) == 0:
        return []
    points, directions = table.actions.points[chosen], table.actions.directions[chosen]
    n_poses = len(pose_set.poses)
    predicted = {}
    for variant in VARIANTS:
        result = evaluate(obj, pose_set, pose, points=points, directions=directions, n_trials=n_trials, variant=variant, seed=seed, config=config)
        predicted[variant] = np.hstack([result.table.next_pose, np.zeros((len(chosen), 1))])
    records = []
    for i, action in enumerate(chosen):
        outcomes = np.array(
            [simulate_push(obj, pose_set, pose, points[i], directions[i], config, rng, noise=True, body=body) for _ in range(n_repeats)]
        )
        records.append(
            ActionRecord(obj.name, pose, int(action), points[i], directions[i], empirical_distribution(outcomes, n_poses),
                         {v: predicted[v][i] for v in VARIANTS})
        )
    return records


def _name_key(name: str) -> int:
    """A stable integer from an object name for seeding (``hash`` is salted per process)."""
    return int.from_bytes(name.encode()[:16].ljust(16, b"\0"), "little") % (2**63)


def metrics(records: list[ActionRecord]) -> dict[str, dict[str, float]]:
    """Mean TV and mAP per variant.

    TV: mean over (pose, action) of the sup-form total variation.
    mAP: average precision of the variant's P(topple) as the score for the label "most
    repeats toppled" (empirical P(topple) > 0.5), computed per object and averaged over the
    objects that have at least one positive label; ``ap_pooled`` is the same over all actions.
    """
    out = {}
    for variant in VARIANTS:
        tv = [total_variation(r.predicted[variant], r.empirical) for r in records]
        scores = np.array([1.0 - r.predicted[variant][r.pose] for r in records])
        labels = np.array([r.empirical_topple > 0.5 for r in records])
        names = np.array([r.object for r in records])
        per_object = [average_precision(scores[names == n], labels[names == n]) for n in dict.fromkeys(names)]
        per_object = [ap for ap in per_object if not np.isnan(ap)]
        out[variant] = {
            "tv": float(np.mean(tv)) if tv else float("nan"),
            "map": float(np.mean(per_object)) if per_object else float("nan"),
            "ap_pooled": average_precision(scores, labels) if len(records) else float("nan"),
        }
    return out


@dataclass
class Validation:
    """Result of ``validate``: per-action records, metrics per variant, counts."""

    records: list[ActionRecord]
    metrics: dict[str, dict[str, float]]
    counts: dict[str, int]


def validate(
    objects: list[ObjectModel],
    n_actions: int = 5,
    n_repeats: int = 10,
    config: Config = Config(),
    seed: int = 0,
    *,
    max_poses: int | None = None,
    n_contacts: int = 200,
    n_trials: int = 50,
) -> Validation:
    """Simulate pushes chosen from the robust model on every pose of every object and score each variant.

    objects : the objects;  n_actions : actions per pose;  n_repeats : simulated pushes per action
    max_poses : only each object's most probable poses (all when None)
    n_contacts, n_trials : the model's candidate contacts and trials per action
    """
    records: list[ActionRecord] = []
    n_poses = 0
    for obj in objects:
        pose_set = stable_poses(obj, config.poses)
        body = body_model(obj)
        indices = range(len(pose_set.poses) if max_poses is None else min(max_poses, len(pose_set.poses)))
        for pose in indices:
            n_poses += 1
            records += validate_pose(obj, pose_set, pose, n_actions, n_repeats, config, seed, body, n_contacts, n_trials)
    counts = {"objects": len(objects), "poses": n_poses, "actions": len(records), "pushes": len(records) * n_repeats}
    return Validation(records, metrics(records), counts)


# ---------------------------------------------------------------- command line


def default_objects(n: int) -> list[ObjectModel]:
    """A box and pybullet_data's random objects (URDF scale 0.015, mass 0.1), ``n`` in all; unloadable ones skipped."""
    import pybullet_data
    import trimesh

    box = trimesh.creation.box((0.05, 0.08, 0.15))
    box.apply_translation([0, 0, 0.075])
    objects = [model_from_mesh(box, mass=0.25, name="box")][:n]
    root = Path(pybullet_data.getDataPath()) / "random_urdfs"
    index = 0
    while len(objects) < n and index < 1000:
        try:
            objects.append(load_mesh(root / f"{index:03d}" / f"{index:03d}.obj", scale=0.015, mass=0.1, name=f"random_{index:03d}"))
        except (MeshError, OSError):
            pass
        index += 1
    return objects


def format_table(result: Validation) -> str:
    """Plain-text table: per variant, simulated TV / mAP next to thesis table 4.3."""
    def cell(value):
        return "  -  " if value is None or np.isnan(value) else f"{value:.3f}"

    lines = [
        f"{'variant':<11} {'TV (sim)':>9} {'mAP (sim)':>10} {'AP pooled':>10} {'TV thesis':>10} {'mAP thesis':>11}",
    ]
    for variant in VARIANTS:
        m, thesis = result.metrics[variant], THESIS_TABLE_4_3.get(variant, {})
        lines.append(
            f"{variant:<11} {cell(m['tv']):>9} {cell(m['map']):>10} {cell(m['ap_pooled']):>10} "
            f"{cell(thesis.get('tv')):>10} {cell(thesis.get('map')):>11}"
        )
    return "\n".join(lines)


def plot(result: Validation, path: str | Path) -> None:
    """Bar chart of mean TV and mAP per variant, with the thesis's table 4.3 values marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    x = np.arange(len(VARIANTS))
    for ax, key, title in zip(axes, ("tv", "map"), ("mean TV (lower is better)", "mAP of 'topples' (higher is better)")):
        ax.bar(x, [result.metrics[v][key] for v in VARIANTS], color="tab:blue", label="pybullet")
        thesis = [THESIS_TABLE_4_3.get(v, {}).get(key, np.nan) for v in VARIANTS]
        ax.scatter(x, thesis, color="tab:red", marker="_", s=600, linewidths=3, label="thesis (physical)", zorder=3)
        ax.set_xticks(x, VARIANTS)
        ax.set_ylim(0, 1)
        ax.set_title(title)
    axes[0].legend(loc="upper right")
    c = result.counts
    fig.suptitle(f"Model vs pybullet: {c['objects']} objects, {c['poses']} poses, {c['actions']} actions, {c['pushes']} pushes")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    """``toppledb validate``: run ``validate`` on a box and random objects and print the table."""
    parser = argparse.ArgumentParser(prog="toppledb validate", description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", type=int, default=4, help="number of objects: a box, then pybullet_data random objects")
    parser.add_argument("--actions", type=int, default=5, help="actions per pose")
    parser.add_argument("--repeats", type=int, default=10, help="simulated pushes per action")
    parser.add_argument("--max-poses", type=int, default=None, help="only each object's most probable poses")
    parser.add_argument("--contacts", type=int, default=200, help="candidate contacts of the model's table")
    parser.add_argument("--trials", type=int, default=50, help="model trials per action (robust variants)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plot", default=None, help="write a bar chart to this PNG")
    args = parser.parse_args(argv)

    started = time.perf_counter()
    config = Config(seed=args.seed)
    result = validate(default_objects(args.objects), args.actions, args.repeats, config, args.seed,
                      max_poses=args.max_poses, n_contacts=args.contacts, n_trials=args.trials)
    wall = time.perf_counter() - started
    c = result.counts
    print(f"{c['objects']} objects, {c['poses']} poses, {c['actions']} actions x {args.repeats} repeats = {c['pushes']} simulated pushes, {wall:.1f} s")
    print(format_table(result))
    if args.plot:
        plot(result, args.plot)
        print(f"plot: {args.plot}")
    # NaN (no positive label) becomes null so the last line is strict JSON.
    metrics_json = {v: {k: None if np.isnan(x) else x for k, x in m.items()} for v, m in result.metrics.items()}
    print(json.dumps({"counts": c, "repeats": args.repeats, "seed": args.seed, "wall_s": round(wall, 1),
                      "metrics": metrics_json, "thesis": THESIS_TABLE_4_3}, allow_nan=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
