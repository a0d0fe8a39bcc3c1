"""Calibration of the model's noise parameters from observed pushes (thesis 4.4.2).

The thesis reached its table 4.3 numbers after a sweep over 100 noise settings with
6-fold cross-validation.  This module searches the seven noise parameters of
``ToppleConfig`` (``BOUNDS``; reasons in docs/VALIDATION.md, "Calibration"):

1. a scrambled Sobol sequence over the bounds (data independent, shared by all folds),
   plus the current defaults as one more candidate;
2. two rounds of local refinement: Gaussian steps (10 %, then 4 % of each range)
   around the best few candidates *of each selection problem*.

A selection problem is one cross-validation fold's training objects (the folds are
grouped by object: an object's pushes are all in one fold), or all objects for the
final choice.  Each fold chooses its setting on its training objects only and reports
it on its held-out objects; the final setting is chosen on all objects and written as
a config TOML (``toppledb dataset --config FILE``).  Objective (``OBJECTIVE_NAMES``): the
mean multi-class Brier score of the calibrated variant (the configuration's by default) over all pushes,
the proper score the default model is chosen by; ``--objective informative`` is the thesis's
sup-TV over the informative pushes, ``--objective all`` sup-TV over all pushes.

Scoring a setting predicts every push of the log once (``scoring.Scorer``); the folds
only aggregate per-push results, so a setting is never scored twice.  Settings are
scored on all cores (joblib; each worker loads the prepared log once).

    toppledb calibrate data/logs/calibration --folds 6 --settings 100 --seed 0 \\
        --heldout data/logs/heldout --out reports/calibrated.toml
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import sys
import tempfile
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
from scipy.stats import qmc

from ..build.atomic import write_text_atomic
from ..model.config import NO_MAP, VARIANTS, Config, ToppleConfig
from .logreader import LogError, PushLog, read_log
from .scoring import Scorer, Scores
from .validation import NOISE_KEYS, bootstrap_difference, informative, observed_topple_rate, push_metrics, report, to_json


@dataclass(frozen=True)
class Bound:
    low: float
    high: float
    reason: str


BOUNDS: dict[str, Bound] = {
    "mu_table_mean": Bound(0.1, 1.0, "tabletop materials from teflon-like (0.1) to rubber on wood (1.0)"),
    "mu_table_std": Bound(0.0, 0.3, "up to 0.3: a table whose friction varies across its surface by a third of its range"),
    "mu_finger_mean": Bound(0.0, 1.5, "a frictionless finger to a rubber tip (the thesis's 0.98 is inside)"),
    "mu_finger_std": Bound(0.0, 0.5, "up to half the mean's range, as the thesis's 0.2 spread of a 0.98 mean"),
    "contact_std": Bound(0.0, 0.005, "m; 0 to 5 mm of finger placement error, 10x the thesis's 0.5 mm"),
    "direction_std": Bound(0.0, 0.3, "0 to about 17 degrees of push-direction error (thesis 0.055)"),
    "rotation_std": Bound(0.0, 0.4, "rad; 0 to 23 degrees of object orientation error (thesis 0.22)"),
    "finger_friction_scale": Bound(0.0, 1.0, "corrected variant only: no finger friction in the tipping balance (0) to Coulomb's law (1)"),
}
"""Search range of every searchable parameter (the noise, and the corrected model's k, which
``--params`` must name); docs/VALIDATION.md gives the reasons."""
SOBOL_SHARE = 0.64
"""Share of the settings drawn quasi-randomly; the rest refine locally."""
REFINE_RADII = (0.10, 0.04)
"""Step standard deviation of each refinement round, as a fraction of each parameter's range."""
REFINE_CENTRES = 4
"""Best candidates of a selection problem that a refinement round steps around."""
OBJECTIVE_NAMES = {"informative": "mean sup-TV over informative pushes", "all": "mean sup-TV over all pushes",
                   "brier": "mean multi-class Brier score over all pushes"}
