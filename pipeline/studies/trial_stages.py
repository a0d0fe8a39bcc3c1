"""Where the model says no: the stage of C.2's balance at which each trial of a logged push is decided.

The default's rows predict topples too rarely on shapes that roll (the parts, rolling and household sets,
docs/VALIDATION.md). Which of the model's conditions stops those trials decides what a correction must change:
the finger's friction (C.2), the table's grip, the finger's force limit (C.1), the path to the apex (C.14). This
study replays every logged push's trials exactly as the engine draws them (the scorer's noise streams, candidate
set and probes) and counts, per push, the share of its trials that ends at each of ``topple.TRIAL_STAGES``:

    python -m pipeline.studies.trial_stages data/logs/corpus data/logs/rolling --json F.json [--table F.csv] \
        [--config FILE.toml] [--set SECTION.KEY=VALUE ...]

The summary is per log and push direction (from above, the side, below, as ``landing_direction`` splits them),
and within each, apart for the pushes that toppled in most of physics' repeats and those that did not: where the
model stops the pushes physics topples is what it gets wrong. The shares of the last stages (``TOPPLING``) are
the trials ``trial_outcomes`` topples, before the neighbourhood mean (C.12) and the maps (C.7, C.15, C.16, C.19)
that make the served P(topple), which is reported beside them. A diagnosis, not a judgement: read it on tuning
logs (the corpus's, the rolling set's) before a correction is built.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from ..build.atomic import write_json_atomic, write_text_atomic
from ..build.corpus import DEFAULT_LIST, read_list
from ..model.config import Config, ToppleConfig
from ..model.landing_direction import CLASSES, direction_classes
from ..model.topple import TRIAL_STAGES, trial_stages
from .logreader import read_log
from .scoring import Group, Scorer
from .validation import config_from_args, to_json

TOPPLED = 0.5
"""A push counts as toppling in physics when at least this share of its repeats toppled."""
TOPPLING = TRIAL_STAGES[TRIAL_STAGES.index("tips"):]
"""The stages of the trials ``trial_outcomes`` topples: by C.2, the carried finger (C.23) or the stuck finger (C.11)."""


def group_stages(scorer: Scorer, group: Group, topple: ToppleConfig) -> np.ndarray:
    """The share of each logged push's trials ending at each stage, the engine's trials for ``scorer``
    (``Scorer.logged_trials``).

    returns : (pushes, len(TRIAL_STAGES)) float, rows summing to 1; NaN for a logged push that is not ``ok``
      (blocked: the engine evaluates no trial of it)
    """
    trials, edges, evaluated = scorer.logged_trials(group, topple)
    mass = scorer.log.objects[group.object_id].model.mass
    stages = trial_stages(trials, edges, mass, topple).reshape(len(group.rows), -1)  # (pushes, T)
    shares = (stages[:, :, None] == np.arange(len(TRIAL_STAGES))).mean(axis=1)
    shares[~evaluated] = np.nan
    return shares


def push_table(path: str, config: Config) -> pd.DataFrame:
    """One row per logged push of the log(s) at ``path`` (several joined by commas are read as one): its
    object, start pose, u_z, direction class, physics' topple rate and repeats, the served P(topple), and
    the share of its trials at each stage (one column per ``TRIAL_STAGES`` name)."""
    log = read_log(path.split(","), config, read_list(DEFAULT_LIST, config.mesh.default_mass))
    scorer = Scorer(log, config.seed, config.contacts)
    served = np.full(len(scorer), np.nan)
    shares = np.full((len(scorer), len(TRIAL_STAGES)), np.nan)
    u_z = np.full(len(scorer), np.nan)
    pose = np.zeros(len(scorer), dtype=int)
    for group, (_, p_topple) in zip(scorer.groups, scorer.predict(config.topple)):
        served[group.rows] = p_topple
        shares[group.rows] = group_stages(scorer, group, config.topple)
        u_z[group.rows] = group.actions.directions[:, 2]
        pose[group.rows] = group.pose.index
    table = pd.DataFrame({"log": path, "object_id": np.asarray(scorer.object_ids)[scorer.object_index], "start_pose": pose,
                          "u_z": u_z, "direction": np.asarray(CLASSES)[direction_classes(u_z)],
                          "physics": scorer.empirical_topple, "repeats": scorer.repeats, "served_p": served})
    for k, name in enumerate(TRIAL_STAGES):
        table[name] = shares[:, k]
    return table


def summarise(table: pd.DataFrame) -> dict:
    """Per log and direction: pushes, objects, physics' rate, the served P, the model's trial share that
    topples, and the mean share of each stage, over all its evaluated pushes and apart for those that
    toppled in physics (rate >= ``TOPPLED``) and those that did not."""
    table = table[table[list(TRIAL_STAGES)].notna().all(axis=1)]

    def block(rows: pd.DataFrame) -> dict:
        out = {"pushes": len(rows), "objects": int(rows.object_id.nunique()), "physics": rows.physics.mean(),
               "served_p": rows.served_p.mean(), "model_trials_topple": rows[list(TOPPLING)].sum(axis=1).mean()}
        out["stages"] = {name: rows[name].mean() for name in TRIAL_STAGES}
        return out

    summary: dict = {}
    for log, of_log in table.groupby("log", sort=False):
        summary[log] = {}
        for direction in CLASSES:
            rows = of_log[of_log.direction == direction]
            if len(rows) == 0:
                continue
            toppled = rows.physics >= TOPPLED
            summary[log][direction] = {"all": block(rows), "toppled_in_physics": block(rows[toppled]),
                                       "stayed_in_physics": block(rows[~toppled])}
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.trial_stages", description=__doc__.split("\n")[0])
    parser.add_argument("logs", nargs="+", help="push logs, each read alone (several joined by commas are read as one)")
    parser.add_argument("--json", type=Path, required=True, help="the summary, per log and push direction")
    parser.add_argument("--table", type=Path, help="every push's row (CSV)")
    parser.add_argument("--config", metavar="FILE.toml", help="model parameters (default: the dataset's defaults)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override one parameter, e.g. --set topple.corrections=...,carried_finger (repeatable)")
    args = parser.parse_args(argv)
    config = config_from_args(argparse.Namespace(config=args.config, overrides=args.overrides, seed=None))
    if "finger_friction" not in config.topple.applied_corrections:
        parser.error("the stages are C.2's: the model must be the corrected variant with finger_friction")
    table = pd.concat([push_table(path, config) for path in args.logs], ignore_index=True)
    summary = summarise(table)
    write_json_atomic(args.json, to_json({"stages": list(TRIAL_STAGES), "toppled_at": TOPPLED,
                                          "corrections": sorted(config.topple.applied_corrections), "by_log": summary}))
    if args.table is not None:
        write_text_atomic(args.table, table.to_csv(index=False))
    for log, directions in summary.items():
        for direction, blocks in directions.items():
            for name, b in blocks.items():
                stages = ", ".join(f"{s} {b['stages'][s]:.2f}" for s in TRIAL_STAGES if b["stages"][s] >= 0.005)
                print(f"{log} {direction} {name}: {b['pushes']} pushes, physics {b['physics']:.2f}, served "
                      f"{b['served_p']:.2f}, trials {b['model_trials_topple']:.2f}; {stages}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
