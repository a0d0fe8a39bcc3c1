"""Which objects a dataset is built from: the corpus.

A corpus is a list of ``ObjectSpec`` (mesh file, scale to metres, mass, where it
comes from, SHA-256 of the file).  Three kinds:

- ``default``: ``pipeline/build/corpus_default.csv``, the 189 objects of pybullet_data
  chosen by the selection rule of thesis 4.4.1 (``toppledb corpus`` regenerates it,
  see ``pipeline.build.selection``);
- a directory of meshes (OBJ/STL/PLY, searched recursively); their units and
  masses come from a sidecar beside them (``corpus.toml`` or ``corpus.csv``, see
  ``SIDECAR_HELP``) and from ``Units`` (the ``--units/--scale/--mass/--density``
  flags), else scale 1 and the configured default mass;
- a list file: CSV with a header and a ``path`` column, optionally ``object_id``,
  ``source``, ``scale`` (default 1), ``mass`` (kg, default from the config) and
  ``sha256`` (checked when given).

Paths in a list file are resolved: absolute as they are; rows whose ``source`` is
``pybullet_data`` or starts with ``pybullet_data/`` relative to the installed
pybullet_data directory (so the committed default list works on any machine);
all others relative to the list file's directory.

Loading never fails on one bad entry: a missing file or a changed checksum is
returned in ``Corpus.problems`` and becomes a failure of that object in the
dataset.  A corpus that cannot be read at all (no such path, malformed CSV,
duplicate ids) raises ``CorpusError`` with a one-line message.
"""

from __future__ import annotations

import csv
import io
import os
import re
import xml.etree.ElementTree as ElementTree
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

from schema.layout import HIVE_NULL, READER_WORDS, check_object_id, object_id_key
from schema.pushlog import PYBULLET_SOURCE, is_pybullet_source

from ..model.config import MESH_SUFFIXES
from .atomic import file_sha256, write_text_atomic

DEFAULT_LIST = Path(__file__).with_name("corpus_default.csv")
LIST_COLUMNS = ("object_id", "source", "path", "scale", "mass", "sha256")
"""Columns of the default list as written by ``write_list``."""

NAMED_MESHES = (
    # (object id, URDF giving mesh/scale/mass, or mesh with scale and mass when there is no URDF)
    ("bunny", None, "bunny.obj", 0.1, None),  # no URDF; 0.1 makes it ~0.2 m tall, tabletop size
    ("duck", "duck_vhacd.urdf", None, None, None),
    ("lego", "lego/lego.urdf", None, None, None),
    ("mug", "objects/mug.urdf", None, None, None),
    ("teddy", "teddy_vhacd.urdf", None, None, None),
)
"""pybullet_data's named tabletop meshes.  From a URDF we take its visual mesh (the
detailed one; collision meshes are convex decompositions or boxes), its scale and mass."""


class CorpusError(ValueError):
    """A corpus that cannot be read; the message is one line."""


SIDECAR_TOML, SIDECAR_CSV = "corpus.toml", "corpus.csv"
SIDECAR_HELP = """\
A directory of meshes may hold a sidecar saying their units and masses:

  corpus.toml                           corpus.csv
    units = "mm"      # or scale = 0.001      path,scale,mass,object_id
    mass = 0.2        # kg, every mesh        bunny.obj,0.1,0.3,bunny
    # density = 700   # or kg/m^3 x volume    parts/bolt.stl,0.001,,
    [objects."bunny.obj"]  # one mesh, by path relative to the directory
    scale = 0.1
    mass = 0.3

Each mesh takes, in order: its own sidecar entry, then the --units/--scale/--mass/
--density flags, then the sidecar's defaults, then scale 1 and mesh.default_mass."""