"""What a setting is chosen by: mean sup-TV over informative pushes (the thesis's form, which
rewards small probabilities on pushes that stay: docs/VALIDATION.md "Reading informative TV"),
over all pushes (which rewards sharp predictions), or the mean multi-class Brier score (a
proper score: least for the true probabilities)."""
OBJECTIVES = tuple(OBJECTIVE_NAMES)


class CalibrationError(ValueError):
    """Calibration cannot run (too few objects for the folds, ...); one line."""


# ---------------------------------------------------------------- folds and settings


def grouped_folds(pushes_per_object: dict[str, int], k: int, seed: int) -> list[list[str]]:
    """Split objects into ``k`` folds: a seeded shuffle, then each object to the fold with the
    fewest pushes so far (folds of similar size; an object is in exactly one fold).

    returns : k lists of object ids
    """
    names = sorted(pushes_per_object)
    if k < 2:
        raise CalibrationError(f"cross-validation needs at least 2 folds, got {k}")
    if len(names) < k:
        raise CalibrationError(_too_few_objects(len(names), k))
    order = np.random.default_rng(seed).permutation(len(names))
    folds: list[list[str]] = [[] for _ in range(k)]
    load = np.zeros(k)
    for i in order:
        f = int(np.argmin(load))
        folds[f].append(names[i])
        load[f] += pushes_per_object[names[i]]
    return [sorted(f) for f in folds]


def _too_few_objects(objects: int, k: int) -> str:
    """Why ``objects`` cannot fill ``k`` folds grouped by object, and what would: each fold holds
    whole objects, so k folds need k objects, and cross-validation at least 2 folds.  A fold count
    is suggested only when one can work (never "--folds 2" to a log of one object)."""
    have = f"{k} folds grouped by object need at least {k} objects; the pushes are of {objects} object{'s' if objects != 1 else ''}"
    if objects < 2:
        return f"{have}, and cross-validation holds out whole objects: log pushes of at least 2 objects"
    fewer = "--folds 2" if objects == 2 else f"--folds {objects} or fewer"
    return f"{have}: use {fewer}, or log pushes of more objects"


def settings_plan(total: int) -> tuple[int, tuple[int, ...]]:
    """(quasi-random settings, settings per refinement round) for ``total`` settings per problem."""
    if total < 4:
        raise CalibrationError(f"--settings must be at least 4, got {total}")
    n_sobol = 2 ** math.floor(math.log2(SOBOL_SHARE * total))
    rest = total - n_sobol
    first = rest - rest // 2
    return n_sobol, (first, rest - first)


def sobol_settings(n: int, params: tuple[str, ...], seed: int) -> np.ndarray:
    """``n`` (a power of two) scrambled Sobol points scaled to the bounds: (n, len(params))."""
    unit = qmc.Sobol(len(params), scramble=True, seed=seed).random_base2(round(math.log2(n)))
    low, high = _bounds(params)
    return low + unit * (high - low)


def refine(centres: np.ndarray, n: int, radius: float, params: tuple[str, ...], rng: np.random.Generator) -> np.ndarray:
    """``n`` Gaussian steps around ``centres`` (taken in turn), clipped to the bounds: (n, len(params))."""
    low, high = _bounds(params)
    base = centres[np.arange(n) % len(centres)]
    return np.clip(base + rng.normal(0.0, radius, base.shape) * (high - low), low, high)


