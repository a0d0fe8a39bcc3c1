"""Mesh loading: repairs are reported, every rejection reason is one clear line."""

import sys

import numpy as np
import pytest
import trimesh
from shapes import DATA

from pipeline.model.config import MeshConfig
from pipeline.model.mesh import MeshError, load_mesh, model_from_mesh


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