@dataclass(frozen=True)
class Units:
    """Scale and mass settings for the meshes of a directory (flags or sidecar).

    scale : metres per file unit (``units`` is the same as a name: mm, cm, in, m)
    mass : kg for every mesh; density : kg/m^3, mass = density x volume (of the
    mesh when watertight, else of its convex hull).  None: not set here.
    """

    scale: float | None = None
    mass: float | None = None
    density: float | None = None
    object_id: str | None = None

    @classmethod
    def parse(cls, values: dict, where: str) -> "Units":
        """From a sidecar table or CSV row: ``units`` or ``scale``, ``mass`` or ``density``."""
        from ..model.mesh import UNIT_SCALES

        known = {"units", "scale", "mass", "density", "object_id"}
        unknown = set(values) - known
        if unknown:
            raise CorpusError(f"{where}: unknown key(s) {sorted(unknown)}; known: units, scale, mass, density, object_id")
        scale = values.get("scale")
        units = values.get("units")
        if units not in (None, ""):
            if units not in UNIT_SCALES:
                raise CorpusError(f"{where}: units {units!r} is not one of {', '.join(UNIT_SCALES)}")
            if scale not in (None, ""):
                raise CorpusError(f"{where}: give units or scale, not both")
            scale = UNIT_SCALES[units]
        mass, density = values.get("mass"), values.get("density")
        if mass not in (None, "") and density not in (None, ""):
            raise CorpusError(f"{where}: give mass or density, not both")
        return cls(
            scale=_number(scale, None, "scale", where),
            mass=_number(mass, None, "mass", where),
            density=_number(density, None, "density", where),
            object_id=values.get("object_id") or None,
        )

    def over(self, other: "Units") -> "Units":
        """These settings, falling back to ``other`` for what is not set (mass and density together)."""
        has_mass = self.mass is not None or self.density is not None
        return Units(
            scale=self.scale if self.scale is not None else other.scale,
            mass=self.mass if has_mass else other.mass,
            density=self.density if has_mass else other.density,
            object_id=self.object_id or other.object_id,
        )


def read_sidecar(directory: Path) -> tuple[Units, dict[str, Units]]:
    """The directory's defaults and per-mesh entries (by path relative to it, POSIX)."""
    toml_path, csv_path = directory / SIDECAR_TOML, directory / SIDECAR_CSV
    if toml_path.is_file() and csv_path.is_file():
        raise CorpusError(f"{directory}: both {SIDECAR_TOML} and {SIDECAR_CSV}; keep one")
    if toml_path.is_file():
        import tomllib

        try:
            data = tomllib.loads(toml_path.read_text())
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
            raise CorpusError(f"{toml_path}: {' '.join(str(err).split())}") from None
        objects = data.get("objects", {})
        if not isinstance(objects, dict) or not all(isinstance(v, dict) for v in objects.values()):
            raise CorpusError(f'{toml_path}: [objects."path"] entries must be tables')
        defaults = Units.parse({k: v for k, v in data.items() if k != "objects"}, SIDECAR_TOML)
        if defaults.object_id:
            raise CorpusError(f"{toml_path}: object_id belongs in an [objects.\"path\"] table")
        entries = {_posix(k): Units.parse(v, f"{SIDECAR_TOML} [objects.{k!r}]") for k, v in objects.items()}
        return defaults, entries
    if csv_path.is_file():
        try:
            rows = list(csv.DictReader(io.StringIO(csv_path.read_text())))
        except (OSError, UnicodeDecodeError, csv.Error) as err:
            raise CorpusError(f"{csv_path}: {err}") from None
        entries = {}
        for number, row in enumerate(rows, start=2):
            row = _csv_row(row, f"{SIDECAR_CSV} row {number}")
            if not row.get("path"):
                raise CorpusError(f"{SIDECAR_CSV} row {number}: empty path")
            settings = {k: v for k, v in row.items() if k != "path"}
            entries[_posix(row["path"])] = Units.parse(settings, f"{SIDECAR_CSV} row {number}")
        return Units(), entries
    return Units(), {}


def _csv_row(raw: dict, where: str) -> dict[str, str]:
    """A ``csv.DictReader`` row with keys and values stripped; a row with more fields than the
    header (which the reader files under the key None) is refused, naming its row."""
    if None in raw:
        raise CorpusError(f"{where}: {len(raw) - 1 + len(raw[None])} fields, more than the header's {len(raw) - 1}")
    return {k.strip(): (v or "").strip() for k, v in raw.items()}


def _posix(path: str) -> str:
    return Path(path).as_posix().removeprefix("./")


def mass_from_density(path: Path, scale: float, density: float) -> float | None:
    """kg: density x volume of the scaled mesh (its convex hull when it is not closed);
    None when the mesh cannot be loaded (the build then reports why)."""
    from ..model.mesh import MeshError, load_mesh

    try:
        obj = load_mesh(path, scale=scale, mass=1.0)
    except MeshError:
        return None
    volume = float(obj.mesh.volume) if obj.mesh.is_volume else float(obj.hull.volume)
    return density * volume


@dataclass(frozen=True)
class ObjectSpec:
    """One object of a corpus.

    object_id : str, unique in the corpus, safe as a file name (see ``schema.layout``)
    path : str, absolute path of the mesh file
    scale : float, multiplies the file's coordinates to give metres
    mass : float, kg
    source : str, where the mesh comes from, e.g. ``pybullet_data/random_urdfs/042/042.urdf``
    sha256 : str, hex digest of the mesh file ("" when it cannot be read)
    """

    object_id: str
    path: str
    scale: float
    mass: float
    source: str
    sha256: str


