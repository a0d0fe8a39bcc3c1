"""The rolling set: generated shapes that roll, to tune on (stop 59).

The corpus's random shapes rarely roll. The parts set showed the model's errors on shapes that do (its faceted
shafts), but it and the household set are for judging, not tuning.  This writes shapes made to roll, from a seed,
so that a correction for them can be tuned without reading either: faceted rods, prisms, cones, frusta, bottles,
capsules and coarse ellipsoids.  Every cross-section's vertices are moved radially by a few per cent
(``RADIAL_JITTER``), so that each facet is a stable pose of its own, as on a real object, rather than one pose
that symmetry merges (a roll onto the next facet of a regular prism lands in the pose it left).

    python -m pipeline.studies.rolling_set OUT [--seed 0]

writes ``OUT/meshes/*.stl`` and ``OUT/rolling_objects.csv``, a corpus list (``toppledb dataset --corpus``,
``toppledb play --objects``), each shape scaled to a 0.12 m largest extent and 0.1 kg like the parts and
household sets.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import trimesh

from ..build.atomic import file_sha256
from ..build.corpus import ObjectSpec, write_list
from .household_set import LARGEST_EXTENT, MASS

RADIAL_JITTER = 0.05
"""Largest relative radial move of a cross-section's vertex (uniform in +-)."""


def ring(sections: int, radius: float, z: float, jitter: np.ndarray) -> np.ndarray:
    """A cross-section's vertices: (sections, 3) float, m, a regular polygon scaled by (1 + jitter) per vertex."""
    angle = 2 * np.pi * np.arange(sections) / sections
    r = radius * (1 + jitter)
    return np.column_stack([r * np.cos(angle), r * np.sin(angle), np.full(sections, z)])


def lathe(profile: list[tuple[float, float]], sections: int, rng: np.random.Generator) -> trimesh.Trimesh:
    """The convex hull of rings at the profile's (radius, z) pairs (m), one jitter shared by all rings, so that
    the facets stay planar along the axis: a convex solid of revolution made of ``sections`` facets."""
    jitter = rng.uniform(-RADIAL_JITTER, RADIAL_JITTER, sections)
    points = [ring(sections, r, z, jitter) if r > 1e-9 else np.array([[0.0, 0.0, z]]) for r, z in profile]
    return trimesh.convex.convex_hull(np.vstack(points))


def shapes(rng: np.random.Generator) -> list[tuple[str, trimesh.Trimesh]]:
    """The set's shapes, named, in a fixed order (sizes before scaling; only proportions matter)."""
    out = []
    for sections in (6, 8, 12, 16, 24):
        for length in (0.7, 1.5, 3.0):  # length over diameter
            out.append((f"prism{sections}_l{length:g}", lathe([(0.5, 0.0), (0.5, length)], sections, rng)))
    for top in (0.0, 0.5):
        for height in (0.8, 2.0):
            out.append((f"frustum16_t{top:g}_h{height:g}", lathe([(0.5, 0.0), (0.5 * top, height)], 16, rng)))
    for neck in (0.35, 0.2):
        out.append((f"bottle16_n{neck:g}", lathe([(0.5, 0.0), (0.5, 1.6), (neck, 2.1), (neck, 2.6)], 16, rng)))
    for sections in (8, 12):
        caps = np.linspace(0, np.pi / 2, 3)
        profile = [(0.5 * np.cos(a), 0.5 - 0.5 * np.sin(a)) for a in caps[::-1]] + [(0.5 * np.cos(a), 1.5 + 0.5 * np.sin(a)) for a in caps]
        out.append((f"capsule{sections}", lathe(profile, sections, rng)))
    for sections, flat in ((10, 0.6), (14, 0.8)):
        profile = [(0.5 * np.cos(a), flat * 0.5 * np.sin(a)) for a in np.linspace(-np.pi / 2, np.pi / 2, 7)]
        out.append((f"ellipsoid{sections}_f{flat:g}", lathe(profile, sections, rng)))
    return out


def write_set(out: Path, seed: int = 0) -> list[str]:
    """Write the set's meshes and list under ``out``; returns the object ids, in the list's order."""
    meshes_dir = out / "meshes"
    meshes_dir.mkdir(parents=True, exist_ok=True)
    specs = []
    for name, mesh in shapes(np.random.default_rng(seed)):
        path = meshes_dir / f"{name}.stl"
        mesh.export(path)
        scale = LARGEST_EXTENT / float(mesh.extents.max())
        specs.append(ObjectSpec(name, str(path), scale, MASS, f"rolling_set:seed{seed}", file_sha256(path)))
    write_list(specs, out / "rolling_objects.csv", root=out)
    return [spec.object_id for spec in specs]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.rolling_set", description=__doc__.split("\n")[0])
    parser.add_argument("out", type=Path, help="directory to write meshes/ and rolling_objects.csv into")
    parser.add_argument("--seed", type=int, default=0, help="seed of the radial jitter (default: 0)")
    args = parser.parse_args(argv)
    ids = write_set(args.out, args.seed)
    print(f"{len(ids)} shapes written to {args.out / 'rolling_objects.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
