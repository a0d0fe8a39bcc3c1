"""Corpus loading: the committed default list, pybullet_data candidates, directory and
list corpora, and regenerating the default list with the selection rule."""

from __future__ import annotations

import csv
import re
import sys
import tomllib
import types
from pathlib import Path

import numpy as np
import pytest
import trimesh

from pipeline.build import corpus as corpus_module
from pipeline.build import fanout
from pipeline.build.atomic import file_sha256
from pipeline.build.corpus import (
    DEFAULT_LIST,
    Corpus,
    CorpusError,
    Units,
    _unique,
    candidate_specs,
    load_corpus,
    object_id_from_name,
    pybullet_data_dir,
    read_list,
    scan_directory,
    urdf_mesh,
    write_list,
)
from pipeline.build.fanout import SchedulerError
from pipeline.build.selection import DEFAULT_COUNT, regenerate_default
from pipeline.model.config import Config
from schema.layout import check_object_id

CUBE_OBJ = """\
v 0 0 0
v 1 0 0
v 1 1 0
v 0 1 0
v 0 0 1
v 1 0 1
v 1 1 1
v 0 1 1
f 1 3 2
f 1 4 3
f 5 6 7
f 5 7 8
f 1 2 6
f 1 6 5
f 2 3 7
f 2 7 6
f 3 4 8
f 3 8 7
f 4 1 5
f 4 5 8
"""


def test_default_list_is_committed_and_matches_pybullet_data():
    assert DEFAULT_LIST.is_file(), "run `python -m pipeline corpus` to create it"
    with open(DEFAULT_LIST) as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == DEFAULT_COUNT
    assert list(rows[0]) == ["object_id", "source", "path", "scale", "mass", "sha256"]
    ids = [row["object_id"] for row in rows]
    assert len(set(ids)) == len(ids)
    candidate_order = [spec.object_id for spec in candidate_specs(0.25)]
    assert ids == [i for i in candidate_order if i in set(ids)], "kept in candidate order"

    corpus = load_corpus("default", default_mass=0.25)
    assert corpus.problems == {}, "every listed mesh exists in pybullet_data with the listed sha256"
    for row, spec in zip(rows, corpus.specs):
        assert not Path(row["path"]).is_absolute()
        assert Path(spec.path) == pybullet_data_dir() / row["path"]
        assert spec.sha256 == row["sha256"] and spec.scale == float(row["scale"]) and spec.mass == float(row["mass"])


def test_candidates_take_scale_and_mass_from_urdfs():
    specs = {spec.object_id: spec for spec in candidate_specs(default_mass=0.25)}
    randoms = [i for i in specs if i.startswith("random_")]
    assert len(randoms) == 1000
    first = specs["random_000"]
    assert first.path.endswith("random_urdfs/000/000.obj")
    assert (first.scale, first.mass) == (0.015, 0.1)
    assert first.source == "pybullet_data/random_urdfs/000/000.urdf"
    duck = specs["duck"]
    assert duck.path.endswith("duck.obj") and (duck.scale, duck.mass) == (0.05, 0.1)
    assert specs["lego"].path.endswith("lego/lego.obj")
    assert specs["teddy"].scale == 0.1
    assert specs["bunny"].mass == 0.25, "no URDF: the configured default mass"
    assert all(spec.sha256 == file_sha256(spec.path) for spec in list(specs.values())[:10])
    for object_id in specs:
        check_object_id(object_id)


def test_urdf_with_non_uniform_scale_is_refused(tmp_path):
    urdf = tmp_path / "thing.urdf"
    urdf.write_text(
        '<robot name="x"><link name="l"><inertial><mass value="0.3"/></inertial>'
        '<visual><geometry><mesh filename="thing.obj" scale="1 2 1"/></geometry></visual></link></robot>'
    )
    with pytest.raises(CorpusError, match=re.escape("thing.urdf: non-uniform mesh scale '1 2 1'")):
        urdf_mesh(urdf)
    urdf.write_text(urdf.read_text().replace('scale="1 2 1"', 'scale="0.5 0.5 0.5"'))
    assert urdf_mesh(urdf) == (tmp_path / "thing.obj", 0.5, 0.3)