@dataclass
class Corpus:
    """Objects in a fixed order, and the entries already known to be unusable.

    problems : object id -> one-line reason (missing file, checksum mismatch)
    """

    name: str
    specs: list[ObjectSpec]
    problems: dict[str, str] = field(default_factory=dict)

    def renamed(self) -> list[tuple[str, str]]:
        """(file name, object id) of each mesh of a directory corpus whose id is not its file's stem: ids
        are derived so that they are unique, safe as file names and read as text by every table reader
        (``object_id_from_name``), and a user asks for an object by the id, not the file."""
        return [(Path(s.path).name, s.object_id) for s in self.specs
                if s.source.startswith("dir:") and Path(s.path).stem != s.object_id]

    def limit(self, n: int | None) -> "Corpus":
        """The first ``n`` objects (all when ``n`` is None)."""
        if n is None:
            return self
        specs = self.specs[:n]
        kept = {s.object_id for s in specs}
        return Corpus(self.name, specs, {k: v for k, v in self.problems.items() if k in kept})


def load_corpus(corpus: str, default_mass: float, units: Units | None = None) -> Corpus:
    """Resolve the ``--corpus`` argument: ``default``, ``pybullet_data`` (every
    candidate, unselected), a directory of meshes, or a CSV list file.

    units : scale/mass settings (the CLI flags), for a directory of meshes only.
    """
    if units is not None and units != Units() and not Path(corpus).is_dir():
        raise CorpusError(
            "--units, --scale, --mass and --density apply to a directory of meshes; "
            "a list file has scale and mass columns"
        )
    if corpus == "default":
        if not DEFAULT_LIST.is_file():
            raise CorpusError(f"default corpus list {DEFAULT_LIST} is missing; run `toppledb corpus`")
        return read_list(DEFAULT_LIST, default_mass, name="default")
    if corpus == PYBULLET_SOURCE:
        return Corpus(PYBULLET_SOURCE, candidate_specs(default_mass))
    path = Path(corpus)
    if path.is_dir():
        return scan_directory(path, default_mass, units)
    if path.is_file():
        return read_list(path, default_mass)
    raise CorpusError(f"corpus not found: {corpus} (give 'default', 'pybullet_data', a directory of meshes or a CSV file)")


# --- files ------------------------------------------------------------------------


def pybullet_data_dir() -> Path:
    try:
        import pybullet_data
    except ImportError:
        raise CorpusError("pybullet_data is not installed (pip install pybullet)") from None
    return Path(pybullet_data.getDataPath())


def object_id_from_name(name: str) -> str:
    """A valid object id from a file stem: other characters become '_', and ids that
    would start with a digit, or are a word such as ``inf`` or ``true`` (``schema.layout.READER_WORDS``),
    get an ``obj_`` prefix (readers would take them for numbers, dates or booleans)."""
    cleaned = re.sub(r"[^A-Za-z0-9_.-]", "_", name)[:120] or "obj"
    readable = re.match(r"[A-Za-z_]", cleaned) and cleaned.lower() not in READER_WORDS and cleaned != HIVE_NULL
    return cleaned if readable else f"obj_{cleaned}"


def _unique(ids: list[str]) -> list[str]:
    """Make derived ids unique deterministically: the second ``x`` (or ``X``) becomes ``x-2``
    (``X-2``), the third ``x-3``, skipping any suffix an id already takes (``x``, ``x``, ``x-2``
    give ``x``, ``x-2``, ``x-2-2``); case does not tell ids apart (``schema.layout.object_id_key``)."""
    taken: set[str] = set()
    out = []
    for object_id in ids:
        unique, n = object_id, 2
        while object_id_key(unique) in taken:  # the smallest free suffix
            unique, n = f"{object_id}-{n}", n + 1
        taken.add(object_id_key(unique))
        out.append(unique)
    return out


def _check_ids(ids: list[str], where: str) -> None:
    """Every id safe as a file name (``schema.layout.check_object_id``) and unique."""
    for object_id in ids:
        try:
            check_object_id(object_id)
        except ValueError as err:
            raise CorpusError(f"{where}: {err}") from None
    counts = Counter(object_id_key(i) for i in ids)
    duplicates = sorted({i for i in ids if counts[object_id_key(i)] > 1})
    if duplicates:
        raise CorpusError(f"{where}: duplicate object ids {duplicates[:5]} (ids name files, so case does not tell them apart)")


