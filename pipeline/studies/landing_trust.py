"""Fit and score the landing trust (candidate LT, ``pipeline.model.landing_trust``) on a push log.

Each logged push is read against the row the planner saw: its object's dataset (one of
``--datasets``, the datasets out of fold the log was played on) holds the push as action
``push_id % ACTION_SPAN`` of pose ``push_id // ACTION_SPAN``, as ``oracle_policy --log`` writes
it.  The row (every pose, plus 0 outside the pose set) is scored against the plays' observed
next poses by the multi-class Brier score (``scoring.brier_score``); the untrusted share per band
is fitted by bounded least squares on the same score, since (LT.1) is linear in it.  With
``--folds DIR`` (a ``--fold-maps`` directory) the shares are also fitted on all folds but one and
scored on that one, every fold in turn, against the rows as they are, the prior alone and the
trivial predictors; the interval is over objects, paired.  ``--shares U...`` scores given shares
instead of fitting them: on a log of objects they were not fitted on, whether the fit carries over.

    python -m pipeline.studies.landing_trust data/logs/corpus_planner --datasets data/corpus_oof_sa_{0..5} \\
        --folds data/corpus_folds --json F
    python -m pipeline.studies.landing_trust LOG --datasets DATASET --shares 0.491 0.241 0.147 0.029
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schema.reader import Dataset, DatasetUnreadable

from ..model.config import Config
from ..model.landing_spread import landing_prior
from ..model.landing_trust import BANDS, checked_shares, landing_bands, trust_terms
from .compare_fold_maps import paired_interval
from .logreader import LogError, read_log
from .policy_experiment import ACTION_SPAN
from .recalibrate import RecalibrationError, fold_of_pushes, read_fold_lists
from .robust_policy import next_pose_rows


class TrustError(ValueError):
    """Inputs the fit cannot use (one line)."""


@dataclass
class TrustData:
    """Every usable push as flat buckets: push i's buckets are ``start[i]:start[i+1]``.

    row : (N,) float, the dataset's P(x' | x, u), 0 outside the pose set;  terms : (N, B) float,
    (LT.1)'s terms;  observed : (N,) float, the plays' frequencies;  prior : (N,) float, the
    drop-probability landing;  stay : (N,) bool, the start pose's bucket;  band : (N,) int, the band of
    each other pose's drop probability (``landing_bands``), -1 at the start pose and outside;  start : (n + 1,) int
    objects : (n,) str per push;  plays : (n,) int;  rejected : reason -> pushes
    """

    row: np.ndarray
    terms: np.ndarray
    observed: np.ndarray
    prior: np.ndarray
    stay: np.ndarray
    band: np.ndarray
    start: np.ndarray
    objects: np.ndarray
    plays: np.ndarray
    rejected: Counter

    @property
    def bucket_push(self) -> np.ndarray:
        """(N,) int, the push each bucket belongs to."""
        return np.repeat(np.arange(len(self.objects)), np.diff(self.start))


POSE_COLUMNS = ["object_id", "pose", "probability", "n_actions"]
"""What the fit reads of a dataset's poses table."""


def object_datasets(roots: list[Path]) -> dict[str, Dataset]:
    """Object id -> the dataset that holds it; an object in two datasets, or a dataset whose poses
    table cannot be read with ``POSE_COLUMNS``, is an error."""
    found: dict[str, Dataset] = {}
    for root in roots:
        try:
            dataset = Dataset.open(root)
            names = dataset.table("poses", columns=POSE_COLUMNS).column("object_id").to_pylist()
        except DatasetUnreadable as err:  # a missing column too: the reader names the file and the column
            raise TrustError(str(err)) from None
        for object_id in set(names):
            if object_id in found:
                raise TrustError(f"object {object_id!r} is in {found[object_id].root} and {root}; give each object's dataset once")
            found[object_id] = dataset
    return found