def test_list_file_resolves_paths_and_defaults(tmp_path):
    (tmp_path / "meshes").mkdir()
    (tmp_path / "meshes" / "cube.obj").write_text(CUBE_OBJ)
    listing = tmp_path / "list.csv"
    listing.write_text(
        "path,scale,mass\n"
        "meshes/cube.obj,0.05,0.2\n"
        "# a comment line\n"
        "meshes/cube.obj,,\n"
        "random_urdfs/001/001.obj,0.015,\n"
    )
    # Same stem twice: ids are made unique; the third row is not a pybullet source, so its
    # path is relative to the list and missing.
    corpus = read_list(listing, default_mass=0.3)
    ids = [s.object_id for s in corpus.specs]
    assert ids == ["cube", "cube-2", "obj_001"]
    first, second, third = corpus.specs
    assert Path(first.path) == tmp_path / "meshes" / "cube.obj"
    assert (first.scale, first.mass, second.scale, second.mass) == (0.05, 0.2, 1.0, 0.3)
    assert first.sha256 == file_sha256(tmp_path / "meshes" / "cube.obj")
    assert first.source == "list:list.csv"
    assert set(corpus.problems) == {"obj_001"} and "not found" in corpus.problems["obj_001"]

    listing.write_text("object_id,source,path,sha256\nx1,pybullet_data/random_urdfs,random_urdfs/001/001.obj,abc\n")
    corpus = read_list(listing, default_mass=0.3)
    assert Path(corpus.specs[0].path) == pybullet_data_dir() / "random_urdfs/001/001.obj"
    assert "changed" in corpus.problems["x1"]


@pytest.mark.parametrize(
    "content, message",
    [
        ("file,scale\na.obj,1\n", "'path' column"),
        ("path,scale\na.obj,big\n", "row 2: scale 'big' is not a number"),
        ("path,mass\na.obj,-1\n", "mass must be positive"),
        ("path,mass\na.obj,0\n", "mass must be positive"),
        ("path,colour\na.obj,red\n", re.escape("list.csv: unknown column(s) ['colour']; known: object_id, source, path, scale, mass, sha256")),
        ("object_id,path\nsame,a.obj\nsame,b.obj\n", "list.csv: duplicate object ids"),
        ("object_id,path\n" + "".join(f"{c},{n}.obj\n" for n in range(2) for c in "abcdef"),
         re.escape("duplicate object ids ['a', 'b', 'c', 'd', 'e'] (ids")),
        ("path,mass\na.obj,heavy\n", "list.csv row 2: mass 'heavy' is not a number"),
        ("path,scale\n,1\n", "list.csv row 2: empty path"),
        ("object_id,path\nPart,a.obj\npart,b.obj\n", "duplicate object ids \\['Part', 'part'\\] \\(ids name files"),
        ("object_id,path\nbad/id,a.obj\n", "bad object id"),
        ("path\n", "no objects"),
        ("path,scale,mass\na.obj,0.015,0.1,extra\n", "row 2: 4 fields, more than the header's 3"),
    ],
)
def test_bad_list_files_give_one_line_errors(tmp_path, content, message):
    listing = tmp_path / "list.csv"
    listing.write_text(content)
    with pytest.raises(CorpusError, match=message) as err:
        read_list(listing, default_mass=0.25)
    assert "\n" not in str(err.value)


