"""Mesh loading: repairs are reported, every rejection reason is one clear line."""

import sys

import numpy as np
import pytest
import trimesh
from shapes import DATA

from pipeline.model.config import MeshConfig
from pipeline.model.mesh import MeshError, _one_line, load_mesh, model_from_mesh, unit_hint


def test_loads_corpus_mesh_in_metres_with_mass():
    obj = load_mesh(f"{DATA}/random_urdfs/000/000.obj", scale=0.015, mass=0.1)
    assert obj.mass == 0.1
    assert 0.05 < obj.mesh.extents.max() < 0.2
    assert obj.hull.contains([obj.center_mass])[0]


def test_default_mass_and_duplicate_vertices_repaired():
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    soup = trimesh.Trimesh(box.triangles.reshape(-1, 3), np.arange(36).reshape(-1, 3), process=False)
    obj = model_from_mesh(soup, name="soup")
    assert obj.mass == MeshConfig().default_mass
    assert any("merged" in r for r in obj.repairs)
    assert np.isclose(obj.mesh.volume, 1e-3)


def test_open_mesh_uses_hull_centre_of_mass_and_says_so():
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-1], process=False)  # every corner kept
    obj = model_from_mesh(open_box, name="open", config=MeshConfig(fill_holes=False))
    assert any("convex hull" in r for r in obj.repairs)
    assert np.allclose(obj.center_mass, 0, atol=1e-9)


def _reason(mesh, **kwargs):
    with pytest.raises(MeshError) as err:
        model_from_mesh(mesh, name="bad", **kwargs)
    message = str(err.value)
    assert "\n" not in message and message.startswith("bad: ")
    return message


def test_rejects_empty_mesh():
    assert "empty mesh" in _reason(trimesh.Trimesh())


def test_rejects_non_finite_vertices():
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    vertices = box.vertices.copy()
    vertices[0, 0] = np.nan
    assert "non-finite vertex" in _reason(trimesh.Trimesh(vertices, box.faces, process=False))


def test_rejects_flat_mesh_as_zero_volume():
    flat = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0], [0.1, 0.1, 0]], [[0, 1, 2], [1, 3, 2]], process=False)
    assert "zero or negative volume" in _reason(flat)


def test_rejects_centre_of_mass_outside_hull():
    box = trimesh.creation.box([0.1, 0.1, 0.1])
    assert "outside the convex hull" in _reason(box, center_mass=[0.2, 0, 0])


def test_rejects_too_small_and_too_large():
    assert "too small" in _reason(trimesh.creation.box([0.001] * 3))
    assert "too large" in _reason(trimesh.creation.box([2.0, 0.1, 0.1]))
    assert "too large" in _reason(trimesh.creation.box([0.1] * 3), scale=10.0)


def test_rejects_bad_mass():
    assert "mass must be a positive" in _reason(trimesh.creation.box([0.1] * 3), mass=-1.0)


def test_unreadable_file_is_one_line(tmp_path):
    path = tmp_path / "broken.obj"
    path.write_text("this is not an obj file\nf 1 2 3\n")
    with pytest.raises(MeshError) as err:
        load_mesh(path)
    assert str(err.value).startswith("broken: ") and "\n" not in str(err.value)


def test_stl_and_ply_round_trip(tmp_path):
    box = trimesh.creation.box([40.0, 60.0, 100.0])  # millimetres in the file
    for suffix in ("stl", "ply", "obj"):
        path = tmp_path / f"box.{suffix}"
        box.export(path)
        obj = load_mesh(path, scale=0.001, mass=0.3)
        assert obj.name == "box" and obj.mass == 0.3
        assert np.allclose(sorted(obj.mesh.extents), [0.04, 0.06, 0.1])
        assert np.isclose(obj.mesh.volume, 0.04 * 0.06 * 0.1)


@pytest.mark.parametrize("suffix", ["obj", "stl"])
@pytest.mark.parametrize("without_charset_detector", [False, True])
def test_random_bytes_name_the_file_not_a_module(tmp_path, monkeypatch, suffix, without_charset_detector):
    if without_charset_detector:  # trimesh imports it only for non-UTF-8 bytes
        monkeypatch.setitem(sys.modules, "charset_normalizer", None)
    path = tmp_path / f"noise.{suffix}"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 3000, dtype=np.uint8).tobytes())
    with pytest.raises(MeshError) as err:
        load_mesh(path)
    message = str(err.value)
    assert message.startswith(f"noise: ") and message.count("noise:") == 1 and "\n" not in message
    assert f"not a valid {suffix.upper()} file" in message and "module" not in message


def test_empty_and_missing_files_say_so(tmp_path):
    (tmp_path / "empty.obj").write_bytes(b"")
    with pytest.raises(MeshError, match="empty.obj: no triangles, the file is empty"):
        load_mesh(tmp_path / "empty.obj")
    with pytest.raises(MeshError, match="mesh file not found"):
        load_mesh(tmp_path / "gone.obj")


