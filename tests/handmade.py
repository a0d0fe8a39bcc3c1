"""Hand-made datasets: tables written by a test, with a manifest that passes
``schema.manifest`` so that readers which insist on a finished dataset accept them."""

from __future__ import annotations

from pathlib import Path

from schema import layout
from schema.manifest import Manifest
from schema.version import CODE_VERSION, SCHEMA_VERSION


def write_minimal_manifest(root: Path, poses_per_object: dict[str, int]) -> Manifest:
    """A valid manifest naming the given objects; counts other than objects and poses are 0."""
    manifest = Manifest.model_validate({
        "schema_version": SCHEMA_VERSION,
        "code_version": {"package": CODE_VERSION, "python": "3"},
        "created": "2026-01-01T00:00:00+00:00",
        "seed": 0,
        "parameters": {
            "seed": 0,
            "poses": {"same_pose_angle": 0.17},
            "contacts": {"n_contacts": 1, "approach_offset": 0.015, "push_depth": 0.04},
            "topple": {"variant": "robust", "n_trials": 1},
            "mdp": {"gamma": 0.95},
        },
        "corpus": {"name": "handmade", "objects": [
            {"object_id": o, "path": f"{o}.obj", "scale": 1.0, "mass": 0.1, "source": "test", "sha256": ""}
            for o in poses_per_object
        ]},
        "counts": {"objects": len(poses_per_object), "failed": 0, "poses": sum(poses_per_object.values()),
                   "actions": 0, "ok_actions": 0, "transitions": 0},
        "tables": {}, "shards": {}, "failures": [],
        "timings": {"wall_s": 0.0, "cpu_s_by_stage": {}, "cpu_s_total": 0.0},
        "run": {},
    })
    (root / layout.MANIFEST).write_text(manifest.to_json())
    return manifest