def test_directory_corpus(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "b.obj").write_text(CUBE_OBJ)
    (tmp_path / "sub" / "007 thing.STL").write_text("solid x\nendsolid x\n")
    (tmp_path / "notes.txt").write_text("not a mesh")
    corpus = scan_directory(tmp_path, default_mass=0.4)
    assert [s.object_id for s in corpus.specs] == ["b", "obj_007_thing"]
    assert all(s.scale == 1.0 and s.mass == 0.4 for s in corpus.specs)
    assert corpus.limit(1).specs == corpus.specs[:1]
    (tmp_path / "empty").mkdir()
    with pytest.raises(CorpusError, match="no OBJ, STL or PLY"):
        scan_directory(tmp_path / "empty", default_mass=0.4)
    # Names that differ only in case name one file on macOS or Windows: the second gets -2.
    (tmp_path / "cased").mkdir()
    (tmp_path / "cased" / "A.obj").write_text(CUBE_OBJ)
    (tmp_path / "cased" / "a.STL").write_text("solid x\nendsolid x\n")
    assert sorted(s.object_id.lower() for s in scan_directory(tmp_path / "cased", default_mass=0.4).specs) == ["a", "a-2"]
    # A file whose own name is a suffix the others would take: every id is still unique.
    (tmp_path / "cased" / "sub").mkdir()
    (tmp_path / "cased" / "sub" / "a-2.obj").write_text(CUBE_OBJ)
    ids = [s.object_id.lower() for s in scan_directory(tmp_path / "cased", default_mass=0.4).specs]
    assert sorted(ids) == ["a", "a-2", "a-2-2"]


def test_a_dangling_link_in_a_directory_corpus_is_listed_as_a_problem(tmp_path):
    # Skipped unseen, a mesh the user meant to build would be missing from the dataset without a word.
    (tmp_path / "b.obj").write_text(CUBE_OBJ)
    (tmp_path / "gone.obj").symlink_to(tmp_path / "nowhere.obj")
    (tmp_path / "fine.obj").symlink_to(tmp_path / "b.obj")
    (tmp_path / "gone.txt").symlink_to(tmp_path / "nowhere.txt")  # not a mesh's name: not listed
    corpus = scan_directory(tmp_path, default_mass=0.4)
    assert [s.object_id for s in corpus.specs] == ["b", "fine", "gone"]
    assert corpus.problems == {"gone": f"mesh file not found: {tmp_path / 'gone.obj'} (a symbolic link to "
                                       f"{tmp_path / 'nowhere.obj'}, which is not there)"}


def test_unknown_corpus_argument():
    with pytest.raises(CorpusError, match="corpus not found"):
        load_corpus("/no/such/corpus", default_mass=0.25)


def test_regenerate_applies_the_selection_rule_in_candidate_order(tmp_path, monkeypatch):
    """The rule itself (pipeline.model.mdp.is_selected) and V_s are the compute side's; here a
    stand-in select_info shows that the list keeps the first selected candidates, in
    candidate order, and that failures are counted, not fatal."""
    config = Config()
    _stand_in_select_info(monkeypatch, config, selected={"duck", "random_001", "random_003", "random_004"})
    out = tmp_path / "corpus.csv"
    counts = regenerate_default(config, out, count=3, limit=10, workers=1, progress=False)
    # A failure's reason is one line of at most 300 characters.
    reason = ("ValueError: broken on two lines " + "x" * 400)[:300]
    assert counts == {"candidates": 10, "failed": 1, "selected": 4, "kept": 3, "failures": {"random_002": reason}}
    corpus = read_list(out, default_mass=0.25)
    assert [s.object_id for s in corpus.specs] == ["duck", "random_001", "random_003"]
    assert corpus.problems == {}
    assert not any(p.name.endswith(".tmp") for p in tmp_path.iterdir())
    # Written as the committed list is: paths relative to pybullet_data, one newline a row.
    with open(out, newline="") as f:
        paths = [row["path"] for row in csv.DictReader(f)]
    assert paths == [Path(s.path).relative_to(pybullet_data_dir()).as_posix() for s in corpus.specs]
    assert b"\r" not in out.read_bytes()


def _stand_in_select_info(monkeypatch, config: Config, selected: set[str]) -> None:
    """A stand-in select_info: V_s and COM heights that pass the rule for ``selected``, an error for
    random_002, and an error for any other configuration than ``config``."""

    def select_info(spec, given):
        if given is not config:
            raise AssertionError("evaluated with another configuration than the one given")
        if spec.object_id == "random_002":
            raise ValueError("broken\n  on two lines " + "x" * 400)
        if spec.object_id in selected:  # high-quality pose with the higher COM
            return np.array([0.9, 0.1]), np.array([0.05, 0.02])
        return np.array([0.1, 0.1]), np.array([0.05, 0.02])

    fake = types.ModuleType("pipeline.model.evaluation")
    fake.select_info = select_info
    monkeypatch.setitem(sys.modules, "pipeline.model.evaluation", fake)


