"""The default corpus: pybullet_data's candidates filtered by the selection rule
of thesis 4.4.1 (a pose with V_s > 0.5, and a lower pose with V_s < 0.25).

``regenerate_default`` evaluates every candidate (stable poses and V_s) on all
cores and writes ``corpus_default.csv``; the first ``DEFAULT_COUNT`` that pass
are kept, whatever the evaluation order.
"""

from __future__ import annotations

from pathlib import Path

from ..model.config import Config
from .corpus import DEFAULT_LIST, ObjectSpec, candidate_specs, pybullet_data_dir, write_list

DEFAULT_COUNT = 189
"""Objects in the thesis's dataset (4.4.1) and in the default corpus."""


def selection_task(spec: ObjectSpec, config: Config) -> tuple[str, bool, str]:
    """Apply the selection rule to one candidate: (object id, selected, reason if it failed).

    Runs in a worker; any failure (bad mesh included) means "not selected".
    """
    from ..model.evaluation import select_info
    from ..model.mdp import is_selected

    try:
        v_s, com_heights = select_info(spec, config)
        return spec.object_id, bool(is_selected(v_s, com_heights)), ""
    except Exception as err:  # one bad candidate must not stop the selection
        return spec.object_id, False, " ".join(f"{type(err).__name__}: {err}".split())[:300]


def regenerate_default(
    config: Config,
    out: str | Path = DEFAULT_LIST,
    count: int = DEFAULT_COUNT,
    limit: int | None = None,
    workers: int | None = None,
    scheduler: str | None = None,
    progress: bool = True,
) -> dict:
    """Select objects from pybullet_data's candidates and write the default list.

    Candidates are ordered named meshes first, then random objects by number; every
    candidate is evaluated (stable poses and V_s per pose) and the first ``count``
    that satisfy ``pipeline.model.mdp.is_selected`` are kept, so the choice does not depend
    on evaluation order or the number of workers.

    Returns counts (candidates, failed, selected, kept) and ``failures``: object id ->
    reason for every candidate that could not be evaluated.
    """
    from .fanout import map_unordered

    root = pybullet_data_dir()
    candidates = candidate_specs(config.mesh.default_mass, root)[:limit]
    outcome: dict[str, tuple[bool, str]] = {}
    for object_id, selected, reason in map_unordered(
        selection_task, [(spec, config) for spec in candidates], workers, scheduler, "selecting", progress
    ):
        outcome[object_id] = (selected, reason)
    chosen = [spec for spec in candidates if outcome[spec.object_id][0]]
    kept = chosen[:count]
    write_list(kept, out, root)
    failures = {spec.object_id: outcome[spec.object_id][1] for spec in candidates if outcome[spec.object_id][1]}
    return {
        "candidates": len(candidates),
        "failed": len(failures),
        "selected": len(chosen),
        "kept": len(kept),
        "failures": failures,
    }
