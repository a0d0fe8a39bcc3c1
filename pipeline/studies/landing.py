"""Where a topple lands, in physics: every topple of every stable pose released at its apex.

The toppling model decides whether a push topples an object over an edge; where the
object then comes to rest is a separate claim, a per-(pose, edge) table.  This study
checks that table against pybullet with no finger at all: the object is turned about
the edge until its centre of mass is ``APEX_MARGIN`` past the apex, released there,
left to fall and settle (``pushsim.rest_on_table``), and the pose it rests in
(``poses.settle``) is compared with

* ``quasi-static``: the thesis's landing (``StablePose.edge_final_pose``, 4.2.4);
* ``momentum x s``: the ``momentum`` correction (docs/MODEL.md C.8), the energy an
  impact keeps scaled by s (s = 1 is Housner's impact, the model's; s = 0 never rolls on,
  which is the quasi-static landing again up to the chain's first step);
* ``onward``: one fall beyond the momentum landing (s = 1), where ``landing_onward``
  (C.18) carries a share of the landings in marginal poses (drop probability at most the
  config's ``topple.landing_onward_below``); ``carried`` says whether C.18 carries the edge's
  landing.  The pose set here is unmerged (below), so a symmetric object's drop probability
  is split over its turned copies and more of its poses count as marginal than in the engine.

Blocked edges (the hull meets the table before the apex) are not released: nothing
falls from them.  Objects come from the same selection as ``toppledb play``.

    toppledb landing --objects corpus --count 42 --json reports/landing_corpus.json
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from ..model.config import Config
from ..model.landing_onward import onward_shares
from ..model.momentum import inertia_per_mass, momentum_poses
from ..model.outcomes import StablePose
from schema.frames import axis_angle_matrices

APEX_MARGIN = np.radians(1.0)
"""rad past the apex at which the object is released, so that it falls the way it toppled."""
FALL_TIME = 3.0
"""s of simulated time to fall and settle (a fall takes well under 1 s)."""
ENERGY_SCALES = (0.0, 0.5, 1.0, 1.5, 2.0)
"""Scales of the impact's kept energy that the study compares (1: the model)."""


def apex_transform(pose: StablePose, edge: int, margin: float = APEX_MARGIN) -> np.ndarray:
    """Object -> world transform of ``pose`` turned about base edge ``edge`` to ``margin`` past its apex.

    The edge stays on the table (z = 0): the turn is about the edge's own line.
    returns : (4, 4) float
    """
    y0, y1 = pose.base_edges[edge]
    turn = axis_angle_matrices(((y1 - y0) / np.linalg.norm(y1 - y0))[None], np.array([pose.apex_angle[edge] + margin]))[0]
    about_edge = np.eye(4)
    about_edge[:3, :3] = turn
    about_edge[:3, 3] = y0 - turn @ y0
    return about_edge @ pose.transform


def land_object(object_id: str, obj, pose_set, config: Config, scales: tuple[float, ...] = ENERGY_SCALES) -> list[dict]:
    """Release every unblocked topple of ``pose_set`` in pybullet; one row per (pose, edge).

    returns : dicts with object, pose, edge, physics (pose it rests in, -1 outside the set),
      quasi_static, momentum (one predicted pose per scale), onward (C.18's onward pose) and
      carried (whether C.18 carries this edge's landing on, with ``config``'s tau)
    """
    from ..model.poses import settle
    from .pushsim import body_model, rest_on_table

    poses = pose_set.poses
    body = body_model(obj)
    pose_tables = (np.array([p.transform for p in poses]), [p.base_edges for p in poses], [p.edge_final_pose for p in poses],
                   [p.edge_blocked for p in poses], obj.center_mass, inertia_per_mass(obj.mesh, obj.hull, obj.center_mass))
    tables = [momentum_poses(*pose_tables, energy_scale=scale)[0] for scale in scales]
    rows = []
    for pose in poses:
        carried = onward_shares(pose.edge_momentum_pose, pose.edge_onward_pose, pose.index, pose_set.probabilities, 1.0,
                                config.topple.landing_onward_below) > 0
        for edge in np.flatnonzero(~pose.edge_blocked & (pose.edge_final_pose != pose.index)).tolist():
            rest = rest_on_table(body, apex_transform(pose, edge), config, FALL_TIME)
            rows.append({
                "object": object_id,
                "pose": pose.index,
                "edge": edge,
                "physics": settle(pose_set, obj, rest[:3, :3]),
                "quasi_static": int(pose.edge_final_pose[edge]),
                "momentum": [int(table[pose.index][edge]) for table in tables],
                "onward": int(pose.edge_onward_pose[edge]),
                "carried": bool(carried[edge]),
            })
    return rows