def test_regenerate_shows_its_progress_and_reports_an_unreachable_scheduler(tmp_path, monkeypatch, capsys):
    config = Config()
    _stand_in_select_info(monkeypatch, config, selected={"duck"})
    regenerate_default(config, tmp_path / "corpus.csv", count=1, limit=2, workers=1, progress=True)
    err = capsys.readouterr().err
    assert "selecting: 100%" in err and re.search(r"obj/s|s/obj", err), "candidates counted as objects"
    monkeypatch.setattr(fanout, "CONNECT_TIMEOUT_S", 0.5)
    with pytest.raises(SchedulerError, match=re.escape("cannot connect to the dask scheduler at tcp://127.0.0.1:1")):
        regenerate_default(config, tmp_path / "other.csv", count=1, limit=2, scheduler="tcp://127.0.0.1:1", progress=False)
    assert not (tmp_path / "other.csv").exists()


def _cube_dir(tmp_path: Path, names: list[str]) -> Path:
    for name in names:
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(CUBE_OBJ)
    return tmp_path


def test_directory_sidecar_toml_sets_units_and_mass_with_per_mesh_entries(tmp_path):
    _cube_dir(tmp_path, ["a.obj", "b.obj", "parts/c.obj"])
    (tmp_path / "corpus.toml").write_text(
        'units = "cm"\nmass = 0.2\n[objects."b.obj"]\nscale = 0.05\nmass = 0.3\nobject_id = "bee"\n'
        '[objects."parts/c.obj"]\ndensity = 1000\n'
    )
    specs = {s.object_id: s for s in scan_directory(tmp_path, default_mass=0.4).specs}
    assert (specs["a"].scale, specs["a"].mass) == (0.01, 0.2), "the sidecar's defaults"
    assert (specs["bee"].scale, specs["bee"].mass) == (0.05, 0.3), "a per-mesh entry wins"
    assert specs["c"].scale == 0.01
    assert specs["c"].mass == pytest.approx(1000 * 0.01**3), "density x volume of the scaled unit cube"

    # Flags override the sidecar's defaults but not its per-mesh entries.
    flagged = {s.object_id: s for s in scan_directory(tmp_path, 0.4, Units(scale=0.02, mass=0.5)).specs}
    assert (flagged["a"].scale, flagged["a"].mass) == (0.02, 0.5)
    assert (flagged["bee"].scale, flagged["bee"].mass) == (0.05, 0.3)
    assert flagged["c"].mass == pytest.approx(1000 * 0.02**3), "its own density beats the --mass flag"


def test_directory_sidecar_csv_and_flags_without_sidecar(tmp_path):
    _cube_dir(tmp_path, ["a.obj", "b.obj"])
    plain = {s.object_id: s for s in scan_directory(tmp_path, 0.4, Units(scale=0.0254, density=500)).specs}
    assert plain["a"].scale == 0.0254 and plain["a"].mass == pytest.approx(500 * 0.0254**3)
    (tmp_path / "corpus.csv").write_text("path,units,mass\nb.obj,mm,0.7\n")
    specs = {s.object_id: s for s in scan_directory(tmp_path, default_mass=0.4).specs}
    assert (specs["a"].scale, specs["a"].mass) == (1.0, 0.4)
    assert (specs["b"].scale, specs["b"].mass) == (0.001, 0.7)