def _dangling(path: Path) -> bool:
    """A symbolic link whose target does not exist."""
    return path.is_symlink() and not path.exists()


def _check_files(specs: list[ObjectSpec], expected_sha: dict[str, str]) -> dict[str, str]:
    problems = {}
    for spec in specs:
        if not os.path.isfile(spec.path):
            link = f" (a symbolic link to {os.readlink(spec.path)}, which is not there)" if _dangling(Path(spec.path)) else ""
            problems[spec.object_id] = f"mesh file not found: {spec.path}{link}"
        elif not spec.sha256:
            problems[spec.object_id] = f"mesh file cannot be read: {spec.path}"
        elif expected_sha.get(spec.object_id) and expected_sha[spec.object_id] != spec.sha256:
            problems[spec.object_id] = (
                f"mesh file changed since the corpus was listed: sha256 {spec.sha256[:12]}..., "
                f"listed {expected_sha[spec.object_id][:12]}..."
            )
    return problems


# --- directory and list corpora ---------------------------------------------------------


def scan_directory(directory: str | Path, default_mass: float, units: Units | None = None) -> Corpus:
    """Every OBJ/STL/PLY file under ``directory``, in path order.  Scale and mass per
    mesh: its sidecar entry, then ``units`` (flags), then the sidecar's defaults, then
    scale 1 and ``default_mass`` (see ``SIDECAR_HELP``)."""
    directory = Path(directory).resolve()
    files = sorted(
        # A link whose target is gone is listed too, so that the build reports it rather than skip it unseen.
        (p for p in directory.rglob("*") if (p.is_file() or _dangling(p)) and p.suffix.lower() in MESH_SUFFIXES),
        key=lambda p: p.relative_to(directory).as_posix(),
    )
    if not files:
        raise CorpusError(f"no OBJ, STL or PLY meshes in {directory}")
    defaults, entries = read_sidecar(directory)
    relative = [p.relative_to(directory).as_posix() for p in files]
    unknown = sorted(set(entries) - set(relative))
    if unknown:
        raise CorpusError(f"{directory}: the sidecar names meshes that are not there: {unknown[:3]}")
    base = (units or Units()).over(defaults)
    chosen = [entries.get(r, Units()).over(base) for r in relative]
    derived = _unique([object_id_from_name(p.stem) for p in files])
    ids = [c.object_id or auto for c, auto in zip(chosen, derived)]
    _check_ids(ids, str(directory))
    specs = []
    for object_id, p, c in zip(ids, files, chosen):
        scale = c.scale if c.scale is not None else 1.0
        mass = c.mass if c.mass is not None else float(default_mass)
        if c.density is not None:
            mass = mass_from_density(p, scale, c.density) or float(default_mass)
        specs.append(ObjectSpec(object_id, str(p), float(scale), float(mass), f"dir:{directory.name}", file_sha256(p)))
    return Corpus(str(directory), specs, _check_files(specs, {}))


def read_list(path: str | Path, default_mass: float, name: str | None = None) -> Corpus:
    """A CSV list file; see the module docstring for its columns and path rules."""
    path = Path(path).resolve()
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise CorpusError(f"cannot read corpus list {path}: {err}") from None
    lines = [line for line in text.splitlines() if line.strip() and not line.lstrip().startswith("#")]
    reader = csv.DictReader(io.StringIO("\n".join(lines)))
    columns = [c.strip() for c in (reader.fieldnames or [])]
    if "path" not in columns:
        raise CorpusError(f"{path.name}: a corpus list needs a header with a 'path' column, got {columns}")
    unknown = set(columns) - set(LIST_COLUMNS)
    if unknown:
        raise CorpusError(f"{path.name}: unknown column(s) {sorted(unknown)}; known: {', '.join(LIST_COLUMNS)}")

    rows = []
    for number, raw in enumerate(reader, start=2):
        where = f"{path.name} row {number}"
        row = _csv_row(raw, where)
        if not row.get("path"):
            raise CorpusError(f"{where}: empty path")
        source = row.get("source") or f"list:{path.name}"
        rows.append(
            (
                row.get("object_id") or None,
                str(_resolve(row["path"], source, path.parent)),
                _number(row.get("scale"), 1.0, "scale", where),
                _number(row.get("mass"), default_mass, "mass", where),
                source,
                row.get("sha256", "").lower(),
            )
        )
    if not rows:
        raise CorpusError(f"{path.name}: the corpus list has no objects")

    derived = _unique([object_id_from_name(Path(r[1]).stem) for r in rows])
    ids = [given or auto for (given, *_), auto in zip(rows, derived)]
    _check_ids(ids, path.name)

    specs = [
        ObjectSpec(object_id, mesh, scale, mass, source, file_sha256(mesh))
        for object_id, (_, mesh, scale, mass, source, _) in zip(ids, rows)
    ]
    expected = {object_id: row[5] for object_id, row in zip(ids, rows)}
    return Corpus(name or str(path), specs, _check_files(specs, expected))


