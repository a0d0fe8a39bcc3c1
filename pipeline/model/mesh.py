"""Loading and validating corpus meshes.

A mesh becomes an ``ObjectModel``: the surface in metres, its convex hull, mass
and centre of mass.  What trimesh can repair is repaired and listed in
``ObjectModel.repairs``; what it cannot is rejected with a ``MeshError`` whose
message is one line naming the object and the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from .config import MESH_SUFFIXES, MeshConfig


class MeshError(ValueError):
    """A mesh that cannot be used; ``str(err)`` is one line: ``<name>: <reason>``."""


FORMATS = "OBJ, STL or PLY"
"""``MESH_SUFFIXES`` as a message names them."""


@dataclass
class ObjectModel:
    """An object ready for the toppling model.

    name : str, identifier used in messages and random streams
    mesh : trimesh.Trimesh, surface in the object frame, metres
    hull : trimesh.Trimesh, convex hull of ``mesh``
    mass : float, kg
    center_mass : (3,) float, m, object frame
    repairs : list[str], what was repaired on load, for the manifest
    """

    name: str
    mesh: trimesh.Trimesh
    hull: trimesh.Trimesh
    mass: float
    center_mass: np.ndarray
    repairs: list[str] = field(default_factory=list)


def load_mesh(
    path: str | Path,
    scale: float = 1.0,
    mass: float | None = None,
    center_mass: np.ndarray | None = None,
    name: str | None = None,
    config: MeshConfig = MeshConfig(),
    corpus_hint: bool = False,
) -> ObjectModel:
    """Load an OBJ/STL/PLY file as an ``ObjectModel``.

    Parameters
    ----------
    path : mesh file
    scale : float, multiplies the file's coordinates to give metres
    mass : float, kg; ``config.default_mass`` when None
    center_mass : (3,) float, m, object frame; uniform density when None
    name : identifier for messages; the file stem when None
    corpus_hint : a size error's unit hint also names the corpus's own settings (a sidecar's
        ``units``, a list's scale column), for a dataset build; otherwise only --units/--scale

    Every error is in toppledb's words, not the mesh library's: a format it does not read,
    a file that is not what its extension says, a file without triangles.
    """
    name = name or Path(path).stem
    file = Path(path).name
    if not Path(path).is_file():
        raise MeshError(f"{name}: mesh file not found: {path}")
    suffix = Path(path).suffix.lower()
    if suffix not in MESH_SUFFIXES:
        what = f"'{suffix}' is not a mesh format toppledb reads" if suffix else "no file extension to tell its format"
        raise MeshError(f"{name}: cannot read {file}: {what}; convert it to {FORMATS}")
    try:
        loaded = trimesh.load(str(path), force="mesh", process=False)
    except OSError as err:  # the file itself cannot be opened or read (permissions, a directory, I/O)
        raise MeshError(f"{name}: cannot read {file}: {(err.strerror or str(err)).lower()}") from None
    except Exception:  # noqa: BLE001 (trimesh raises many types for unreadable files, ImportError included)
        # ImportError: trimesh imports its text-encoding detector only for bytes that are not
        # UTF-8; the real cause is the file, not the missing module.
        raise MeshError(f"{name}: cannot read {file}: {_not_a_mesh(path)}") from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise MeshError(f"{name}: {file} holds no triangle mesh")
    if len(loaded.faces) == 0:
        # Forced to a mesh, trimesh drops vertices no face uses: read again to say what the file holds.
        points = _point_count(path)
        why = f"a point cloud ({points} vertices, no faces), not a surface" if points else f"no triangles, {_not_a_mesh(path)}"
        raise MeshError(f"{name}: cannot read {file}: {why}")
    return model_from_mesh(
        loaded, scale=scale, mass=mass, center_mass=center_mass, name=name, config=config, corpus_hint=corpus_hint
    )


MAGIC = {".ply": b"ply"}
"""How a file of the format begins, where the format says (OBJ and binary STL do not)."""


def _not_a_mesh(path: str | Path) -> str:
    """Why a file gave no mesh, for the user: empty, damaged, binary garbage, or text without
    faces; and what to do (a mesh in a format toppledb reads)."""
    data = Path(path).read_bytes()[:4096]
    suffix = Path(path).suffix.lower()
    kind = suffix.lstrip(".").upper() or "mesh"
    if not data:
        return "the file is empty"
    again = f"; export it again as {FORMATS}"
    if suffix in MAGIC and data.startswith(MAGIC[suffix]):
        return f"a damaged {kind} file (its header reads as {kind}, its contents do not){again}"
    try:
        data.decode("utf-8")
    except UnicodeDecodeError:
        return f"not a valid {kind} file (binary data that is neither {kind} nor UTF-8 text){again}"
    return f"not a valid {kind} file (text without vertices and faces){again}"


def _point_count(path: str | Path) -> int:
    """How many vertices a file holds when read as points (0 when it cannot be read so)."""
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception:  # noqa: BLE001 (only a message depends on it)
        return 0
    return len(loaded.vertices) if isinstance(loaded, trimesh.PointCloud) else 0


UNIT_SCALES = {"mm": 0.001, "cm": 0.01, "in": 0.0254, "m": 1.0}
"""Metres per file unit, for the ``--units`` flag and ``units`` in a corpus sidecar."""
UNIT_NAMES = {"mm": "millimetres", "cm": "centimetres", "in": "inches", "m": "metres"}


def unit_hint(extent: float, config: MeshConfig, corpus: bool = False) -> str:
    """For an object ``extent`` metres across that is out of the tabletop range, the
    file units that would make it fit, as a hint: "" when none would.  ``corpus``: also
    name the corpus's settings (a dataset build); else only the --units/--scale flags
    (``add``, ``figures``), the only ones there."""
    # Likeliest first: the unit that puts the object nearest the middle of the range (on a log scale),
    # so a 10 m "object" is read as 10 cm, not as the 1 cm it would be in millimetres.
    middle = np.log(np.sqrt(config.min_extent * config.max_extent))
    fits = sorted(
        (unit for unit, factor in UNIT_SCALES.items()
         if unit != "m" and config.min_extent <= extent * factor <= config.max_extent),
        key=lambda unit: abs(np.log(extent * UNIT_SCALES[unit]) - middle),
    )
    if extent < config.min_extent:
        grown = [extent / factor for unit, factor in UNIT_SCALES.items() if unit != "m"]
        fitting = any(config.min_extent <= size <= config.max_extent for size in grown)
        where = "--units, --scale, or the corpus's scale" if corpus else "--units or --scale"
        return f"; check the file's units ({where})" if fitting else ""
    if not fits:
        return ""
    return (
        "; the file is probably in " + " or ".join(UNIT_NAMES[u] for u in fits) + f": use --units {fits[0]}"
        + (f" (or units = \"{fits[0]}\" in corpus.toml, or a scale column)" if corpus else "")
    )


def model_from_mesh(
    mesh: trimesh.Trimesh,
    scale: float = 1.0,
    mass: float | None = None,
    center_mass: np.ndarray | None = None,
    name: str = "mesh",
    config: MeshConfig = MeshConfig(),
    corpus_hint: bool = False,
) -> ObjectModel:
    """Validate and repair an in-memory mesh; see ``load_mesh``."""
    mass = config.default_mass if mass is None else float(mass)
    if not np.isfinite(mass) or mass <= 0:
        raise MeshError(f"{name}: mass must be a positive number of kg, got {mass}")
    if not np.isfinite(scale) or scale <= 0:
        raise MeshError(f"{name}: scale must be positive, got {scale}")
    if len(mesh.faces) == 0 or len(mesh.vertices) == 0:
        raise MeshError(f"{name}: empty mesh (no faces)")
    if not np.all(np.isfinite(mesh.vertices)):
        raise MeshError(f"{name}: non-finite vertex coordinates")

    mesh = mesh.copy()
    mesh.apply_scale(scale)
    repairs = repair(mesh, config)
    if len(mesh.faces) == 0:
        raise MeshError(f"{name}: no triangle with an area: every face is degenerate (repeated or collinear corners)")

    extent = float(mesh.extents.max())
    if extent < config.min_extent:
        raise MeshError(
            f"{name}: too small for a tabletop: largest side {extent:.4g} m < {config.min_extent} m{unit_hint(extent, config, corpus_hint)}"
        )
    if extent > config.max_extent:
        raise MeshError(
            f"{name}: too large for a tabletop: largest side {extent:.4g} m > {config.max_extent} m{unit_hint(extent, config, corpus_hint)}"
        )

    # A flat mesh makes trimesh divide by a zero volume; the rejection below says why.
    with np.errstate(invalid="ignore", divide="ignore"):
        try:
            hull = mesh.convex_hull
        except Exception as err:  # qhull fails on flat or degenerate input
            qhull = _one_line(err).split(" While executing")[0]
            raise MeshError(f"{name}: zero volume: the mesh is flat or degenerate ({qhull[:120]})") from None
        flat = not hull.is_volume or hull.volume <= 1e-12
    if flat:
        raise MeshError(f"{name}: zero or negative volume (the mesh is flat or degenerate)")

    if mesh.is_volume:
        volume = float(mesh.volume)
        if volume <= 1e-12:
            raise MeshError(f"{name}: zero or negative volume ({volume:.3g} m^3)")
        default_com = np.asarray(mesh.center_mass, dtype=float)
    else:
        # An open surface has no inside; its convex hull is the best solid we know.
        repairs.append("open surface (not watertight after repair): treated as its convex hull for the centre of mass")
        default_com = np.asarray(hull.center_mass, dtype=float)

    com = default_com if center_mass is None else np.asarray(center_mass, dtype=float).reshape(3)
    if not np.all(np.isfinite(com)):
        raise MeshError(f"{name}: non-finite centre of mass")
    # signed_distance is positive inside; a COM on or outside the hull cannot rest stably.
    if center_mass is not None and trimesh.proximity.signed_distance(hull, com[None])[0] <= 0:
        raise MeshError(f"{name}: centre of mass {np.round(com, 4).tolist()} is outside the convex hull")

    return ObjectModel(name=name, mesh=mesh, hull=hull, mass=mass, center_mass=com, repairs=repairs)


def repair(mesh: trimesh.Trimesh, config: MeshConfig) -> list[str]:
    """Repair ``mesh`` in place with trimesh; return a line per repair made."""
    repairs = []
    n_vertices, n_faces = len(mesh.vertices), len(mesh.faces)
    mesh.merge_vertices()
    if len(mesh.vertices) < n_vertices:
        repairs.append(f"merged {n_vertices - len(mesh.vertices)} duplicate vertices")
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) < n_faces:
        repairs.append(f"removed {n_faces - len(mesh.faces)} degenerate or duplicate faces")
    if len(mesh.faces) == 0:
        return repairs
    if config.fill_holes and not mesh.is_watertight:
        if mesh.fill_holes():
            repairs.append("filled holes")
    if mesh.is_watertight:
        before = mesh.faces.copy()
        trimesh.repair.fix_normals(mesh)
        if mesh.faces.shape != before.shape or np.any(mesh.faces != before):
            repairs.append("fixed face winding and normals")
    return repairs


def _one_line(err: Exception) -> str:
    text = " ".join(str(err).split())
    return text[:200] or type(err).__name__