@pytest.mark.parametrize(
    "sidecar, text, message",
    [
        ("corpus.toml", 'units = "furlong"\n', "units 'furlong' is not one of mm, cm, in, m"),
        ("corpus.toml", 'units = "mm"\nscale = 0.001\n', "units or scale, not both"),
        ("corpus.toml", "mass = -1\n", "corpus.toml: mass must be positive and finite, got -1"),
        ("corpus.toml", "mass = true\n", "mass True is not a number"),
        ("corpus.toml", 'scale = "big"\n', "corpus.toml: scale 'big' is not a number"),
        ("corpus.toml", "density = 0\n", "corpus.toml: density must be positive and finite, got 0"),
        ("corpus.toml", "colour = 1\n", "corpus.toml: unknown key(s) ['colour']"),
        # The table's and the CSV's own words are no settings: in a setting's place they are unknown too.
        ("corpus.toml", 'path = "meshes"\n', "corpus.toml: unknown key(s) ['path']; known: units, scale, mass, density, object_id"),
        ("corpus.toml", '[objects."a.obj"]\npath = "b.obj"\n', "corpus.toml [objects.'a.obj']: unknown key(s) ['path']"),
        ("corpus.csv", "path,objects\na.obj,b.obj\n", "corpus.csv row 2: unknown key(s) ['objects']"),
        ("corpus.toml", 'object_id = "a"\n', 'corpus.toml: object_id belongs in an [objects."path"] table'),
        ("corpus.toml", "objects = 1\n", 'corpus.toml: [objects."path"] entries must be tables'),
        ("corpus.toml", '[objects]\n"a.obj" = 1\n', 'corpus.toml: [objects."path"] entries must be tables'),
        ("corpus.toml", '[objects."a.obj"]\ndensity = "dense"\n', "corpus.toml [objects.'a.obj']: density 'dense' is not a number"),
        ("corpus.toml", '[objects."missing.obj"]\nmass = 1\n', "names meshes that are not there"),
        ("corpus.toml", "units = \n", "corpus.toml"),
        ("corpus.csv", "path,mass,density\na.obj,1,2\n", "corpus.csv row 2: give mass or density, not both"),
        ("corpus.csv", "path,mass\na.obj,1,2\n", "corpus.csv row 2: 3 fields, more than the header's 2"),
        ("corpus.csv", "path,mass\n,1\n", "corpus.csv row 2: empty path"),
        ("corpus.csv", "path,scale\na.obj,inf\n", "corpus.csv row 2: scale must be positive and finite, got inf"),
    ],
)
def test_bad_sidecars_give_one_line_errors(tmp_path, sidecar, text, message):
    _cube_dir(tmp_path, ["a.obj"])
    (tmp_path / sidecar).write_text(text)
    with pytest.raises(CorpusError, match=re.escape(message)) as err:
        scan_directory(tmp_path, default_mass=0.4)
    assert "\n" not in str(err.value)


def test_unit_flags_are_refused_for_list_corpora():
    with pytest.raises(CorpusError, match="apply to a directory of meshes"):
        load_corpus("default", 0.25, Units(scale=0.001))


def test_a_sidecar_names_its_own_problems(tmp_path):
    _cube_dir(tmp_path, ["a.obj"])
    (tmp_path / "corpus.toml").write_text("units = \n")
    (tmp_path / "corpus.csv").write_text("path,mass\na.obj,1\n")
    with pytest.raises(CorpusError) as err:
        scan_directory(tmp_path, default_mass=0.4)
    assert str(err.value) == f"{tmp_path.resolve()}: both corpus.toml and corpus.csv; keep one"

    # A TOML syntax error: the parser's own reason, on one line, after the file's path.
    (tmp_path / "corpus.csv").unlink()
    try:
        tomllib.loads("units = \n")
    except tomllib.TOMLDecodeError as parser:
        reason = " ".join(str(parser).split())
    with pytest.raises(CorpusError) as err:
        scan_directory(tmp_path, default_mass=0.4)
    assert str(err.value) == f"{tmp_path.resolve() / 'corpus.toml'}: {reason}"

    # A CSV sidecar that is not text in this locale's encoding: the decoder's reason, after the path.
    (tmp_path / "corpus.toml").unlink()
    (tmp_path / "corpus.csv").write_bytes(b"path,mass\na.obj,\xff\xfe1\n")
    try:
        (tmp_path / "corpus.csv").read_text()
    except UnicodeDecodeError as decoder:
        reason = str(decoder)
    with pytest.raises(CorpusError) as err:
        scan_directory(tmp_path, default_mass=0.4)
    assert str(err.value) == f"{tmp_path.resolve() / 'corpus.csv'}: {reason}"