def test_size_errors_name_the_likely_unit():
    millimetres = trimesh.creation.box([120.0, 80.0, 40.0])  # a 12 cm part drawn in mm, read as metres
    assert "probably in millimetres: use --units mm" in _reason(millimetres)
    inches = trimesh.creation.box([8.0, 3.0, 3.0])  # 8 in = 20 cm, or 8 cm
    assert "probably in centimetres or inches" in _reason(inches)
    assert "units" not in _reason(trimesh.creation.box([3000.0, 1, 1])), "no unit makes a 3 km object fit"
    assert "check the file's units" in _reason(trimesh.creation.box([0.1] * 3), scale=0.01)


def _box(size=(0.05, 0.06, 0.07)):
    return trimesh.creation.box(size)


@pytest.mark.parametrize("case, expected", [
    ("clean", []),
    ("soup", ["merged 28 duplicate vertices"]),  # 12 separate triangles: 36 corners for 8
    ("duplicate and degenerate faces", ["removed 2 degenerate or duplicate faces"]),
    ("one face wound backwards", ["fixed face winding and normals"]),
    ("one face missing", ["filled holes"]),
])
def test_the_repair_log_says_what_was_repaired_and_nothing_else(case, expected):
    box = _box()
    faces = box.faces.copy()
    vertices = box.vertices
    if case == "soup":
        vertices, faces = box.triangles.reshape(-1, 3), np.arange(36).reshape(-1, 3)
    elif case == "duplicate and degenerate faces":
        faces = np.vstack([faces, faces[:1], [[0, 0, 1]]])
    elif case == "one face wound backwards":
        faces[0] = faces[0][::-1]
    elif case == "one face missing":
        faces = faces[1:]
    obj = model_from_mesh(trimesh.Trimesh(vertices, faces, process=False))
    assert obj.repairs == expected
    assert obj.mesh.is_watertight and np.isclose(obj.mesh.volume, 0.05 * 0.06 * 0.07)


def test_a_file_is_read_as_written_and_repaired_with_a_record(tmp_path):
    # trimesh must not merge the file's vertices on load: the repair log would lose them.
    box = _box()
    lines = [f"v {x} {y} {z}" for x, y, z in box.triangles.reshape(-1, 3)]
    lines += [f"f {3 * i + 1} {3 * i + 2} {3 * i + 3}" for i in range(12)]
    (tmp_path / "soup.obj").write_text("\n".join(lines) + "\n")
    obj = load_mesh(tmp_path / "soup.obj", mass=0.3)
    assert obj.repairs == ["merged 28 duplicate vertices"]
    np.testing.assert_allclose(obj.mesh.extents, [0.05, 0.06, 0.07])  # scale 1 unless told
    inside = [0.01, -0.02, 0.005]
    chosen = load_mesh(tmp_path / "soup.obj", center_mass=inside, scale=2.0)
    np.testing.assert_allclose(chosen.center_mass, inside)
    np.testing.assert_allclose(chosen.mesh.extents, [0.1, 0.12, 0.14])
    with pytest.raises(MeshError, match="too small for a tabletop"):
        load_mesh(tmp_path / "soup.obj", config=MeshConfig(min_extent=0.1))


@pytest.mark.parametrize("mass", [0.0, -1.0, float("nan")])
def test_rejects_a_mass_that_is_not_positive(mass):
    assert f"mass must be a positive number of kg, got {float(mass)}" in _reason(_box(), mass=mass)


@pytest.mark.parametrize("scale", [0.0, -0.01, float("nan"), float("inf")])
def test_rejects_a_scale_that_is_not_positive_and_finite(scale):
    assert f"scale must be positive, got {scale}" in _reason(_box(), scale=scale)


def test_one_triangle_is_flat_not_empty():
    triangle = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.02]], [[0, 1, 2]], process=False)
    message = _reason(triangle)
    assert "zero volume: the mesh is flat or degenerate (QH" in message  # qhull's reason, cut before its trace
    assert "While executing" not in message


def test_a_chosen_centre_of_mass_inside_is_kept_and_one_outside_is_named():
    inside = [0.02, -0.02, 0.03]
    np.testing.assert_allclose(model_from_mesh(_box(), center_mass=inside).center_mass, inside)
    assert "centre of mass [0.1235, 0.0, 0.01] is outside the convex hull" in _reason(_box(), center_mass=[0.123456, 0, 0.01])


def test_an_error_is_one_line_of_at_most_200_characters_or_its_type():
    assert _one_line(ValueError("first line\n   second\tline ")) == "first line second line"
    assert _one_line(ValueError("x" * 500)) == "x" * 200
    assert _one_line(KeyError()) == "KeyError"


def test_no_unit_hint_when_no_unit_would_fit():
    config = MeshConfig()
    assert unit_hint(1e-9, config) == ""  # too small in any unit
    assert unit_hint(1e6, config) == ""  # too large in any unit
    assert "check the file's units" in unit_hint(0.001, config)  # 1 mm: 3.9 cm if it were inches