def summarise(rows: list[dict], scales: tuple[float, ...] = ENERGY_SCALES) -> dict:
    """Share of released topples each predictor lands right, overall and where the model's
    momentum landing (scale 1) differs from the quasi-static one; and where the topples whose
    landing C.18 carries on (``carried``) rest."""
    physics = np.array([r["physics"] for r in rows])
    quasi = np.array([r["quasi_static"] for r in rows])
    momentum = np.array([r["momentum"] for r in rows]).reshape(len(rows), len(scales))
    model = momentum[:, scales.index(1.0)] if 1.0 in scales else quasi
    differ = model != quasi
    return {
        "released": len(rows),
        "objects": len({r["object"] for r in rows}),
        "outside_pose_set": int(np.sum(physics < 0)),
        "momentum_differs": int(differ.sum()),
        "agreement": {
            "quasi_static": _share(quasi == physics),
            **{f"momentum x {s:g}": _share(momentum[:, i] == physics) for i, s in enumerate(scales)},
        },
        "agreement_where_they_differ": {
            "quasi_static": _share((quasi == physics)[differ]),
            "momentum": _share((model == physics)[differ]),
        },
        **_marginal_landings(rows, model, physics),
    }


def _marginal_landings(rows: list[dict], model: np.ndarray, physics: np.ndarray) -> dict:
    """Where topples rest whose model landing C.18 carries on: in it, or in its onward pose."""
    if not rows or "carried" not in rows[0]:
        return {}
    onward = np.array([r["onward"] for r in rows])
    marginal = np.array([r["carried"] for r in rows], dtype=bool)
    return {"marginal_landings": {
        "released": int(marginal.sum()),
        "objects": len({r["object"] for r, m in zip(rows, marginal) if m}),
        "rest_in_landing": _share((physics == model)[marginal]),
        "rest_onward": _share((physics == onward)[marginal]),
    }}


ROW_FIELDS = ("object", "pose", "edge", "physics", "quasi_static", "momentum", "onward", "carried")


def record_text(summary: dict, rows: list[dict]) -> str:
    """The JSON record: the summary, then one released topple per line (``ROW_FIELDS``)."""
    head = json.dumps({**summary, "row_fields": ROW_FIELDS}, indent=1)[:-2]
    lines = ",\n".join(json.dumps([row[name] for name in ROW_FIELDS]) for row in rows)
    return f'{head},\n "rows": [\n{lines}\n ]\n}}\n'


def _share(hits: np.ndarray) -> float | None:
    return round(float(np.mean(hits)), 4) if len(hits) else None


def _land_spec(spec, config: Config) -> tuple[str, list[dict], str | None]:
    """One object (in a worker): its rows, or its failure."""
    from ..model.evaluation import load_object
    from ..model.mesh import MeshError
    from ..model.poses import stable_poses

    try:
        obj = load_object(spec, config)
        # Unmerged: momentum_poses follows a roll-on chain in each landing orientation's own
        # frame (as stable_poses does); merged symmetric poses would lend it a representative's.
        pose_set = stable_poses(obj, config.poses, merge_symmetric=False)
    except MeshError as err:
        return spec.object_id, [], str(err)
    return spec.object_id, land_object(spec.object_id, obj, pose_set, config), None


def main(argv: list[str] | None = None) -> int:
    """``toppledb landing``: release every topple at its apex in pybullet and score the landing tables."""
    from ..build.corpus import CorpusError
    from ..build.fanout import map_unordered
    from ..cli import UsageError, make_config, positive_int, refused_outputs
    from ..build.atomic import write_text_atomic
    from .playlog import PlayError, select_objects

    parser = argparse.ArgumentParser(prog="toppledb landing", description=__doc__.split("\n\n")[0])
    parser.add_argument("--objects", default="corpus", metavar="corpus|heldout|CORPUS",
                        help="as toppledb play: the default corpus, the held-out objects, or a list file or directory of "
                             "meshes (default: %(default)s)")
    parser.add_argument("--count", type=positive_int, metavar="N", help="objects (default: all of the mode's)")
    parser.add_argument("--seed", type=int, default=0, help="object selection seed, as toppledb play (default: %(default)s)")
    parser.add_argument("--workers", type=positive_int, help="worker processes (default: all cores)")
    parser.add_argument("--config", type=Path, metavar="FILE.toml", help="model parameters (table friction: topple.mu_table_mean)")
    parser.add_argument("--set", dest="overrides", action="append", default=[], metavar="SECTION.KEY=VALUE")
    parser.add_argument("--json", type=Path, help="write the summary and every row here")
    args = parser.parse_args(argv)
    if refused_outputs(args.json):
        return 2
    started = time.perf_counter()
    try:
        config = make_config(args)
        specs = select_objects(args.objects, args.count, args.seed, config.mesh.default_mass)
    except (UsageError, PlayError, CorpusError) as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    order = {spec.object_id: i for i, spec in enumerate(specs)}
    results = sorted(map_unordered(_land_spec, [(spec, config) for spec in specs], args.workers), key=lambda r: order[r[0]])
    rows = [row for _, object_rows, _ in results for row in object_rows]
    failed = {object_id: reason for object_id, _, reason in results if reason}
    summary = {**summarise(rows), "objects_mode": args.objects, "count": args.count, "seed": args.seed,
               "table_friction": config.topple.mu_table_mean, "apex_margin_deg": float(np.degrees(APEX_MARGIN)),
               "failed": failed, "wall_s": round(time.perf_counter() - started, 1)}
    print(json.dumps({k: v for k, v in summary.items() if k != "failed"}, indent=1))
    for object_id, reason in failed.items():
        print(f"not released: {object_id}: {reason}", file=sys.stderr)
    if args.json:
        write_text_atomic(args.json, record_text(summary, rows))
        print(f"record: {args.json}")
    return 0


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