def test_a_csv_sidecar_takes_empty_cells_as_not_set(tmp_path):
    # Each row fills one of units/scale and one of mass/density: the empty cell is no value, not a second one.
    _cube_dir(tmp_path, ["a.obj", "b.obj"])
    (tmp_path / "corpus.csv").write_text("path,units,scale,mass,density\na.obj,,0.05,,1000\nb.obj,cm,,0.7,\n")
    specs = {s.object_id: s for s in scan_directory(tmp_path, default_mass=0.4).specs}
    assert (specs["a"].scale, specs["a"].mass) == (0.05, pytest.approx(1000 * 0.05**3))
    assert (specs["b"].scale, specs["b"].mass) == (0.01, 0.7)


def test_density_weighs_the_mesh_or_its_hull_and_an_unreadable_mesh_keeps_the_default_mass(tmp_path):
    # A closed ring: its own volume, well below its hull's.
    ring = trimesh.creation.annulus(r_min=0.02, r_max=0.05, height=0.03)
    ring.export(tmp_path / "ring.obj")
    closed = trimesh.load(tmp_path / "ring.obj", force="mesh")
    assert closed.is_volume and closed.volume < 0.9 * closed.convex_hull.volume
    # The ring without its top: two holes no repair fills, so its hull is what is weighed (the surface
    # integral of an open mesh is no volume; here it happens to give the closed ring's).
    trimesh.Trimesh(ring.vertices, ring.faces[ring.face_normals[:, 2] < 0.9]).export(tmp_path / "open.obj")
    hull = trimesh.load(tmp_path / "open.obj", force="mesh").convex_hull.volume
    (tmp_path / "zgarbage.obj").write_text("this is not a mesh\n")
    (tmp_path / "corpus.toml").write_text('density = 800\n[objects."open.obj"]\nscale = 2\n')
    specs = {s.object_id: s for s in scan_directory(tmp_path, default_mass=0.4).specs}
    assert specs["ring"].mass == pytest.approx(800 * closed.volume, rel=1e-9)
    assert specs["open"].mass == pytest.approx(800 * 2**3 * hull, rel=1e-9), "the open ring's hull, scaled"
    assert specs["zgarbage"].mass == 0.4, "no volume to weigh: the default mass (the build then says why)"


def test_a_directory_corpus_is_named_by_its_path_and_ordered_by_relative_path(tmp_path):
    # "a-b/..." sorts before "a/..." as text ('-' < '/'), after it part by part: the order is the text's,
    # the same the sidecar's keys are written in, so which of two equal stems gets "-2" does not depend on it.
    _cube_dir(tmp_path, ["a/x.obj", "a-b/x.obj", "a0.obj"])
    corpus = scan_directory(tmp_path, default_mass=0.4)
    relative = [Path(s.path).relative_to(tmp_path.resolve()).as_posix() for s in corpus.specs]
    assert relative == sorted(relative) == ["a-b/x.obj", "a/x.obj", "a0.obj"]
    assert [s.object_id for s in corpus.specs] == ["x", "x-2", "a0"]
    assert corpus.name == str(tmp_path.resolve())
    assert {s.source for s in corpus.specs} == {f"dir:{tmp_path.resolve().name}"}

    (tmp_path / "corpus.toml").write_text('[objects."a0.obj"]\nobject_id = "bad/id"\n')
    with pytest.raises(CorpusError, match=re.escape(f"{tmp_path.resolve()}: bad object id")):
        scan_directory(tmp_path, default_mass=0.4)
    # Entries for meshes that are not there: the first three are named, in order.
    (tmp_path / "corpus.toml").write_text("".join(f'[objects."{n}.obj"]\nmass = 1\n' for n in "pqrs"))
    with pytest.raises(CorpusError) as err:
        scan_directory(tmp_path, default_mass=0.4)
    assert str(err.value).endswith("not there: ['p.obj', 'q.obj', 'r.obj']")