def pose_columns(dataset: Dataset, columns: list[str]) -> dict[str, dict[str, np.ndarray]]:
    """Each object's ``columns`` of the poses table, (P,) arrays in pose order, read in one pass."""
    table = dataset.table("poses", columns=["object_id", "pose", *columns]).sort_by([("object_id", "ascending"), ("pose", "ascending")])
    ids = np.asarray(table.column("object_id").to_pylist(), dtype=object)
    values = {name: table.column(name).to_numpy(zero_copy_only=False) for name in columns}
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]]) if len(ids) else np.zeros(0, int)
    return {ids[a]: {name: column[a:b] for name, column in values.items()} for a, b in zip(starts, [*starts[1:], len(ids)])}


def poses_by_object(dataset: Dataset) -> dict[str, tuple[np.ndarray, list[int]]]:
    """Each object's drop probabilities ((P,) float) and actions per pose, in pose order."""
    return {object_id: (c["probability"].astype(float), c["n_actions"].tolist())
            for object_id, c in pose_columns(dataset, ["probability", "n_actions"]).items()}


def trust_data(log, datasets: dict[str, Dataset]) -> TrustData:
    """The log's pushes against their datasets' rows (``TrustData``); a push whose object or action
    the datasets do not hold is counted under its reason, not used."""
    parts = {name: [] for name in ("row", "terms", "observed", "prior", "stay", "band")}
    objects, plays, sizes = [], [], []
    rejected: Counter = Counter()
    poses_of: dict[Path, dict] = {}  # each dataset's poses, object -> (drop probabilities, actions per pose), read once
    by_object: dict[str, list] = {}
    for push in log.pushes:
        by_object.setdefault(push.object_id, []).append(push)
    for object_id, pushes in by_object.items():
        dataset = datasets.get(object_id)
        if dataset is None:
            rejected["object in none of the datasets"] += len(pushes)
            continue
        if dataset.root not in poses_of:
            poses_of[dataset.root] = poses_by_object(dataset)
        drop, n_actions = poses_of[dataset.root].get(object_id, (np.zeros(0), []))
        if len(drop) != len(log.objects[object_id].poses.poses):
            rejected["the dataset's stable poses differ from the log's"] += len(pushes)
            continue
        rows = next_pose_rows(dataset, object_id, n_actions)
        terms = [trust_terms(r, x, drop) for x, r in enumerate(rows)]
        bucket = np.arange(len(drop) + 1)  # every pose, then outside the pose set
        bands = np.append(landing_bands(drop), -1)
        priors = [np.append(landing_prior(drop, x, len(drop)), 0.0) for x in range(len(drop))]
        for push in pushes:
            pose, action = divmod(int(push.push_id), ACTION_SPAN)
            if pose != push.pose or action >= len(rows[pose]) or not np.isfinite(rows[pose][action]).all():
                rejected["push id names no ok push of its start pose"] += 1
                continue
            parts["row"].append(np.append(rows[pose][action], 0.0))
            parts["terms"].append(np.vstack([terms[pose][action], np.zeros(len(BANDS) + 1)]))
            parts["observed"].append(push.empirical(len(drop)))
            parts["prior"].append(priors[pose])
            parts["stay"].append(bucket == pose)
            parts["band"].append(np.where(bucket == pose, -1, bands))
            objects.append(object_id)
            plays.append(len(push.outcomes))
            sizes.append(len(drop) + 1)
    if not objects:
        raise TrustError(f"no push of the log is in the datasets (rejected: {dict(rejected)})")
    flat = {name: np.concatenate(values) for name, values in parts.items()}
    return TrustData(flat["row"], flat["terms"], flat["observed"], flat["prior"], flat["stay"], flat["band"],
                     np.concatenate([[0], np.cumsum(sizes)]), np.array(objects), np.array(plays), rejected)


def fit_shares(data: TrustData, pushes: np.ndarray | None = None) -> np.ndarray:
    """The untrusted shares u_b in [0, 1] of least Brier score over ``pushes`` ((n,) bool, default all),
    each push weighted alike.  A band no push lands in gets 0 (nothing says to move it)."""
    from scipy.optimize import lsq_linear

    keep = np.ones(len(data.objects), dtype=bool) if pushes is None else np.asarray(pushes, dtype=bool)
    buckets = keep[data.bucket_push]
    terms = data.terms[buckets]
    used = np.abs(terms).sum(axis=0) > 0
    shares = np.zeros(terms.shape[1])
    if used.any():
        shares[used] = lsq_linear(terms[:, used], (data.observed - data.row)[buckets], bounds=(0.0, 1.0), method="bvls").x
    return shares