def _resolve(mesh: str, source: str, list_dir: Path) -> Path:
    if os.path.isabs(mesh):
        return Path(mesh)
    if is_pybullet_source(source):
        return pybullet_data_dir() / mesh
    return (list_dir / mesh).resolve()


def _number(text: str | float | None, default: float | None, what: str, where: str) -> float | None:
    if text is None or text == "":
        return None if default is None else float(default)
    if isinstance(text, bool):  # a TOML ``mass = true`` is not 1 kg
        raise CorpusError(f"{where}: {what} {text!r} is not a number")
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise CorpusError(f"{where}: {what} {text!r} is not a number") from None
    if not value > 0 or value == float("inf"):
        raise CorpusError(f"{where}: {what} must be positive and finite, got {text}")
    return value


def write_list(specs: list[ObjectSpec], path: str | Path, root: Path | None) -> None:
    """Write specs as a list file with paths relative to ``root`` (None: absolute paths), atomically."""
    path = Path(path)
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(LIST_COLUMNS)
    for s in specs:
        mesh = Path(s.path).resolve()
        written = mesh.as_posix() if root is None else mesh.relative_to(root.resolve()).as_posix()
        writer.writerow([s.object_id, s.source, written, repr(s.scale), repr(s.mass), s.sha256])
    write_text_atomic(path, buffer.getvalue())


# --- pybullet_data candidates -----------------------------------------------------------


def urdf_mesh(urdf: Path) -> tuple[Path, float | None, float | None]:
    """Mesh file, uniform scale and mass of a single-link URDF (visual geometry first).

    Returns (mesh path, scale or None when unspecified, mass in kg or None).
    """
    try:
        root = ElementTree.parse(urdf).getroot()
    except (OSError, ElementTree.ParseError) as err:
        raise CorpusError(f"cannot parse {urdf}: {err}") from None
    meshes = root.findall(".//visual/geometry/mesh") + root.findall(".//collision/geometry/mesh")
    if not meshes:
        raise CorpusError(f"{urdf.name}: no mesh geometry")
    mesh = meshes[0]
    scale = None
    if mesh.get("scale"):
        factors = {float(x) for x in mesh.get("scale").split()}
        if len(factors) != 1:
            raise CorpusError(f"{urdf.name}: non-uniform mesh scale {mesh.get('scale')!r}")
        scale = factors.pop()
    mass_element = root.find(".//inertial/mass")
    mass = float(mass_element.get("value")) if mass_element is not None else None
    if mass is not None and mass <= 0:
        mass = None  # a zero URDF mass marks a static body, not a real mass
    return urdf.parent / mesh.get("filename"), scale, mass


def candidate_specs(default_mass: float, root: Path | None = None) -> list[ObjectSpec]:
    """Every candidate object in pybullet_data: the named meshes, then the 1000 random
    objects (``random_000`` ... ``random_999``), in that order."""
    root = root or pybullet_data_dir()
    specs = []
    for object_id, urdf, mesh, scale, mass in NAMED_MESHES:
        if urdf is not None:
            if not (root / urdf).is_file():
                continue
            mesh_path, scale, mass = urdf_mesh(root / urdf)
            source = f"{PYBULLET_SOURCE}/{urdf}"
        else:
            mesh_path, source = root / mesh, PYBULLET_SOURCE
        if mesh_path.is_file():
            specs.append(_spec(object_id, mesh_path, scale, mass, source, default_mass))
    for urdf in sorted((root / "random_urdfs").glob("[0-9][0-9][0-9]/[0-9][0-9][0-9].urdf")):
        mesh_path, scale, mass = urdf_mesh(urdf)
        relative = urdf.relative_to(root).as_posix()
        specs.append(_spec(f"random_{urdf.stem}", mesh_path, scale, mass, f"{PYBULLET_SOURCE}/{relative}", default_mass))
    return specs


def _spec(object_id, mesh_path: Path, scale, mass, source: str, default_mass: float) -> ObjectSpec:
    return ObjectSpec(
        object_id=object_id,
        path=str(mesh_path.resolve()),
        scale=float(scale) if scale is not None else 1.0,
        mass=float(mass) if mass is not None else float(default_mass),
        source=source,
        sha256=file_sha256(mesh_path),
    )