def _urdf(path: Path, geometry: str, inertial: str = '<inertial><mass value="0.3"/></inertial>') -> Path:
    path.write_text(f'<robot name="x"><link name="l">{inertial}{geometry}</link></robot>')
    return path


def test_urdf_meshes_their_fallbacks_and_refusals(tmp_path):
    visual = '<visual><geometry><mesh filename="seen.obj"/></geometry></visual>'
    collision = '<collision><geometry><mesh filename="hull.obj" scale="2 2 2"/></geometry></collision>'
    assert urdf_mesh(_urdf(tmp_path / "a.urdf", collision + visual)) == (tmp_path / "seen.obj", None, 0.3), "visual first"
    assert urdf_mesh(_urdf(tmp_path / "b.urdf", collision)) == (tmp_path / "hull.obj", 2.0, 0.3), "else the collision mesh"
    assert urdf_mesh(_urdf(tmp_path / "c.urdf", visual, inertial="")) == (tmp_path / "seen.obj", None, None), "no mass given"
    assert urdf_mesh(_urdf(tmp_path / "d.urdf", visual, '<inertial><mass value="0"/></inertial>'))[2] is None, "static body"
    with pytest.raises(CorpusError, match=r"^e\.urdf: no mesh geometry$"):
        urdf_mesh(_urdf(tmp_path / "e.urdf", '<visual><geometry><box size="1 1 1"/></geometry></visual>'))
    (tmp_path / "f.urdf").write_text("<robot>")
    with pytest.raises(CorpusError, match=re.escape(f"cannot parse {tmp_path / 'f.urdf'}: ")):
        urdf_mesh(tmp_path / "f.urdf")


def test_candidates_of_a_pybullet_data_tree_without_some_named_urdfs(tmp_path):
    # duck's URDF (listed before teddy's) is missing: it is skipped, and the later named meshes still come.
    (tmp_path / "bunny.obj").write_text(CUBE_OBJ)
    (tmp_path / "teddy.obj").write_text(CUBE_OBJ)
    _urdf(tmp_path / "teddy_vhacd.urdf", '<visual><geometry><mesh filename="teddy.obj" scale="0.1 0.1 0.1"/></geometry></visual>')
    (tmp_path / "random_urdfs" / "007").mkdir(parents=True)
    (tmp_path / "random_urdfs" / "007" / "007.obj").write_text(CUBE_OBJ)
    _urdf(tmp_path / "random_urdfs" / "007" / "007.urdf", '<visual><geometry><mesh filename="007.obj"/></geometry></visual>',
          inertial="")
    specs = candidate_specs(default_mass=0.25, root=tmp_path)
    assert [s.object_id for s in specs] == ["bunny", "teddy", "random_007"]
    bunny, teddy, random = specs
    assert (bunny.scale, bunny.mass, bunny.source) == (0.1, 0.25, "pybullet_data")
    assert (teddy.scale, teddy.mass, teddy.source) == (0.1, 0.3, "pybullet_data/teddy_vhacd.urdf")
    assert (random.scale, random.mass) == (1.0, 0.25), "no scale or mass in its URDF: 1 and the default mass"
    assert random.source == "pybullet_data/random_urdfs/007/007.urdf"
    assert random.path == str((tmp_path / "random_urdfs" / "007" / "007.obj").resolve())


def test_a_list_written_with_absolute_paths_reads_back_the_same(tmp_path):
    corpus = scan_directory(_cube_dir(tmp_path / "meshes", ["a.obj", "sub/b.obj"]), default_mass=0.4)
    write_list(corpus.specs, tmp_path / "list.csv", root=None)
    assert b"\r" not in (tmp_path / "list.csv").read_bytes(), "one newline a row, as the committed default list"
    again = read_list(tmp_path / "list.csv", default_mass=0.9)
    assert again.specs == corpus.specs and again.problems == {}