def brier_per_push(data: TrustData, predicted: np.ndarray) -> np.ndarray:
    """(n,) float, each push's multi-class Brier score of ``predicted`` ((N,) float per bucket)."""
    return np.bincount(data.bucket_push, (predicted - data.observed) ** 2, len(data.objects))


def predictions(data: TrustData, shares: np.ndarray) -> dict[str, np.ndarray]:
    """Per bucket: the rows as they are, with the trust, with the prior landing alone (every share
    1), never topples, and a constant rate (the log's) landing by the prior."""
    topple = float(np.mean(1.0 - data.observed[data.stay]))
    return {"rows": data.row,
            "trust": data.row + data.terms @ shares,
            "prior_landing": data.row + data.terms @ np.ones(data.terms.shape[1]),
            "never_topples": data.stay.astype(float),
            "constant_rate": np.where(data.stay, 1.0 - topple, topple * data.prior)}


def out_of_fold(data: TrustData, folds: list[list[str]]) -> dict:
    """The shares fitted on all folds but one and scored on it, every fold in turn."""
    fold = fold_of_pushes(list(data.objects), folds)
    trust = np.empty(len(data.row))
    per_fold = []
    bucket_fold = fold[data.bucket_push]
    for k in range(len(folds)):
        if not (fold == k).any():
            continue
        shares = fit_shares(data, fold != k)
        mine = bucket_fold == k
        trust[mine] = (data.row + data.terms @ shares)[mine]
        per_fold.append({"fold": k, "pushes": int((fold == k).sum()), "shares": shares.tolist()})
    scores = {name: brier_per_push(data, predicted) for name, predicted in predictions(data, np.zeros(len(BANDS) + 1)).items()
              if name != "trust"}
    scores["trust_out_of_fold"] = brier_per_push(data, trust)
    weight = np.ones(len(data.objects))
    return {"folds": per_fold,
            "brier": {name: float(s.mean()) for name, s in scores.items()},
            "trust_minus_rows": float((scores["trust_out_of_fold"] - scores["rows"]).mean()),
            "trust_minus_rows_interval": paired_interval(scores["trust_out_of_fold"] - scores["rows"], weight, data.objects),
            "prior_landing_minus_rows": float((scores["prior_landing"] - scores["rows"]).mean()),
            "prior_landing_minus_rows_interval": paired_interval(scores["prior_landing"] - scores["rows"], weight, data.objects)}


def band_summary(data: TrustData) -> list[dict]:
    """Per band: the landing mass the rows put on its poses, summed over pushes, the mass physics put
    there, and the pushes whose rows land there."""
    out = []
    for b in range(len(BANDS) + 1):
        on = data.band == b
        out.append({"band": b, "predicted_mass": float(data.row[on].sum()), "observed_mass": float(data.observed[on].sum()),
                    "pushes": len(np.unique(data.bucket_push[on & (data.row > 0)]))})
    return out