def _bounds(params: tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    return np.array([BOUNDS[p].low for p in params]), np.array([BOUNDS[p].high for p in params])


def with_values(topple: ToppleConfig, params: tuple[str, ...], values: np.ndarray) -> ToppleConfig:
    return replace(topple, **{p: float(v) for p, v in zip(params, values)})


def objective(
    tv: np.ndarray, predicted: np.ndarray, observed: np.ndarray, kind: str = "informative", brier: np.ndarray | None = None
) -> float:
    """Mean sup-TV over informative pushes (``kind='informative'``) or all pushes (``'all'``), or
    the mean Brier score (``'brier'``, which needs ``brier``: (n,) float per push)."""
    if kind == "brier":
        return float(np.mean(brier))
    if kind == "all":
        return float(np.mean(tv))
    useful = informative(predicted, observed)
    return float(np.mean(tv[useful])) if useful.any() else 0.0


# ---------------------------------------------------------------- scoring many settings

_WORKER_SCORERS: dict[str, Scorer] = {}
"""Per worker process: prepared logs by pickle path, loaded on a worker's first task."""


def _score_items(scorer: Scorer | str, base: ToppleConfig, params: tuple[str, ...], items) -> list[Scores]:
    if isinstance(scorer, str):
        if scorer not in _WORKER_SCORERS:
            with open(scorer, "rb") as f:
                _WORKER_SCORERS[scorer] = pickle.load(f)
        scorer = _WORKER_SCORERS[scorer]
    out = []
    for variant, values in items:
        out.append(scorer.score(replace(with_values(base, params, values), variant=variant)))
    return out


class Evaluator:
    """Scores (variant, parameter values) items against one prepared log, on ``workers`` processes."""

    def __init__(self, scorer: Scorer, base: ToppleConfig, params: tuple[str, ...], workers: int, progress: bool) -> None:
        self.scorer, self.base, self.params, self.workers, self.progress = scorer, base, params, workers, progress
        self.evaluated = 0
        self._dir = None
        self._path = None
        if workers > 1:
            # Before any scoring: the pickle then carries no ray-tracer caches.
            self._dir = tempfile.TemporaryDirectory(prefix="toppledb-calibrate-")
            self._path = os.path.join(self._dir.name, "scorer.pkl")
            with open(self._path, "wb") as f:
                pickle.dump(scorer, f, protocol=pickle.HIGHEST_PROTOCOL)

    def close(self) -> None:
        if self._dir is not None:
            self._dir.cleanup()

    def __call__(self, items: list[tuple[str, np.ndarray]], label: str) -> list[Scores]:
        from tqdm import tqdm

        bar = tqdm(total=len(items), desc=label, unit="setting", disable=not self.progress, file=sys.stderr, leave=True)
        results: list = []
        if self.workers <= 1:
            for item in items:
                results += _score_items(self.scorer, self.base, self.params, [item])
                bar.update(1)
        else:
            from joblib import Parallel, delayed

            chunk = max(1, min(4, len(items) // (4 * self.workers)))
            chunks = [items[i : i + chunk] for i in range(0, len(items), chunk)]
            jobs = (delayed(_score_items)(self._path, self.base, self.params, c) for c in chunks)
            for part in Parallel(n_jobs=self.workers, return_as="generator")(jobs):
                results += part
                bar.update(len(part))
        bar.close()
        self.evaluated += len(items)
        return results


# ---------------------------------------------------------------- calibration


@dataclass
class Problem:
    """One selection problem: choose a setting on ``rows`` (training pushes)."""

    name: str
    rows: np.ndarray
    candidates: list[int]


def calibrate(
    log: PushLog,
    config: Config = Config(),
    *,
    folds: int = 6,
    settings: int = 100,
    seed: int = 0,
    params: tuple[str, ...] = NOISE_KEYS,
    variant: str | None = None,
    kind: str = "brier",
    workers: int = 1,
    progress: bool = False,
) -> dict:
    """Search the noise parameters on ``log`` with object-grouped k-fold cross-validation.

    config : the base model (its non-searched parameters and ``seed`` are kept)
    variant : the variant whose objective is minimised (default: the configuration's)
    settings : candidates each selection problem chooses among (Sobol + refinement; plus the defaults)
    returns : a JSON-ready dict: folds (objects, chosen values, training objective, held-out
      metrics per variant for the chosen and the base setting), pooled held-out metrics,
      the final chosen values (all objects), settings scored, timings
    """
    if kind not in OBJECTIVES:
        raise CalibrationError(f"unknown objective {kind!r}; choose one of {', '.join(OBJECTIVES)}")
    unknown = sorted(set(params) - set(BOUNDS))
    if unknown:
        raise CalibrationError(f"cannot calibrate {', '.join(unknown)}; searchable: {', '.join(BOUNDS)}")
    timings: dict[str, float] = {}
    started = time.perf_counter()
    scorer = Scorer(log, config.seed, config.contacts)
    timings["prepare_s"] = time.perf_counter() - started
    # The noise is searched on the counted probabilities: the smoothing (MODEL.md C.12) would
    # cost a whole pose's candidates per logged pose, and the recalibration (C.7) is fitted
    # afterwards on the chosen noise (`toppledb recalibrate`), never the other way round.
    variant = variant or config.topple.variant
    base = replace(config.topple.counted(), variant=variant)
    observed = scorer.empirical_topple
    pushes_per_object = {name: int(np.sum(scorer.object_index == i)) for i, name in enumerate(scorer.object_ids)}
    fold_objects = grouped_folds(pushes_per_object, folds, seed)
    fold_of_push = np.empty(len(scorer), dtype=int)
    for f, names in enumerate(fold_objects):
        for name in names:
            fold_of_push[scorer.object_index == scorer.object_ids.index(name)] = f

    n_sobol, rounds = settings_plan(settings)
    rng = np.random.default_rng([seed, 1])
    values: list[np.ndarray] = []
    scored: list[Scores] = []  # per setting, every push
    evaluator = Evaluator(scorer, base, params, workers, progress)
    try:
        def run(batch: np.ndarray, label: str) -> list[int]:
            t = time.perf_counter()
            out = evaluator([(variant, v) for v in batch], label)
            timings[f"{label}_s"] = time.perf_counter() - t
            first = len(values)
            for v, scores in zip(batch, out):
                values.append(np.asarray(v, dtype=float))
                scored.append(scores)
            return list(range(first, len(values)))

        defaults = np.array([getattr(base, p) for p in params])
        shared = run(np.vstack([defaults[None], sobol_settings(n_sobol, params, seed)]), "sobol")
        problems = [Problem(f"fold {f}", np.flatnonzero(fold_of_push != f), list(shared)) for f in range(folds)]
        problems.append(Problem("all", np.arange(len(scorer)), list(shared)))

        def train_score(c: int, rows: np.ndarray) -> float:
            s = scored[c]
            return objective(s.tv[rows], s.p_topple[rows], observed[rows], kind, s.brier[rows])

        for r, (n_new, radius) in enumerate(zip(rounds, REFINE_RADII)):
            if n_new == 0:
                continue
            batch, owners = [], []
            for problem in problems:
                ranked = sorted(problem.candidates, key=lambda c: (train_score(c, problem.rows), c))
                centres = np.array([values[c] for c in ranked[:REFINE_CENTRES]])
                batch.append(refine(centres, n_new, radius, params, rng))
                owners.append(len(batch[-1]))
            added = run(np.vstack(batch), f"refine{r + 1}")
            start = 0
            for problem, n in zip(problems, owners):
                problem.candidates += added[start : start + n]
                start += n

        chosen = {p.name: min(p.candidates, key=lambda c: (train_score(c, p.rows), c)) for p in problems}

        # Every variant at each fold's chosen setting and at the base setting, held out.
        other = [v for v in VARIANTS if v != variant]
        items = [(v, defaults) for v in VARIANTS] + [(v, values[chosen[p.name]]) for p in problems[:-1] for v in other]
        t0 = time.perf_counter()
        extra = evaluator(items, "variants")
        timings["variants_s"] = time.perf_counter() - t0
    finally:
        evaluator.close()

    base_scores = dict(zip(VARIANTS, extra[: len(VARIANTS)]))
    fold_scores = {}
    position = len(VARIANTS)
    for problem in problems[:-1]:
        fold_scores[problem.name] = {variant: scored[chosen[problem.name]]}
        for v in other:
            fold_scores[problem.name][v] = extra[position]
            position += 1

    fold_reports = []
    pooled = {v: Scores(np.empty(len(scorer)), np.empty(len(scorer)), np.empty(len(scorer))) for v in VARIANTS}

    def metrics_on(scores: Scores, rows: np.ndarray) -> dict[str, float]:
        return push_metrics(scores.tv[rows], scores.p_topple[rows], observed[rows], scorer.object_index[rows], scores.brier[rows])

    for f, problem in enumerate(problems[:-1]):
        test = np.flatnonzero(fold_of_push == f)
        held_out = {}
        for v in VARIANTS:
            fold = fold_scores[problem.name][v]
            for name in ("tv", "p_topple", "brier"):
                getattr(pooled[v], name)[test] = getattr(fold, name)[test]
            held_out[v] = {"calibrated": metrics_on(fold, test), "base": metrics_on(base_scores[v], test)}
        c = chosen[problem.name]
        fold_reports.append({
            "fold": f,
            "objects": fold_objects[f],
            "pushes": len(test),
            "chosen": dict(zip(params, map(float, values[c]))),
            "chosen_is_base": c == shared[0],
            "train_objective": train_score(c, problem.rows),
            "train_objective_base": train_score(shared[0], problem.rows),
            "held_out": held_out,
        })
    everything = np.arange(len(scorer))
    # Calibrated minus base on the held-out folds, paired over the same resampled objects.
    difference = {
        v: bootstrap_difference(pooled[v], base_scores[v], observed, scorer.object_index, seed=seed) for v in VARIANTS
    }
    cross_validated = {
        v: {"calibrated": metrics_on(pooled[v], everything), "base": metrics_on(base_scores[v], everything)} for v in VARIANTS
    }
    final = chosen["all"]
    timings["total_s"] = time.perf_counter() - started
    return {
        "objective": f"{OBJECTIVE_NAMES[kind]}, variant {variant}",
        "objective_kind": kind,
        "variant": variant,
        "params": list(params),
        "bounds": {p: asdict(BOUNDS[p]) for p in params},
        "base": dict(zip(params, map(float, defaults))),
        "chosen": dict(zip(params, map(float, values[final]))),
        "chosen_objective": train_score(final, everything),
        "base_objective": train_score(shared[0], everything),
        "folds": fold_reports,
        "cross_validated": cross_validated,
        "cross_validated_difference": difference,
        "settings": {"per_problem": len(problems[-1].candidates), "scored": len(values), "sobol": n_sobol,
                     "refine_rounds": list(rounds), "variant_scorings": len(items)},
        "seed": seed,
        "counts": log.counts(),
        "timings": {k: round(v, 2) for k, v in timings.items()},
    }


# ---------------------------------------------------------------- output


def calibrated_config(base: Config, chosen: dict[str, float]) -> Config:
    return base.with_overrides({f"topple.{k}": v for k, v in chosen.items()})


def write_toml(path: str | Path, topple: dict[str, float | tuple[float, ...]], comments: list[str],
               mdp: dict[str, float] | None = None) -> None:
    """A config TOML holding only the given ``[topple]`` (and ``[mdp]``) keys (everything else stays default):
    every number exactly (repr), a sequence (recalibration knots) as a list of them, strings
    and booleans as TOML writes them.  Exactly,
    because knots fitted on a smoothed table (MODEL.md C.12) can differ in the 7th digit, and
    rounding them would make x no longer strictly increasing."""
    def value(v) -> str:
        if isinstance(v, (list, tuple)):
            return "[" + ", ".join(repr(float(x)) for x in v) + "]"
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return json.dumps(v)  # a TOML basic string
        if isinstance(v, int):
            return str(v)
        return repr(float(v))

    lines = [f"# {c}" for c in comments] + ["", "[topple]"]
    lines += [f"{key} = {value(v)}" for key, v in topple.items()]
    if mdp:
        lines += ["", "[mdp]"] + [f"{key} = {value(v)}" for key, v in mdp.items()]
    write_text_atomic(path, "\n".join(lines) + "\n")


def write_outputs(out: str | Path, topple: dict, comments: list[str], record: str | Path, result: dict,
                  mdp: dict | None = None) -> None:
    """The config TOML (checked by loading it, as ``toppledb dataset --config`` will) and the
    JSON record of a calibration command; prints where they are."""
    write_toml(out, topple, comments, mdp)
    Config.from_toml(out)
    write_text_atomic(record, json.dumps(to_json(result), indent=1, allow_nan=False) + "\n")
    print(f"config: {out}\nrecord: {record} ({result['wall_s']} s)")


def format_calibration(result: dict) -> str:
    def cell(value):
        return "  -  " if value is None or (isinstance(value, float) and math.isnan(value)) else f"{value:.3f}"

    lines = [(f"objective: {result['objective']}; {result['settings']['per_problem']} settings per fold, "
              f"{result['settings']['scored']} scored")]
    lines.append(f"{'fold':<6} {'objects':>7} {'pushes':>6} {'train base':>10} {'train cal':>9} "
                 f"{'held-out TVi base':>17} {'held-out TVi cal':>16}")
    v = result["variant"]
    for fold in result["folds"]:
        ho = fold["held_out"][v]
        lines.append(f"{fold['fold']:<6} {len(fold['objects']):>7} {fold['pushes']:>6} {cell(fold['train_objective_base']):>10} "
                     f"{cell(fold['train_objective']):>9} {cell(ho['base']['tv_informative']):>17} {cell(ho['calibrated']['tv_informative']):>16}")
    lines.append("cross-validated (held-out folds pooled):")
    lines.append(f"{'variant':<11} {'setting':<10} {'TV inform.':>10} {'TV all':>7} {'Brier':>6} {'AP':>6} {'mAP':>6} {'ECE':>6}")
    for variant, m in result["cross_validated"].items():
        for setting in ("base", "calibrated"):
            x = m[setting]
            lines.append(f"{variant:<11} {setting:<10} {cell(x['tv_informative']):>10} {cell(x['tv_all']):>7} "
                         f"{cell(x.get('brier')):>6} {cell(x['ap']):>6} {cell(x['map']):>6} {cell(x['ece']):>6}")
    lines.append("chosen (all objects): " + ", ".join(f"{k}={val:.4g}" for k, val in result["chosen"].items()))
    return "\n".join(lines)


def _changes(base: dict, calibrated: dict) -> str:
    """'informative sup-TV 0.333 -> 0.320, ...' for the TOML's comments."""
    names = (("tv_informative", "informative sup-TV"), ("tv_all", "sup-TV over all pushes"), ("brier", "Brier"))
    return ", ".join(f"{label} {base[key]:.3f} -> {calibrated[key]:.3f}" for key, label in names if key in base and key in calibrated)


def format_difference(label: str, difference: dict) -> str:
    """Calibrated minus base, per variant, with the paired bootstrap interval (negative: calibrated is better)."""
    lines = [f"calibrated - base, {label} (95 % paired bootstrap over objects; negative is better):"]
    for variant, d in difference.items():
        parts = [f"{key} {d[key]['difference']:+.3f} [{d[key]['ci'][0]:+.3f}, {d[key]['ci'][1]:+.3f}]"
                 for key in ("tv_informative", "tv_all", "brier") if key in d]
        lines.append(f"  {variant:<11} " + "   ".join(parts))
    return "\n".join(lines)


def bench(logs: list[str] | None, config: Config, pushes: int, repeats: int, seed: int) -> dict:
    """Time preparing a log and scoring one setting (the robust variant) on one core.

    logs : push logs to time; None: a model-made log of about ``pushes`` pushes on default-corpus objects
    """
    from ..build.corpus import load_corpus, pybullet_data_dir
    from .synthetic_log import MeshSpec, model_log

    generate_s = 0.0
    if logs:
        started = time.perf_counter()
        log = read_log(logs, config)
    else:
        import pyarrow.parquet as pq

        started = time.perf_counter()
        specs, per_pose = [], 10
        corpus = load_corpus("default", config.mesh.default_mass)
        # Corpus objects have about 11 usable poses: pushes / (11 * per_pose) objects.
        for spec in corpus.specs[: max(1, int(np.ceil(pushes / (11 * per_pose))))]:
            specs.append(MeshSpec(spec.object_id, os.path.relpath(spec.path, pybullet_data_dir()), spec.scale, spec.mass, "pybullet_data"))
        table = model_log(specs, config, pushes_per_pose=per_pose, repeats=repeats, seed=seed,
                          resolve=lambda source, path: str(pybullet_data_dir() / path))
        generate_s = time.perf_counter() - started
        with tempfile.TemporaryDirectory() as tmp:
            pq.write_table(table, f"{tmp}/bench.parquet")
            started = time.perf_counter()
            log = read_log([f"{tmp}/bench.parquet"], config)
    read_s = time.perf_counter() - started
    t = time.perf_counter()
    scorer = Scorer(log, config.seed, config.contacts)
    prepare_s = time.perf_counter() - t
    wall, cpu = [], []
    for _ in range(3):
        t, c = time.perf_counter(), time.process_time()
        scorer.score(config.topple)
        wall.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    n = len(scorer)
    # The first scoring also builds each mesh's ray structure; later settings reuse it.
    score_cpu = float(np.median(cpu[1:]))
    return {"pushes": n, "rows": log.rows, "objects": len(scorer.object_ids), "start_poses": len(scorer.groups),
            "trials": config.topple.n_trials, "generate_s": round(generate_s, 2), "read_s": round(read_s, 2),
            "prepare_s": round(prepare_s, 2), "score_first_wall_s": round(wall[0], 3),
            "score_wall_s": round(float(np.median(wall[1:])), 3), "score_cpu_s": round(score_cpu, 3),
            "score_cpu_s_per_5000_pushes": round(score_cpu * 5000 / max(n, 1), 3)}


def main(argv: list[str] | None = None) -> int:
    """``toppledb calibrate LOG...``: search the noise parameters, write a config TOML and a JSON record."""
    from ..build.corpus import CorpusError, load_corpus
    from ..cli import UsageError, refused_outputs
    from .validation import config_from_args, format_report

    parser = argparse.ArgumentParser(prog="toppledb calibrate", description=__doc__.split("\n\n")[0])
    parser.add_argument("logs", nargs="*", help="calibration push logs (Parquet files or directories) on corpus objects")
    parser.add_argument("--folds", type=int, default=6, help="cross-validation folds, grouped by object (default: %(default)s)")
    parser.add_argument("--settings", type=int, default=100, help="candidate settings per selection problem (default: %(default)s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the search, the folds and the model's trials (default: %(default)s)")
    parser.add_argument("--params", nargs="+", choices=list(BOUNDS), default=list(NOISE_KEYS),
                        help="parameters to search (default: the seven noise parameters)")
    parser.add_argument("--variant", choices=VARIANTS, default=None,
                        help="variant whose objective is minimised (default: the configuration's, `corrected` unless --config says otherwise)")
    parser.add_argument("--objective", choices=OBJECTIVES, default="brier", help="what a setting is chosen by: the Brier score (the default model's rule), or mean sup-TV over informative or all pushes (OBJECTIVE_NAMES; default: %(default)s)")
    parser.add_argument("--corpus", default="default", help="calibrate only on this corpus's objects ('none': any object; default: %(default)s)")
    parser.add_argument("--heldout", nargs="+", metavar="LOG", help="score the chosen setting once more on this log (objects outside the corpus)")
    parser.add_argument("--config", type=Path, metavar="FILE.toml", help="base parameters (default: the dataset's defaults; --config thesis for the thesis's)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--workers", type=int, default=os.cpu_count() or 1, help="processes scoring settings (default: all cores)")
    parser.add_argument("--out", type=Path, default=Path("data/reports/calibrated.toml"), help="config TOML to write (default: %(default)s)")
    parser.add_argument("--json", type=Path, default=Path("data/reports/calibration.json"), help="full record (default: %(default)s)")
    parser.add_argument("--bootstrap", type=int, default=1000, help="bootstrap resamples of the held-out report (default: %(default)s)")
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--bench", action="store_true", help="only time scoring one setting (on LOG, or on a model-made log)")
    parser.add_argument("--bench-pushes", type=int, default=5000, help="pushes of the model-made bench log (default: %(default)s)")
    args = parser.parse_args(argv)
    if not args.bench and refused_outputs(args.out, args.json):  # --bench writes neither
        return 2

    try:
        config = config_from_args(args)
        # As in ``calibrate``: the base, the chosen setting and the held-out report are the
        # counted model, neither smoothed (MODEL.md C.12) nor recalibrated (C.7); the written
        # TOML holds the noise and an identity map (the default's map was fitted for the default
        # noise), so a dataset built with it smooths as the defaults say and maps nothing.
        config = replace(config, topple=config.topple.counted())
        if args.bench:
            print(json.dumps(bench(args.logs, config, args.bench_pushes, 10, args.seed)))
            return 0
        if not args.logs:
            raise UsageError("give at least one calibration log")
        corpus = None if args.corpus == "none" else load_corpus(args.corpus, config.mesh.default_mass)
        log = read_log(args.logs, config, corpus, corpus_only=corpus is not None)
        if not log.pushes:
            raise UsageError(f"no usable pushes in {' '.join(args.logs)} ({log.rows} rows; rejected: {dict(log.rejected)})")
        heldout = read_log(args.heldout, config, corpus, exclude_corpus=corpus is not None) if args.heldout else None
        if heldout is not None and not heldout.pushes:
            raise UsageError(f"no usable pushes in the held-out log ({heldout.rows} rows; rejected: {dict(heldout.rejected)})")
        started = time.perf_counter()
        result = calibrate(log, config, folds=args.folds, settings=args.settings, seed=args.seed, params=tuple(args.params),
                           variant=args.variant, kind=args.objective, workers=args.workers, progress=not args.no_progress)
    except (UsageError, CorpusError, LogError, CalibrationError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    print(format_calibration(result))
    print(format_difference("held-out folds", result["cross_validated_difference"]))
    calibrated = calibrated_config(config, result["chosen"])
    if heldout is not None:
        rate = observed_topple_rate(log)
        result["heldout"] = {}
        held_scorer = Scorer(heldout, config.seed, config.contacts)
        for name, cfg in (("base", config), ("calibrated", calibrated)):
            r = report(heldout, cfg, VARIANTS, rate=rate, rate_source="calibration log", n_resamples=args.bootstrap,
                       seed=args.seed, scorer=held_scorer)
            result["heldout"][name] = {k: r[k] for k in ("counts", "variants", "references", "worst_objects", "topple")}
            print(f"held-out log, {name} setting:")
            print(format_report(r))
        result["heldout"]["difference"] = {
            v: bootstrap_difference(held_scorer.score_variant(calibrated.topple, v), held_scorer.score_variant(config.topple, v),
                                    held_scorer.empirical_topple, held_scorer.object_index, seed=args.seed)
            for v in VARIANTS
        }
        print(format_difference("held-out log", result["heldout"]["difference"]))
    result["wall_s"] = round(time.perf_counter() - started, 1)
    variant = result["variant"]  # --variant, or the configuration's
    comments = [
        "toppledb calibrate: noise parameters chosen on push logs (docs/VALIDATION.md, Calibration)",
        f"logs: {' '.join(args.logs)}; {result['counts']['pushes']} pushes on {result['counts']['objects']} objects",
        (f"objective: {result['objective']}; {args.folds}-fold CV grouped by object, "
         f"{result['settings']['per_problem']} settings per fold, seed {args.seed}"),
        "cross-validated {v}, base -> calibrated: {m}".format(
            v=variant, m=_changes(result["cross_validated"][variant]["base"], result["cross_validated"][variant]["calibrated"])),
    ]
    if heldout is not None:
        comments.append("held-out log ({v}), base -> calibrated: {m}".format(
            v=variant, m=_changes(result["heldout"]["base"]["variants"][variant],
                                  result["heldout"]["calibrated"]["variants"][variant])))
    # The default's recalibration map (MODEL.md C.7) was fitted on the default noise's
    # probabilities; over other noise it would map other numbers, so this file clears it.
    comments.append("recalibration map cleared (fitted for the default noise): refit with toppledb recalibrate LOG --config THIS_FILE")
    write_outputs(args.out, {**result["chosen"], **NO_MAP}, comments, args.json, result)
    return 0


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