def test_list_files_read_as_written(tmp_path, monkeypatch):
    (tmp_path / "a.obj").write_text(CUBE_OBJ)
    (tmp_path / "b.obj").write_text(CUBE_OBJ)
    listing = tmp_path / "list.csv"
    # An indented comment is a comment too; a row without mass takes the default one.
    listing.write_text(f"path,mass,sha256\n  # b.obj is listed below\na.obj,0.2,\nb.obj,,{'0' * 64}\nc.obj,,\n")
    corpus = load_corpus(str(listing), default_mass=0.3)
    assert corpus.name == str(listing.resolve())
    assert [(s.object_id, s.mass) for s in corpus.specs] == [("a", 0.2), ("b", 0.3), ("c", 0.3)]
    listed, found = "0" * 12, file_sha256(tmp_path / "b.obj")[:12]
    assert corpus.problems == {
        "b": f"mesh file changed since the corpus was listed: sha256 {found}..., listed {listed}...",
        "c": f"mesh file not found: {tmp_path / 'c.obj'}",
    }
    # The first of them, with only its own problems.
    first = corpus.limit(1)
    assert (first.name, first.specs, first.problems) == (corpus.name, corpus.specs[:1], {})
    last_two = Corpus(corpus.name, corpus.specs[1:], corpus.problems).limit(1)
    assert last_two.problems == {"b": corpus.problems["b"]} and corpus.limit(None) is corpus
    # A mesh that is there but cannot be read (its checksum comes back empty).
    monkeypatch.setattr(corpus_module, "file_sha256", lambda path: "")
    assert read_list(listing, 0.3).problems["a"] == f"mesh file cannot be read: {tmp_path / 'a.obj'}"

    listing.write_bytes(b"path\n\xff\xfe.obj\n")
    try:
        listing.read_text()
    except UnicodeDecodeError as decoder:
        reason = str(decoder)
    with pytest.raises(CorpusError) as err:
        read_list(listing, 0.3)
    assert str(err.value) == f"cannot read corpus list {listing.resolve()}: {reason}"


def test_the_default_and_pybullet_data_corpora_by_name(monkeypatch):
    default = load_corpus("default", default_mass=0.25)
    assert default.name == "default" and len(default.specs) == DEFAULT_COUNT
    every = load_corpus("pybullet_data", default_mass=0.3)
    assert every.name == "pybullet_data" and every.problems == {}
    assert every.specs == candidate_specs(default_mass=0.3)
    assert every.specs[0].object_id == "bunny" and every.specs[0].mass == 0.3, "no URDF: the mass given"
    with pytest.raises(CorpusError) as err:
        load_corpus("default", 0.25, Units(scale=0.001))
    assert str(err.value) == ("--units, --scale, --mass and --density apply to a directory of meshes; "
                              "a list file has scale and mass columns")
    monkeypatch.setattr(corpus_module, "DEFAULT_LIST", Path("/no/such/corpus_default.csv"))
    with pytest.raises(CorpusError) as err:
        load_corpus("default", 0.25)
    assert str(err.value) == "default corpus list /no/such/corpus_default.csv is missing; run `toppledb corpus`"
    monkeypatch.setitem(sys.modules, "pybullet_data", None)  # import pybullet_data now raises ImportError
    with pytest.raises(CorpusError) as err:
        pybullet_data_dir()
    assert str(err.value) == "pybullet_data is not installed (pip install pybullet)"


def test_ids_derived_from_file_names():
    assert object_id_from_name("") == "obj"
    assert object_id_from_name("x" * 200) == "x" * 120, "cut to 120 characters"
    assert object_id_from_name("a b/c") == "a_b_c"
    # Words a reader would type as a number or boolean, in any case, and digits first get a prefix.
    assert [object_id_from_name(n) for n in ("True", "NaN", "inf", "7up", "Truly")] == [
        "obj_True", "obj_NaN", "obj_inf", "obj_7up", "Truly"]
    assert _unique(["x", "x", "X", "x-2"]) == ["x", "x-2", "X-3", "x-2-2"], "the smallest free suffix, case ignored"