def test_the_unit_hint_names_the_likeliest_unit_first():
    # pybullet_data's random_urdfs/011 is 10.16 file units across: 1 cm in millimetres, 10 cm in
    # centimetres, 26 cm in inches; all three fit the range, and 10 cm sits nearest its middle.
    hint = unit_hint(10.16, MeshConfig())
    assert hint == "; the file is probably in centimetres or inches or millimetres: use --units cm"
    assert unit_hint(80.0, MeshConfig()).endswith("probably in millimetres: use --units mm")  # 8 cm; 80 cm in cm is too large


def test_a_mesh_of_degenerate_triangles_only_is_refused_with_the_reason():
    # Repair removes every zero-area face; what is left has no extent to measure.
    collinear = trimesh.Trimesh([[0, 0, 0], [0.05, 0, 0], [0.1, 0, 0]], [[0, 1, 2]], process=False)
    assert "no triangle with an area: every face is degenerate" in _reason(collinear)
    repeated = trimesh.Trimesh([[0, 0, 0], [0.1, 0, 0]], [[0, 1, 1], [1, 0, 0]], process=False)
    assert "no triangle with an area" in _reason(repeated)


def test_rejects_a_chosen_centre_of_mass_that_is_not_finite():
    assert "non-finite centre of mass" in _reason(_box(), center_mass=[np.nan, 0.0, 0.0])


def test_a_point_cloud_file_has_no_triangles(tmp_path):
    header = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    (tmp_path / "points.ply").write_text(header + "0 0 0\n1 0 0\n0 1 0\n")
    (tmp_path / "points.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n")
    trimesh.PointCloud(np.random.default_rng(0).random((5, 3))).export(tmp_path / "binary.ply", encoding="binary")
    for file, count in (("points.ply", 3), ("points.obj", 4), ("binary.ply", 5)):
        stem = file.split(".")[0]
        with pytest.raises(MeshError, match=rf"{stem}: cannot read {file}: a point cloud \({count} vertices, no faces\), not a surface"):
            load_mesh(tmp_path / file)


@pytest.mark.parametrize("file, content, reason", [
    ("photo.png", b"\x89PNG\r\n", "'.png' is not a mesh format toppledb reads; convert it to OBJ, STL or PLY"),
    ("part.off", b"OFF\n3 1 0\n", "'.off' is not a mesh format toppledb reads; convert it to OBJ, STL or PLY"),
    ("part", b"v 0 0 0\n", "no file extension to tell its format; convert it to OBJ, STL or PLY"),
    ("junk.ply", b"junk\n", "not a valid PLY file (text without vertices and faces); export it again as OBJ, STL or PLY"),
    ("cut.ply", b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nend_header\n1\n",
     "a damaged PLY file (its header reads as PLY, its contents do not); export it again as OBJ, STL or PLY"),
])
def test_an_unsupported_or_unreadable_file_is_named_in_toppledbs_words(tmp_path, file, content, reason):
    """Not trimesh's "file_type 'png' not supported" or "Not a ply file!": the file, what is
    wrong with it and the formats toppledb reads."""
    (tmp_path / file).write_bytes(content)
    with pytest.raises(MeshError) as err:
        load_mesh(tmp_path / file)
    assert str(err.value) == f"{file.split('.')[0]}: cannot read {file}: {reason}"


def test_the_formats_read_are_those_a_directory_corpus_picks_up():
    from pipeline.build.corpus import MESH_SUFFIXES as corpus_suffixes
    from pipeline.model.mesh import MESH_SUFFIXES

    assert corpus_suffixes == MESH_SUFFIXES


def test_the_unit_hint_names_the_corpus_only_for_a_corpus_object():
    """A dataset build can set units in corpus.toml or a scale column; ``add`` and ``figures`` only by flags."""
    millimetres = trimesh.creation.box([120.0, 80.0, 40.0])
    assert _reason(millimetres).endswith("probably in millimetres: use --units mm")
    assert _reason(millimetres, corpus_hint=True).endswith('use --units mm (or units = "mm" in corpus.toml, or a scale column)')
    assert unit_hint(0.001, MeshConfig()) == "; check the file's units (--units or --scale)"
    assert unit_hint(0.001, MeshConfig(), corpus=True) == "; check the file's units (--units, --scale, or the corpus's scale)"


@pytest.mark.parametrize("error", [PermissionError(13, "Permission denied"), IsADirectoryError(21, "Is a directory")])
def test_a_file_that_cannot_be_opened_is_one_line_not_a_traceback(tmp_path, monkeypatch, error):
    # As root (CI) chmod 000 is no obstacle, so the loader is made to meet the error itself.
    path = tmp_path / "box.obj"
    path.write_text("v 0 0 0\n")

    def refuse(*args, **kwargs):
        raise error

    monkeypatch.setattr(trimesh, "load", refuse)
    with pytest.raises(MeshError, match=rf"^box: cannot read box\.obj: {error.strerror.lower()}$"):
        load_mesh(path)
