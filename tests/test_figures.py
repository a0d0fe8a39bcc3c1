"""Pictures of one object (thesis figures 4.5 and 4.6): the images hold what they claim."""

from __future__ import annotations

import numpy as np
import pytest
from shapes import random_object

import pipeline as toppledb
from pipeline.studies import figures
from schema.vocabulary import STATUS_NAMES

CONFIG = toppledb.Config().with_overrides({
    "contacts.n_contacts": 40, "topple.n_trials": 5, "suction.n_candidates": 20, "suction.n_samples": 5,
})


@pytest.fixture(scope="module")
def evaluated():
    obj = random_object(1)
    return obj, toppledb.evaluate_object(obj, CONFIG)


def _image(path):
    import matplotlib.image

    image = matplotlib.image.imread(path)
    assert image.ndim == 3 and image.shape[0] >= 400 and image.shape[1] >= 400
    assert image[..., :3].std() > 0.05, "not blank"
    return image[..., :3]


def test_graph_figure_has_one_node_per_pose(evaluated, tmp_path):
    from scipy import ndimage

    _, result = evaluated
    drawn = figures.graph_figure(result, tmp_path / "graph.png")
    image = _image(tmp_path / "graph.png")
    magenta = (image[..., 0] > 0.9) & (image[..., 1] < 0.15) & (image[..., 2] > 0.9)
    labels, count = ndimage.label(magenta)
    sizes = np.bincount(labels.ravel())[1:]
    assert drawn["nodes"] == len(result.poses) == int(np.sum(sizes > 20)), "one outlined node per pose"
    edges = figures.topple_edges(result)
    assert drawn["edges"] == len(edges) > 0
    assert all(0 < p <= 1 and a != b for (a, b), p in edges.items())


def test_pushes_figure_and_3d_scene(evaluated, tmp_path):
    import trimesh

    obj, result = evaluated
    drawn = figures.pushes_figure(obj, result, 0, tmp_path / "pushes.png")
    image = _image(tmp_path / "pushes.png")
    colourful = np.ptp(image, axis=2) > 0.3  # the viridis contacts and the colour bar, not greys
    assert colourful.mean() > 0.005
    ok = list(STATUS_NAMES).index("ok")
    assert drawn["contacts"] == int(np.sum(result.actions[0].status == ok)) > 0
    figures.scene_file(obj, result, 0, tmp_path / "object.glb")
    scene = trimesh.load(tmp_path / "object.glb")
    clouds = [g for g in scene.geometry.values() if isinstance(g, trimesh.PointCloud)]
    assert len(clouds) == 1 and len(clouds[0].vertices) == drawn["contacts"]


def test_the_figures_command_reads_millimetres_as_the_dataset_command_does(tmp_path, capsys):
    """``--units mm`` (what a too-large mesh's error suggests) scales the file as --scale 0.001
    does; giving both is refused."""
    import trimesh

    part = tmp_path / "part.stl"
    box = trimesh.creation.box([60.0, 40.0, 100.0])
    box.apply_translation([0, 0, 50.0])
    box.export(part)
    assert figures.main([str(part), "--pose", "0", "--contacts", "20", "--trials", "2", "--out", str(tmp_path / "f")]) == 2
    err = capsys.readouterr().err
    assert err.endswith("use --units mm\n"), "figures has no corpus.toml or scale column to suggest"
    assert figures.main([str(part), "--units", "mm", "--pose", "0", "--contacts", "20", "--trials", "2",
                         "--out", str(tmp_path / "f")]) == 0
    assert (tmp_path / "f" / "pushes_0.png").is_file() and (tmp_path / "f" / "object.glb").is_file()
    with pytest.raises(SystemExit) as refused:
        figures.main([str(part), "--units", "mm", "--scale", "0.001"])
    assert refused.value.code == 2


def test_a_file_that_is_no_mesh_is_bad_input_in_toppledbs_words(tmp_path, capsys):
    (tmp_path / "photo.png").write_bytes(b"\x89PNG\r\n")
    (tmp_path / "junk.ply").write_text("junk\n")
    assert figures.main([str(tmp_path / "photo.png"), "--out", str(tmp_path / "f")]) == 2
    assert capsys.readouterr().err == (
        "error: photo: cannot read photo.png: '.png' is not a mesh format toppledb reads; convert it to OBJ, STL or PLY\n"
    )
    assert figures.main([str(tmp_path / "junk.ply"), "--out", str(tmp_path / "f")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: junk: cannot read junk.ply: not a valid PLY file") and "Not a ply file" not in err
    assert not (tmp_path / "f").exists()


def test_an_arrow_never_reads_probability_zero():
    # Every drawn arrow has P > 0 (topple_edges keeps only those); one below 0.005 would read 0.00.
    assert figures.edge_label(0.004) == "<0.01" and figures.edge_label(1e-9) == "<0.01"
    assert figures.edge_label(0.005) == "0.01" and figures.edge_label(0.954) == "0.95"