def study(logs: list[str], dataset_roots: list[Path], folds_dir: Path | None, config: Config,
          shares: list[float] | None = None) -> dict:
    """The shares fitted on the logs (``shares`` None) or the given ones scored on them: the next-pose
    Brier score of each predictor at those shares (in sample when fitted), the trust minus the rows
    with its interval over objects, and with ``folds_dir`` the fit out of fold."""
    if shares is not None:
        try:
            shares = checked_shares(shares)
        except ValueError as err:
            raise TrustError(str(err)) from None
        if folds_dir is not None:
            raise TrustError("given shares are scored as they are; --folds fits them, so give one or the other")
    folds = None if folds_dir is None else read_fold_lists(folds_dir)  # a bad list before minutes of reading
    datasets = object_datasets(dataset_roots)
    log = read_log(logs, config)
    data = trust_data(log, datasets)
    fitted = shares is None
    shares = fit_shares(data) if fitted else shares
    scores = {name: brier_per_push(data, p) for name, p in predictions(data, shares).items()}
    difference = scores["trust"] - scores["rows"]
    result = {"logs": logs, "datasets": [str(r) for r in dataset_roots], "bands": list(BANDS),
              "pushes": len(data.objects), "objects": len(np.unique(data.objects)), "plays": int(data.plays.sum()),
              "rejected_pushes": dict(data.rejected), "log_rejected_rows": dict(log.rejected),
              "shares": shares.tolist(), "shares_fitted": fitted, "by_band": band_summary(data),
              "brier": {name: float(s.mean()) for name, s in scores.items()},
              "trust_minus_rows": float(difference.mean()),
              "trust_minus_rows_interval": paired_interval(difference, np.ones(len(difference)), data.objects)}
    if folds is not None:
        result["out_of_fold"] = out_of_fold(data, folds)
    return result


def text(result: dict) -> str:
    lines = [f"{result['pushes']} pushes ({result['plays']} plays) on {result['objects']} objects; rejected {result['rejected_pushes']}",
             "untrusted share per band (drop probability <= " + ", ".join(f"{b}" for b in result["bands"]) + ", above): "
             + ", ".join(f"{s:.3f}" for s in result["shares"]),
             f"next-pose Brier ({'in sample, the shares fitted here' if result['shares_fitted'] else 'the shares given'}): "
             + ", ".join(f"{k} {v:.4f}" for k, v in result["brier"].items()),
             "trust minus rows {:+.4f} [{:+.4f}, {:+.4f}] (95 % over objects)".format(result["trust_minus_rows"],
                                                                                   *result["trust_minus_rows_interval"])]
    for band in result["by_band"]:
        lines.append(f"  band {band['band']}: {band['pushes']} pushes, landing mass predicted {band['predicted_mass']:.1f}, "
                     f"observed there {band['observed_mass']:.1f}")
    oof = result.get("out_of_fold")
    if oof:
        lines.append("out of fold, next-pose Brier: " + ", ".join(f"{k} {v:.4f}" for k, v in oof["brier"].items()))
        low, high = oof["trust_minus_rows_interval"]
        lines.append(f"trust minus rows {oof['trust_minus_rows']:+.4f} [{low:+.4f}, {high:+.4f}] (95 % over objects)")
        low, high = oof["prior_landing_minus_rows_interval"]
        lines.append(f"prior landing minus rows {oof['prior_landing_minus_rows']:+.4f} [{low:+.4f}, {high:+.4f}]")
        for f in oof["folds"]:
            lines.append(f"  fold {f['fold']} ({f['pushes']} pushes): shares " + ", ".join(f"{s:.3f}" for s in f["shares"]))
    return "\n".join(lines)


def planner_log_arguments(parser: argparse.ArgumentParser) -> None:
    """The inputs of a study that reads planner logs against the datasets their pushes came from."""
    parser.add_argument("logs", nargs="+", help="push logs whose push ids name dataset pushes (oracle_policy --log)")
    parser.add_argument("--datasets", nargs="+", type=Path, required=True, help="the datasets the logs' pushes were drawn from")


def main(argv: list[str] | None = None) -> int:
    from ..cli import print_and_record

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.landing_trust", description=__doc__.split("\n\n")[0])
    planner_log_arguments(parser)
    parser.add_argument("--folds", type=Path, help="a --fold-maps directory: also fit and score out of fold")
    parser.add_argument("--shares", type=float, nargs=len(BANDS) + 1, metavar="U",
                        help="score these untrusted shares (one per band) instead of fitting them, e.g. on objects they were not fitted on")
    parser.add_argument("--json", type=Path, help="write the result here")
    args = parser.parse_args(argv)
    try:
        result = study(args.logs, args.datasets, args.folds, Config(), args.shares)
    except (TrustError, LogError, RecalibrationError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    return print_and_record(text(result), result, args.json)


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
