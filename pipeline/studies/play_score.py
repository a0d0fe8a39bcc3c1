"""Score traced plays against two datasets' rows: which says better where the played pushes came to rest.

``push_course --plays`` records, for each play, the start pose, the push (its action index in the dataset it was
planned on) and the pose it came to rest in.  Two datasets of the same objects and candidates (the default and a
variant built with ``--set``) give each push a row P(x' | x, u); each play is scored by the next-pose Brier score
of its row, the sum over the pose set and outside of (P - observed)^2 (the start pose when it stayed, as ``toppledb
report`` scores a push), and the variant's minus the base's is averaged by push direction with trials clustered by
object:

    python -m pipeline.studies.play_score BASE VARIANT PLAYS.jsonl [PLAYS.jsonl ...] [--json F]

Each plays file is read against the dataset directories BASE and VARIANT as given, or, with ``{set}`` in them,
against the set named by the plays file's ``H_<set>.jsonl`` stem (``data/heldout_sa_{set}``).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from .candidate_choice import CLASSES
from .pooled_gain import clustered_entry
from .push_course import landing_given_topple
from .scoring import brier_score


def brier(row: np.ndarray, landed: int) -> float:
    """Next-pose Brier score of one play: row (P,) float, P(x' | x, u) over the pose set (the rest, 1 - sum, is
    outside it); landed : the pose it came to rest in, -1 outside the pose set."""
    row = np.nan_to_num(np.asarray(row, dtype=float))
    observed = np.zeros(len(row) + 1)
    observed[landed if landed >= 0 else len(row)] = 1.0
    predicted = np.append(row, max(0.0, 1.0 - row.sum()))
    return float(brier_score(predicted[None], observed[None])[0])


def scored(plays: list[dict], base_rows, variant_rows) -> dict:
    """By direction class: each dataset's mean Brier over the plays and the variant's minus the base's, clustered by
    object.  base_rows, variant_rows : (object_id, pose, action) -> (P,) float row"""
    out = {}
    for name in CLASSES:
        mine = [p for p in plays if p["direction"] == name and p["kind"] != "no contact"]
        if not mine:
            continue
        keys = [(p["object_id"], p["pose"], p["action"]) for p in mine]
        base = np.array([brier(base_rows(*k), p["landed"]) for k, p in zip(keys, mine)])
        variant = np.array([brier(variant_rows(*k), p["landed"]) for k, p in zip(keys, mine)])
        objects = [p["object_id"] for p in mine]
        out[name] = {"base": clustered_entry(base, objects, "plays"), "variant": clustered_entry(variant, objects, "plays"),
                     "variant_minus_base": clustered_entry(variant - base, objects, "plays")}
        # The topples that came to rest in another pose of the set: each row's probability of it given a topple.
        moved = [(k, p) for k, p in zip(keys, mine) if 0 <= p["landed"] != p["pose"]]
        if moved:
            of = [p["object_id"] for _, p in moved]
            out[name]["landing_given_topple"] = {
                label: clustered_entry([landing_given_topple(rows(*k), p["pose"], p["landed"]) for k, p in moved], of, "topples")
                for label, rows in (("base", base_rows), ("variant", variant_rows))}
    return out


def dataset_rows(root: str | Path):
    """(object_id, pose, action) -> (P,) row of the dataset at ``root``, one object's rows read at a time."""
    from schema.reader import Dataset

    from .landing_trust import pose_columns
    from .robust_policy import next_pose_rows

    dataset = Dataset.open(root)
    n_actions = {o: c["n_actions"].tolist() for o, c in pose_columns(dataset, ["n_actions"]).items()}
    cache: dict[str, list[np.ndarray]] = {}

    def row(object_id: str, pose: int, action: int) -> np.ndarray:
        if object_id not in cache:
            if object_id not in n_actions:
                raise ValueError(f"{root} has no object {object_id}")
            cache.clear()  # the plays come object by object
            cache[object_id] = next_pose_rows(dataset, object_id, n_actions[object_id])
        return cache[object_id][pose][action]

    return row


def main(argv: list[str] | None = None) -> int:
    from ..cli import print_and_record, refused_outputs

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.play_score", description=__doc__.split("\n\n")[0])
    parser.add_argument("base", help="the base dataset directory ({set}: the plays file's set)")
    parser.add_argument("variant", help="the variant's dataset directory, the same objects and candidates")
    parser.add_argument("plays", nargs="+", type=Path, help="push_course --plays files")
    parser.add_argument("--json", type=Path, help="write the result here")
    args = parser.parse_args(argv)
    if refused_outputs(args.json):
        return 2
    plays, result = [], {}
    try:
        for path in args.plays:
            here = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
            name = path.stem.split("_")[-1]
            base, variant = dataset_rows(args.base.format(set=name)), dataset_rows(args.variant.format(set=name))
            plays.append((here, base, variant))
        pooled = [p for here, _, _ in plays for p in here]
        rows = {}
        for here, base, variant in plays:
            for key in sorted({(p["object_id"], p["pose"], p["action"]) for p in here}):  # object by object: one read each
                rows[key] = (base(*key), variant(*key))
        result = {"base": args.base, "variant": args.variant, "plays": len(pooled), "files": [str(p) for p in args.plays],
                  "by_direction": scored(pooled, lambda *k: rows[k][0], lambda *k: rows[k][1])}
    except (OSError, ValueError, KeyError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    lines = [f"{result['plays']} plays; next-pose Brier, {args.variant} against {args.base} (clustered by object):"]
    for name, entry in result["by_direction"].items():
        d = entry["variant_minus_base"]
        se = "" if d["se"] is None else f" +/- {d['se']:.4f}"
        lines.append(f"  from {name}: {d['plays']} plays on {d['objects']} objects, base {entry['base']['mean']:.4f}, "
                     f"variant {entry['variant']['mean']:.4f}, difference {d['mean']:+.4f}{se}")
        if "landing_given_topple" in entry:
            g = entry["landing_given_topple"]
            lines.append(f"    the landed pose given a topple ({g['base']['topples']} topples): base {g['base']['mean']:.3f}, "
                         f"variant {g['variant']['mean']:.3f}")
    return print_and_record("\n".join(lines), result, args.json)


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
