"""The boosted map of P(topple) (docs/MODEL.md C.19)."""

from __future__ import annotations

import json
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import pipeline.model.topple as topple_module
from pipeline.build import shards
from pipeline.build.corpus import ObjectSpec
from pipeline.model.boosted_map import (
    FEATURES,
    BoostedMapError,
    _skip_shared_splits,
    boosted_features,
    boosted_probability,
    fit_trees,
    fitted_logit,
    load_trees,
    map_boosted_rows,
    map_file,
    trees_from_dict,
)
from pipeline.model.config import Config, ContactConfig
from pipeline.model.edges import edge_geometry
from pipeline.model.feature_map import FORCE_RATIO_RANGE, LOGIT_FLOOR, landing_rows, needed_force_ratio, pose_features
from pipeline.model.outcomes import Actions
from pipeline.model.rng import stream
from pipeline.model.topple import evaluate_pose
from pipeline.studies.logreader import read_log
from pipeline.studies.scoring import Scorer
from schema.frames import transform_points
from schema.vocabulary import STATUS_OK
from tests.test_smoothing import pose_and_candidates  # noqa: F401 (fixture: random_object(3), pose 2, 80 contacts)
from tests.test_validation import model_logs  # noqa: F401 (fixture)

F = len(FEATURES)
SPEC = ObjectSpec(object_id="box", path="box.stl", scale=1.0, mass=0.25, sha256="0" * 64, source="test")


def _stump(feature, threshold, left_value, right_value, missing_left=True):
    """One split: node 0 on ``feature``, leaves 1 (<= threshold) and 2."""
    return {"feature": [feature, 0, 0], "threshold": [threshold, 0.0, 0.0], "left": [1, 0, 0], "right": [2, 0, 0],
            "missing_left": [missing_left, False, False], "leaf": [False, True, True], "value": [0.0, left_value, right_value]}


def _map(*trees, baseline=-0.5):
    return {"features": list(FEATURES), "baseline": baseline, "trees": list(trees)}


def _sigmoid(x):
    return 1.0 / (1.0 + np.exp(-x))


def test_two_stumps_and_a_deeper_tree_sum_their_leaves_by_hand():
    deeper = {"feature": [0, 3, 0, 0, 0], "threshold": [0.0, 1.0, 0, 0, 0], "left": [1, 3, 0, 0, 0], "right": [2, 4, 0, 0, 0],
              "missing_left": [False, True, False, False, False], "leaf": [False, False, True, True, True],
              "value": [0.0, 0.0, 0.7, -0.3, 0.2]}
    trees = trees_from_dict(_map(_stump(0, 0.0, -1.0, 1.0), _stump(5, 0.5, 0.25, -0.25, missing_left=False), deeper))
    assert list(trees.roots) == [0, 3, 6] and len(trees.leaf) == 11, "one node array, tree after tree"
    x = np.zeros((4, F))
    x[:, 0] = [-1.0, 1.0, -1.0, 0.0]  # the last one exactly on the threshold: <= goes left
    x[:, 5] = [0.0, 1.0, np.nan, 0.5]  # NaN goes right in the second stump
    x[:, 3] = [0.0, 0.0, 5.0, np.nan]  # NaN goes left in the deeper tree's second split
    expected = -0.5 + np.array([-1.0 + 0.25 - 0.3, 1.0 - 0.25 + 0.7, -1.0 - 0.25 + 0.2, -1.0 + 0.25 - 0.3])
    assert np.allclose(boosted_probability(x, trees), _sigmoid(expected), rtol=0, atol=1e-15)


def test_fitted_trees_predict_what_scikit_learn_predicts():
    pytest.importorskip("sklearn")
    rng = np.random.default_rng(0)
    x = rng.normal(size=(600, F))
    x[rng.random((600, F)) < 0.05] = np.nan
    rate = _sigmoid(1.5 * np.nan_to_num(x[:, 0]) - np.nan_to_num(x[:, 7]) * np.nan_to_num(x[:, 2]))
    repeats = np.full(600, 10)
    observed = rng.binomial(10, rate) / 10
    fitted = fit_trees(x, observed, repeats, seed=1, max_iter=40, min_samples_leaf=20)
    trees = trees_from_dict(json.loads(json.dumps(fitted)))  # through JSON, as a file carries them
    q = boosted_probability(x, trees)
    assert np.corrcoef(q, rate)[0, 1] > 0.8, "the trees learned the rate"

    from sklearn.ensemble import HistGradientBoostingClassifier

    from pipeline.model.boosted_map import FIT_PARAMS

    toppled = np.round(observed * repeats)
    weight = np.concatenate([toppled, repeats - toppled])
    keep = weight > 0
    model = HistGradientBoostingClassifier(**{**FIT_PARAMS, "max_iter": 40, "min_samples_leaf": 20, "random_state": 1})
    model.fit(np.vstack([x, x])[keep], np.r_[np.ones(600), np.zeros(600)][keep], sample_weight=weight[keep])
    assert np.allclose(q, model.predict_proba(x)[:, 1], rtol=0, atol=1e-12)


def _shared_subtree(d):
    """A second tree whose nodes 1 and 2 both point at leaves 3 and 4 (a walk ends, but no tree)."""
    d["trees"].append({"feature": [0, 1, 2, 0, 0], "threshold": [0.0] * 5, "left": [1, 3, 3, 0, 0], "right": [2, 4, 4, 0, 0],
                       "missing_left": [True] * 5, "leaf": [False, False, False, True, True], "value": [0.0] * 5})


@pytest.mark.parametrize("change, message", [
    (lambda d: d.update(features=list(FEATURES[:-1])), rf"its features are not this version's \({F}, from logit_p\)$"),
    (lambda d: d.pop("features"), rf"its features are not this version's \({F}, from logit_p\)$"),
    (lambda d: d.update(features=None), "features are not this version's"),
    (lambda d: d.update(features=5), "features are not this version's"),
    (lambda d: d.update(baseline=10**400), "baseline is not a finite number"),  # JSON's integer, past any float
    (lambda d: d["trees"][0].update(feature=[10**20, 0, 0]), "tree 0: feature holds entries out of range"),
    (lambda d: d["trees"][0].update(value=[0.0, 10**400, 1.0]), "tree 0: value holds entries out of range"),
    (lambda d: d["trees"][0].update(left=[1, 0, 0], right=[1, 0, 0]), "tree 0 reaches node 1 twice"),  # both children one leaf
    (_shared_subtree, "tree 1 reaches node 4 twice$"),  # counted within tree 1, which starts at node 3
    (lambda d: d["trees"][0].update(threshold=[True, 0.0, 0.0]), "threshold holds entries that are not float"),
    (lambda d: d["trees"][0].update(value=[0.0, "1.0", 1.0]), "value holds entries that are not float"),
    (lambda d: d.update(baseline=float("nan")), "baseline is not a finite number"),
    (lambda d: d.update(trees=[]), "no list of trees"),
    (lambda d: d["trees"][0].update(left=[7, 0, 0]), "points outside its tree"),
    (lambda d: d["trees"][0].update(feature=[F, 0, 0]), "splits on no feature"),
    (lambda d: d["trees"][0].update(left=[0, 0, 0]), "reaches node 0 twice"),
    (lambda d: d["trees"][0].update(left=[3, 0, 0]), "points outside its tree"),  # the first index past the tree
    (lambda d: d["trees"][0].update(right=[-1, 0, 0]), "points outside its tree"),
    (lambda d: d["trees"][0].update(feature=[-1, 0, 0]), "splits on no feature"),
    (lambda d: d["trees"][0].update(value=[0.0, float("inf"), 1.0]), "leaf's value is not finite"),
    (lambda d: d["trees"][0].update(threshold=[float("nan"), 0.0, 0.0]), "threshold is not finite"),
    (lambda d: d["trees"][0].pop("value"), "tree 0 is not an object with the lists feature, threshold, left, right, missing_left, leaf, value$"),
    (lambda d: d["trees"][0].update(left=1), "left is not a list of nodes"),
    (lambda d: d["trees"][0].update(left=[1, 0]), "differ in length"),
    (lambda d: d["trees"][0].update(threshold=[0.0] * 4), "differ in length"),  # would shift every later tree
    (lambda d: d["trees"].insert(0, {k: [] for k in d["trees"][0]}), "tree 0: feature is not a list of nodes"),
    (lambda d: d["trees"].append({k: [] for k in d["trees"][0]}), "tree 1: feature is not a list of nodes"),
    (lambda d: d["trees"][0].update(missing_left=["false", True, True]), "missing_left holds entries that are not bool"),
    (lambda d: d["trees"][0].update(left=[1.5, 0, 0]), "left holds entries that are not int"),
    (lambda d: d.update(trees={"a": 1}), "no list of trees"),
    (lambda d: d.update(baseline="0.1"), "baseline is not a finite number"),
    (lambda d: d.update(baseline=True), "baseline is not a finite number"),
])
def test_a_file_that_is_no_boosted_map_is_refused_with_a_reason(change, message):
    data = _map(_stump(0, 0.0, -1.0, 1.0))
    change(data)
    with pytest.raises(BoostedMapError, match=message) as refused:
        trees_from_dict(data, name="m")
    assert str(refused.value).startswith("topple.boosted_map 'm': "), "one line that names the map"


def test_what_is_no_json_object_is_refused_and_a_map_read_from_no_file_has_no_hash():
    with pytest.raises(BoostedMapError, match=r"^topple\.boosted_map '': not a JSON object$"):
        trees_from_dict([_stump(0, 0.0, -1.0, 1.0)])
    assert trees_from_dict(_map(_stump(0, 0.0, -1.0, 1.0))).sha256 == ""


def test_integer_thresholds_and_values_are_read_as_floats_even_past_int64():
    """JSON carries 0 and 1e20 as integers when a writer drops the ".0"; they are numbers all the same."""
    trees = trees_from_dict(_map(_stump(0, 10**20, -1, 1), _stump(1, 0, 2, 0), baseline=0))
    assert trees.threshold.dtype == trees.value.dtype == np.float64 and trees.threshold[0] == 1e20
    x = np.zeros((2, F))
    x[:, 0] = [1e19, 1e21]
    x[:, 1] = [0, 1]
    assert np.allclose(boosted_probability(x, trees), _sigmoid(np.array([-1.0 + 2.0, 1.0 + 0.0])), rtol=0, atol=1e-15)


@pytest.mark.parametrize("shape", [(2, F + 1), (2, F - 1), (F,), (1, 2, F)])
def test_features_of_any_other_shape_are_refused(shape):
    trees = trees_from_dict(_map(_stump(0, 0.0, -1.0, 1.0)))
    with pytest.raises(ValueError, match=re.escape(f"features must be (A, {F}), got {shape}")):
        boosted_probability(np.zeros(shape), trees)


def test_a_missing_or_broken_file_names_the_path(tmp_path):
    with pytest.raises(BoostedMapError) as missing:
        load_trees(str(tmp_path / "nowhere.json"))
    assert str(missing.value).startswith(
        f"topple.boosted_map '{tmp_path}/nowhere.json': no such file {(tmp_path / 'nowhere.json').resolve()}; ")
    assert "Errno" not in str(missing.value)
    with pytest.raises(BoostedMapError, match="'nowhere': no packaged map of that name; .*packaged map \\(boosted_map_s41\\)"):
        load_trees("nowhere")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(BoostedMapError, match="bad.json is not valid JSON"):
        load_trees(str(bad))
    assert map_file("boosted_map_s41").name == "boosted_map_s41.json" and map_file("x/y.json") == Path("x/y.json")


def test_the_packaged_map_loads_with_this_versions_features():
    trees = load_trees("boosted_map_s41")
    assert len(trees.roots) == 300 and len(trees.sha256) == 64
    assert np.all((trees.feature[~trees.leaf] >= 0) & (trees.feature[~trees.leaf] < F))


def test_rows_take_q_where_they_land_and_keep_their_landing_in_proportion():
    points = np.array([[0, 0, 0], [0.05, 0, 0], [0.3, 0, 0], [0.6, 0, 0]], dtype=float)
    directions = np.tile([1.0, 0, 0], (4, 1))
    actions = Actions(points=points, normals=-directions, directions=directions,
                      status=np.array([STATUS_OK] * 3 + [STATUS_OK + 1], dtype=np.int8), max_height=1.0)
    rows = np.array([[0.4, 0.3, 0.3], [0.9, 0.1, 0.0], [1.0, 0.0, 0.0], [np.nan] * 3])
    features = np.zeros((4, F))
    features[:, 0] = [-1.0, 1.0, 1.0, 1.0]
    trees = trees_from_dict(_map(_stump(0, 0.0, -1.0, 1.0)))
    mapped, p = map_boosted_rows(rows, features, 0, actions, trees, pool=4)
    q = _sigmoid(np.array([-1.5, 0.5, 0.5]))
    assert np.allclose(p[:2], q[:2]) and np.allclose(mapped[:3].sum(axis=1), 1.0)
    assert mapped[0, 1] == pytest.approx(mapped[0, 2]), "push 0 still lands evenly in poses 1 and 2"
    assert np.allclose(mapped[1], [1 - q[1], q[1], 0.0])
    # Push 2 never toppled and no neighbour within 2 cm does; the pose's mean landing gives it one.
    pose_landing = landing_rows(rows, 0, points, directions, pool=4, rows=np.array([2]))[0]
    assert np.allclose(mapped[2], np.r_[1 - q[2], q[2] * pose_landing[1:]])
    assert np.all(np.isnan(mapped[3])) and np.isnan(p[3])
    # A pose nothing leaves: nowhere known to land, every row as it was.
    still = np.array([[1.0, 0.0, 0.0]] * 3 + [[np.nan] * 3])
    kept, p_kept = map_boosted_rows(still, features, 0, actions, trees, pool=4)
    assert np.array_equal(kept[:3], still[:3]) and np.array_equal(p_kept[:3], [0.0, 0.0, 0.0])


def _actions_at_one_spot(n):
    """n pushes at one contact in one direction, all ok: each is every other's neighbour."""
    directions = np.tile([1.0, 0, 0], (n, 1))
    return Actions(points=np.zeros((n, 3)), normals=-directions, directions=directions,
                   status=np.full(n, STATUS_OK, dtype=np.int8), max_height=-1)


def test_a_pose_with_one_ok_row_maps_it():
    rows = np.array([[0.5, 0.5, 0.0], [np.nan] * 3])
    features = np.zeros((2, F))
    features[:, 0] = 1.0
    trees = trees_from_dict(_map(_stump(0, 0.0, -1.0, 1.0)))
    mapped, p = map_boosted_rows(rows, features, 0, _actions_at_one_spot(2), trees)
    q = _sigmoid(-0.5 + 1.0)
    assert np.allclose(mapped[0], [1 - q, q, 0.0]) and p[0] == pytest.approx(q)
    assert np.all(np.isnan(mapped[1])) and np.isnan(p[1])


def test_a_probe_that_never_toppled_borrows_its_landing_from_the_candidates_only():
    """Row 0 is the pose's one candidate (pool 1) and lands in pose 1; row 1, a probe, lands in pose 2;
    row 2, a probe that never toppled, takes the mean of the pool's and its own leaving parts: pose 1 only
    (over all three rows it would be half pose 1, half pose 2)."""
    rows = np.array([[0.5, 0.5, 0.0], [0.5, 0.0, 0.5], [1.0, 0.0, 0.0]])
    features = np.zeros((3, F))
    features[:, 0] = 1.0
    trees = trees_from_dict(_map(_stump(0, 0.0, -1.0, 1.0)))
    q = _sigmoid(-0.5 + 1.0)
    mapped, p = map_boosted_rows(rows, features, 0, _actions_at_one_spot(3), trees, pool=1)
    assert np.allclose(mapped, [[1 - q, q, 0.0], [1 - q, 0.0, q], [1 - q, q, 0.0]]) and np.allclose(p, q)
    everyone, _ = map_boosted_rows(rows, features, 0, _actions_at_one_spot(3), trees)
    assert np.allclose(everyone[2], [1 - q, q / 2, q / 2]), "without a pool every row is a neighbour"


def test_the_engine_maps_every_ok_row_last_from_its_features(pose_and_candidates, tmp_path):  # noqa: F811
    obj, pose_set, pose, actions = pose_and_candidates
    topple = replace(Config().topple, n_trials=40, boosted_map="")
    trees_file = tmp_path / "stumps.json"
    trees_file.write_text(json.dumps(_map(_stump(0, -2.0, -1.0, 0.5), _stump(13, 0.3, 0.4, -0.4), baseline=0.1)))
    boosted = replace(topple, boosted_map=str(trees_file))
    assert boosted.needs_candidates and boosted.without_recalibration().boosted_map == ""
    assert replace(boosted, variant="robust").applied_boosted_map == "", "the thesis's variants never apply it"

    def table(t):
        return evaluate_pose(obj, pose, pose_set.probabilities, actions, t, stream(3, obj.name, pose.index, "trials"))

    plain, unmapped, mapped = table(topple), table(topple.without_recalibration()), table(boosted)
    ok = actions.status == STATUS_OK
    assert (plain.p_topple[ok] > 0).any()
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    features = boosted_features(plain.p_topple, unmapped.p_topple, plain.mean_force, actions,
                                edge_geometry(pose.base_edges, center_mass), center_mass, pose_set.probabilities,
                                pose.index, obj, topple.gravity)
    assert np.allclose(features[ok, 0], fitted_logit(plain.p_topple[ok]))
    assert np.allclose(features[ok, FEATURES.index("drop_probability")], pose_set.probabilities[pose.index])
    q = boosted_probability(features[ok], load_trees(str(trees_file)))
    assert np.allclose(mapped.p_topple[ok], q), "this pose has topples, so every ok push has somewhere to land"
    assert np.allclose(mapped.next_pose[ok].sum(axis=1), 1.0) and np.all(np.isnan(mapped.next_pose[~ok]))
    assert np.array_equal(mapped.outcomes, plain.outcomes) and np.array_equal(mapped.mean_force, plain.mean_force, equal_nan=True)


def test_a_shard_is_rebuilt_when_its_map_file_changes(tmp_path):
    trees_file = tmp_path / "m.json"
    trees_file.write_text(json.dumps(_map(_stump(0, 0.0, -1.0, 1.0))))
    config = Config().with_overrides({"topple.boosted_map": str(trees_file)})
    before = shards.fingerprint(shards.shard_inputs(SPEC, config))
    trees_file.write_text(json.dumps(_map(_stump(0, 0.0, -1.0, 2.0))))
    load_trees.cache_clear()
    assert shards.fingerprint(shards.shard_inputs(SPEC, config)) != before
    assert shards.fingerprint(shards.shard_inputs(SPEC, Config())) != before


def test_the_scorer_gives_the_engines_features_and_the_fit_is_written(model_logs, tmp_path):  # noqa: F811
    pytest.importorskip("sklearn")
    from pipeline.studies.recalibrate import main
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    log = read_log([path])
    contacts = ContactConfig(n_contacts=CANDIDATES_PER_POSE)
    scorer = Scorer(log, seed=2, contacts=contacts)
    topple = replace(Config().topple, boosted_map="")  # the model the map is fitted over
    features, _, lands = scorer.boosted_inputs(topple)
    p = scorer.score(topple).p_topple
    assert np.allclose(features[:, 0], fitted_logit(p)) and lands[p > 0].all()
    out, record = tmp_path / "b.toml", tmp_path / "b.json"
    code = main([str(path), "--boosted", "--corpus", "none", "--folds", "3", "--set", f"contacts.n_contacts={CANDIDATES_PER_POSE}",
                 "--seed", "2", "--set", "seed=2", "--out", str(out), "--json", str(record)])
    assert code == 0
    result = json.loads(record.read_text())
    written = Config.from_toml(out).topple
    assert written.boosted_map == str(tmp_path / "b.trees.json") == result["trees_file"]
    assert written.down_map == topple.down_map and written.side_map == topple.side_map, "the other maps are kept"
    trees = load_trees(written.boosted_map)
    expected = trees_from_dict(fit_trees(features[np.isfinite(p)], scorer.empirical_topple[np.isfinite(p)],
                                         scorer.repeats[np.isfinite(p)], 2))
    assert np.allclose(boosted_probability(features, trees), boosted_probability(features, expected), equal_nan=True)
    assert set(result["cross_validated"]) >= {"identity", "boosted_map"} and result["pushes"] == len(log.pushes)



def test_fold_maps_are_each_fitted_without_their_objects_and_list_them_as_a_corpus(model_logs, tmp_path, capsys):  # noqa: F811
    """``--fold-maps``: fold k's trees are the fit on the pushes of the other folds' objects, and
    fold k's corpus list holds exactly its objects (absolute paths), so a dataset of the list built
    with the map never maps an object the map was fitted on."""
    pytest.importorskip("sklearn")
    from pipeline.build.atomic import file_sha256
    from pipeline.build.corpus import read_list, write_list
    from pipeline.studies.recalibrate import main, push_folds
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    log = read_log([path])
    specs = [ObjectSpec(f"box{i}", str(model_logs / f"box{i}.stl"), 1.0, 0.25, "test", file_sha256(model_logs / f"box{i}.stl"))
             for i in range(3)]
    corpus_list = tmp_path / "boxes.csv"
    write_list(specs, corpus_list, None)
    folds_dir, record = tmp_path / "folds", tmp_path / "b.json"
    common = [str(path), "--corpus", str(corpus_list), "--folds", "3", "--set", f"contacts.n_contacts={CANDIDATES_PER_POSE}",
              "--seed", "2", "--set", "seed=2", "--out", str(tmp_path / "b.toml"), "--json", str(record)]
    assert main([*common, "--boosted", "--fold-maps", str(folds_dir)]) == 0
    result = json.loads(record.read_text())
    assert result["fold_lists"] == [str(folds_dir / f"fold_{k}.csv") for k in range(3)]

    scorer = Scorer(log, seed=2, contacts=ContactConfig(n_contacts=CANDIDATES_PER_POSE))
    features, p, _ = scorer.boosted_inputs(replace(Config().topple, boosted_map=""))
    rows = np.isfinite(p)
    fold_objects, fold_of = push_folds([scorer.object_ids[i] for i in scorer.object_index], 3, 2)
    assert result["fold_objects"] == fold_objects
    listed = []
    for k in range(3):
        train = (fold_of != k) & rows
        expected = trees_from_dict(fit_trees(features[train], scorer.empirical_topple[train], scorer.repeats[train], 2))
        written = load_trees(str(folds_dir / f"fold_{k}.trees.json"))
        assert np.array_equal(boosted_probability(features, written), boosted_probability(features, expected), equal_nan=True)
        members = read_list(folds_dir / f"fold_{k}.csv", 0.25).specs
        assert [m.object_id for m in members] == sorted(fold_objects[k])
        assert all(Path(m.path).is_absolute() and Path(m.path) == (model_logs / f"{m.object_id}.stl").resolve()
                   and m.sha256 == file_sha256(m.path) for m in members)
        listed += [m.object_id for m in members]
    assert sorted(listed) == sorted(scorer.object_ids), "every logged object in one fold"

    capsys.readouterr()
    assert main([*common, "--fold-maps", str(folds_dir)]) == 2
    assert "--fold-maps writes the boosted map's folds; give --boosted" in capsys.readouterr().err
    (tmp_path / "b.trees.json").unlink()  # a second fit to the same --out is refused (test_all_maps)
    assert main([*common[:1], "--corpus", "none", *common[3:], "--boosted", "--fold-maps", str(tmp_path / "other")]) == 2
    assert "--fold-maps writes corpus lists: give a --corpus, not 'none'" in capsys.readouterr().err


def test_folds_from_an_earlier_fold_maps_directory_are_the_folds_used(model_logs, tmp_path, capsys):  # noqa: F811
    """``--folds-from DIR``: the fit's folds are DIR's lists, not drawn, so two maps' corpus datasets out
    of fold hold the same objects; a logged object in no list, or one list alone, is refused."""
    pytest.importorskip("sklearn")
    from pipeline.build.atomic import file_sha256
    from pipeline.build.corpus import write_list
    from pipeline.studies.recalibrate import main
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    specs = {f"box{i}": ObjectSpec(f"box{i}", str(model_logs / f"box{i}.stl"), 1.0, 0.25, "test",
                                   file_sha256(model_logs / f"box{i}.stl")) for i in range(3)}
    corpus_list = tmp_path / "boxes.csv"
    write_list(list(specs.values()), corpus_list, None)
    given = tmp_path / "given"
    given.mkdir()
    # Folds no draw of three folds gives: two objects together, one alone.
    write_list([specs["box0"], specs["box2"]], given / "fold_0.csv", None)
    write_list([specs["box1"]], given / "fold_1.csv", None)
    common = [str(path), "--corpus", str(corpus_list), "--boosted", "--folds", "3", "--set", f"contacts.n_contacts={CANDIDATES_PER_POSE}",
              "--seed", "2", "--set", "seed=2", "--out", str(tmp_path / "b.toml"), "--json", str(tmp_path / "b.json")]
    out_dir = tmp_path / "out"

    def fit(*options: str, log: str = str(path)) -> int:
        (tmp_path / "b.trees.json").unlink(missing_ok=True)  # a second fit to the same --out is refused (test_all_maps)
        return main([log, *common[1:], *options])

    assert fit("--folds-from", str(given), "--fold-maps", str(out_dir)) == 0
    result = json.loads((tmp_path / "b.json").read_text())
    assert result["fold_objects"] == [["box0", "box2"], ["box1"]] and result["folds"] == 2
    assert sorted(p.name for p in out_dir.iterdir()) == ["fold_0.csv", "fold_0.trees.json", "fold_1.csv", "fold_1.trees.json"]
    assert "the folds of" in (tmp_path / "b.toml").read_text()

    # The folds it wrote, read back, and --folds 3 ignored: the same folds and, fitted on the same pushes, the same maps.
    again = tmp_path / "again"
    assert fit("--folds-from", str(out_dir), "--fold-maps", str(again)) == 0
    record = json.loads((tmp_path / "b.json").read_text())
    assert record["fold_objects"] == [["box0", "box2"], ["box1"]] and record["folds_from"] == str(out_dir)
    for k in range(2):
        assert (again / f"fold_{k}.trees.json").read_text() == (out_dir / f"fold_{k}.trees.json").read_text()
        assert (again / f"fold_{k}.csv").read_text() == (out_dir / f"fold_{k}.csv").read_text()

    capsys.readouterr()
    (given / "fold_1.csv").unlink()
    write_list([specs["box0"]], given / "fold_0.csv", None)
    assert fit("--folds-from", str(given)) == 2
    assert "holds 1 fold list(s)" in capsys.readouterr().err
    write_list([specs["box2"]], given / "fold_1.csv", None)
    assert fit("--folds-from", str(given)) == 2
    assert "1 logged object(s) in no fold: box1" in capsys.readouterr().err
    write_list([specs["box1"], specs["box2"]], given / "fold_1.csv", None)
    write_list([specs["box0"], specs["box2"]], given / "fold_0.csv", None)
    assert fit("--folds-from", str(given)) == 2
    assert "object 'box2' is in folds 0 and 1" in capsys.readouterr().err
    # A fold list naming an object the corpus does not hold is refused before the fit, not when the lists are written.
    write_list([specs["box1"]], given / "fold_1.csv", None)
    write_list([specs["box0"], specs["box2"], ObjectSpec("stranger", specs["box0"].path, 1.0, 0.25, "test", specs["box0"].sha256)],
               given / "fold_0.csv", None)
    assert fit("--folds-from", str(given), "--fold-maps", str(tmp_path / "never")) == 2
    assert "folds hold 1 object(s) not in corpus" in capsys.readouterr().err and not (tmp_path / "never").exists()
    # ... and before any log is read: a log that does not exist is not what it reports.
    assert fit("--folds-from", str(given), "--fold-maps", str(tmp_path / "never"), log=str(tmp_path / "no_such_log")) == 2
    assert "folds hold 1 object(s) not in corpus" in capsys.readouterr().err
    assert main([*common[:3], *common[4:], "--folds-from", str(given)]) == 2
    assert "--folds-from gives the boosted map's folds; give --boosted" in capsys.readouterr().err


def test_two_fold_map_sets_are_scored_out_of_fold_each_push_by_its_folds_map(model_logs, tmp_path, capsys):  # noqa: F811
    """``compare_fold_maps``: each push is mapped by its object's fold's map; the same maps differ by
    nothing, and fold maps of constants c_k score exactly (c_k - f)^2 + f (1 - f) where the model lands."""
    pytest.importorskip("sklearn")
    import shutil

    from pipeline.studies.compare_fold_maps import main as compare_main
    from pipeline.studies.recalibrate import main
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    path = model_logs / "reported.parquet"
    settings = ["--set", f"contacts.n_contacts={CANDIDATES_PER_POSE}", "--set", "seed=2"]
    a, b, record = tmp_path / "a", tmp_path / "b", tmp_path / "c.json"
    from pipeline.build.atomic import file_sha256
    from pipeline.build.corpus import write_list

    corpus_list = tmp_path / "boxes.csv"
    write_list([ObjectSpec(f"box{i}", str(model_logs / f"box{i}.stl"), 1.0, 0.25, "test", file_sha256(model_logs / f"box{i}.stl"))
                for i in range(3)], corpus_list, None)
    assert main([str(path), "--corpus", str(corpus_list), "--boosted", "--folds", "3", "--seed", "2", *settings,
                 "--out", str(tmp_path / "a.toml"), "--json", str(tmp_path / "a.json"), "--fold-maps", str(a)]) == 0
    shutil.copytree(a, b)
    common = [str(path), "--corpus", str(corpus_list), *settings, "--json", str(record)]
    assert compare_main([str(a), str(b), *common]) == 0
    same = json.loads(record.read_text())["logs"][str(path)]
    assert same["b_minus_a_brier"] == 0.0 and same["b_minus_a_interval"] == [0.0, 0.0] and same["a"] == same["b"]

    constant = [0.2, 0.5, 0.8]  # B: fold k's map the constant constant[k]
    for k in range(3):
        logit = float(np.log(constant[k] / (1 - constant[k])))
        (b / f"fold_{k}.trees.json").write_text(json.dumps(_map(_stump(0, 0.0, 0.0, 0.0), baseline=logit)))
    load_trees.cache_clear()
    assert compare_main([str(a), str(b), *common]) == 0
    result = json.loads(record.read_text())["logs"][str(path)]
    log = read_log([path])
    scorer = Scorer(log, seed=2, contacts=ContactConfig(n_contacts=CANDIDATES_PER_POSE))
    _, p, lands = scorer.boosted_inputs(Config().topple)
    rows = np.isfinite(p)
    f, w = scorer.empirical_topple[rows], scorer.repeats[rows]
    from pipeline.studies.recalibrate import fold_of_pushes, read_fold_lists

    fold = fold_of_pushes([scorer.object_ids[i] for i in scorer.object_index], read_fold_lists(a))[rows]
    assert len(set(fold.tolist())) == 3, "every fold holds logged pushes"
    q = np.where(lands[rows], np.array(constant)[fold], p[rows])
    assert lands[rows].any()
    assert result["b"]["brier"] == pytest.approx(np.average((q - f) ** 2 + f * (1 - f), weights=w), abs=1e-12)
    assert result["pushes"] == int(rows.sum()) and result["b_minus_a_brier"] == pytest.approx(result["b"]["brier"] - result["a"]["brier"])
    low, high = result["b_minus_a_interval"]
    assert low <= result["b_minus_a_brier"] <= high

    capsys.readouterr()
    (b / "fold_2.csv").unlink()
    (b / "fold_0.csv").write_text((a / "fold_0.csv").read_text() + "".join((a / "fold_2.csv").read_text().splitlines(True)[1:]))
    assert compare_main([str(a), str(b), *common]) == 2
    assert "hold different folds; fit B with --folds-from" in capsys.readouterr().err

# --- the features: every column what its name says (M09, M10, M24, M27, M28, M11, M12) --------------

def test_every_feature_column_is_what_its_name_says(pose_and_candidates):  # noqa: F811
    obj, pose_set, pose, actions = pose_and_candidates
    n = len(actions.status)
    rng = np.random.default_rng(0)
    p, unmapped = rng.random(n), rng.random(n)
    mean_force = np.where(rng.random(n) < 0.5, np.nan, rng.random(n) * 5)
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    edges = edge_geometry(pose.base_edges, center_mass)
    g = boosted_features(p, unmapped, mean_force, actions, edges, center_mass, pose_set.probabilities, pose.index, obj, 9.81)
    col = {name: g[:, i] for i, name in enumerate(FEATURES)}
    longest, middle, shortest = np.sort(obj.mesh.extents)[::-1]
    assert np.allclose(col["logit_p"], fitted_logit(p)) and np.allclose(col["logit_p_unmapped"], fitted_logit(unmapped))
    push = pose_features(unmapped, actions.points, actions.directions, mean_force, obj.mass * 9.81)
    assert np.allclose(g[:, 2:6], push[:, 2:], equal_nan=True), "C.13's features of the unmapped P"
    assert np.allclose(col["drop_probability"], pose_set.probabilities[pose.index])
    assert pose.index != np.argmax(pose_set.probabilities) or len(pose_set.probabilities) == 1
    assert np.allclose(col["log_poses"], np.log(len(pose_set.probabilities)))
    assert np.allclose(col["base_edges"], len(edges.com_distance))
    assert np.allclose(col["flatness"], shortest / longest) and np.allclose(col["middle_over_size"], middle / longest)
    assert np.allclose(col["log_mass"], np.log(obj.mass)) and np.allclose(col["log_size"], np.log(longest))
    assert np.allclose(col["horizontal"], np.hypot(actions.directions[:, 0], actions.directions[:, 1]))
    assert np.allclose(col["contact_height_over_size"], actions.points[:, 2] / longest)
    assert len({round(float(v), 9) for v in (shortest / longest, middle / longest, np.log(obj.mass), np.log(longest))}) == 4
    height = center_mass[2]
    assert height > 1e-3 and np.allclose(col["height_over_size"], height / longest)
    assert np.allclose(col["widest_edge"], edges.com_distance.max() / height) and edges.com_distance.max() > edges.com_distance.min()
    ratio = needed_force_ratio(actions.points, actions.directions, edges)
    assert np.allclose(col["log_needed_force_ratio"], np.log(np.clip(ratio, *FORCE_RATIO_RANGE)))
    assert np.isinf(ratio).any() and np.all(np.abs(col["log_needed_force_ratio"]) <= np.log(1e3) + 1e-12), "clipped"
    # N over the pose's candidates only: the last rows (probes) are nobody else's neighbours.
    k = n - 20
    pooled = boosted_features(p, unmapped, mean_force, actions, edges, center_mass, pose_set.probabilities, pose.index, obj, 9.81,
                              pool=k)
    push_k = pose_features(unmapped, actions.points, actions.directions, mean_force, obj.mass * 9.81, pool=k)
    assert np.allclose(pooled[:, 2:6], push_k[:, 2:], equal_nan=True)
    assert not np.allclose(pooled[:, 2], g[:, 2]), "the test needs probes that are some candidate's neighbours"


def test_the_logit_floor_is_the_fitted_form_bit_for_bit():
    """fitted_logit's reason to exist: the packaged map has thresholds exactly on log(f / (1 - f))."""
    floor = np.log(LOGIT_FLOOR / (1.0 - LOGIT_FLOOR))
    assert fitted_logit(np.array([0.0, LOGIT_FLOOR]))[0] == floor == fitted_logit(np.array([LOGIT_FLOOR]))[0]
    top = fitted_logit(np.array([1.0, 1.0 - LOGIT_FLOOR]))
    ceiling = 1.0 - LOGIT_FLOOR
    assert top[0] == top[1] == np.log(ceiling / (1.0 - ceiling)), "a push that always topples is clipped too"
    assert top[0] == pytest.approx(-floor, rel=1e-14)
    trees = load_trees("boosted_map_s41")
    on_floor = ~trees.leaf & (trees.feature == 0) & (trees.threshold == floor)
    assert on_floor.any(), "the packaged map splits logit_p exactly at the floor"


# --- the engine's wiring (T01-T04) and the config (C02) -------------------------------------------

def test_the_engine_passes_boosted_features_of_the_unmapped_p_and_the_candidates(pose_and_candidates, tmp_path, monkeypatch):  # noqa: F811
    obj, pose_set, pose, actions = pose_and_candidates
    topple = replace(Config().topple, n_trials=40, boosted_map="")
    trees_file = tmp_path / "stumps.json"
    trees_file.write_text(json.dumps(_map(_stump(0, -2.0, -1.0, 0.5))))
    boosted = replace(topple, boosted_map=str(trees_file))
    seen = {}
    real_features, real_rows = topple_module.boosted_features, topple_module.map_boosted_rows

    def features(*args, **kwargs):
        seen["features"] = (args, kwargs)
        return real_features(*args, **kwargs)

    def rows(*args, **kwargs):
        seen["rows"] = (args, kwargs)
        return real_rows(*args, **kwargs)

    monkeypatch.setattr(topple_module, "boosted_features", features)
    monkeypatch.setattr(topple_module, "map_boosted_rows", rows)
    k = len(actions.status) - 5

    def table(t):
        return evaluate_pose(obj, pose, pose_set.probabilities, actions, t, stream(3, obj.name, pose.index, "trials"), candidates=k)

    table(boosted)
    unmapped = table(topple.without_recalibration())
    args, kwargs = seen["features"]
    assert np.allclose(args[1], unmapped.p_topple, equal_nan=True), "the second P is the unmapped one"
    assert kwargs.get("pool") == k and seen["rows"][1].get("pool") == k, "probes never neighbour probes"
    # The thesis's variants never reach the map, whatever the field says.
    seen.clear()
    robust = table(replace(boosted, variant="robust"))
    assert "features" not in seen and np.array_equal(robust.next_pose, table(replace(topple, variant="robust")).next_pose,
                                                     equal_nan=True)


def test_the_boosted_map_alone_needs_the_candidates():
    bare = replace(Config().topple, smoothing_radius=0.0, feature_map=(), down_map=(), boosted_map="")
    assert not bare.needs_candidates and replace(bare, boosted_map="boosted_map_s41").needs_candidates


# --- shards (S02, S03) -----------------------------------------------------------------------------

def test_a_shard_without_the_map_keeps_the_identity_it_had_before_it_existed(tmp_path):
    without = Config().with_overrides({"topple.boosted_map": "", "mdp.min_direction_z": -0.3})
    inputs = shards.shard_inputs(SPEC, without)
    assert "boosted_map" not in inputs["config"]["topple"] and "boosted_map_sha256" not in inputs
    assert "boosted_map_sha256" in shards.shard_inputs(SPEC, Config()), "the default applies the packaged map"
    thesis = Config().with_overrides({"topple.variant": "robust"})
    named = thesis.with_overrides({"topple.boosted_map": str(tmp_path / "nowhere.json")})
    assert shards.shard_inputs(SPEC, named) == shards.shard_inputs(SPEC, thesis), "a thesis variant never reads the file"


def test_boosted_recalibrate_fits_each_fold_on_the_others_and_scores_the_model_without_the_map(model_logs, tmp_path, monkeypatch):  # noqa: F811
    from pipeline.studies import recalibrate as rc
    from pipeline.studies.logreader import read_log
    from pipeline.studies.scoring import Scorer
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    log = read_log([model_logs / "reported.parquet"])
    plus, minus, stump = (tmp_path / f"{n}.json" for n in ("plus", "minus", "stump"))
    plus.write_text(json.dumps(_map(_stump(0, 0.0, 10.0, 10.0), baseline=0.0)))
    minus.write_text(json.dumps(_map(_stump(0, 0.0, -10.0, -10.0), baseline=0.0)))
    stump.write_text(json.dumps(_map(_stump(0, -2.0, -1.0, 0.5))))
    config = Config().with_overrides({"contacts.n_contacts": CANDIDATES_PER_POSE, "seed": 2, "topple.boosted_map": str(stump)})
    topple = config.topple
    scorer = Scorer(log, 2, config.contacts)
    features, _, lands = scorer.boosted_inputs(topple)
    p = scorer.score(replace(topple, boosted_map="")).p_topple
    rows = np.isfinite(p)
    # SC1: the second column is the unmapped P's
    unmapped = scorer.score(topple.without_recalibration()).p_topple
    assert np.allclose(features[rows, 1], fitted_logit(unmapped[rows]))
    # SC2: `lands` is where the engine's map changes P
    moved = scorer.score(replace(topple, boosted_map=str(plus))).p_topple != scorer.score(replace(topple, boosted_map=str(minus))).p_topple
    assert np.array_equal(lands[rows], moved[rows])

    fits, mapped = [], []
    real_fit = rc.fit_trees
    monkeypatch.setattr(rc, "fit_trees", lambda f, o, r, s: fits.append(len(f)) or real_fit(f, o, r, s, max_iter=3))
    monkeypatch.setattr(rc, "boosted_probability", lambda x, t: mapped.append(len(x)) or np.full(len(x), 0.5))
    result = rc.boosted_recalibrate(log, config, folds=3, seed=2)
    _, fold_of = rc.push_folds([scorer.object_ids[i] for i in scorer.object_index], 3, 2)
    assert fits == [int(((fold_of != f) & rows).sum()) for f in range(3)] + [int(rows.sum())], "R02/R06"
    assert mapped == [int(((fold_of == f) & rows & lands).sum()) for f in range(3)], "R01"
    held = np.where(rows & lands, 0.5, p)
    expected = rc.metrics_by_predictor({"identity": p, "boosted_map": held}, rows, scorer.empirical_topple,
                                       scorer.repeats.astype(float), scorer.object_index)
    assert result["cross_validated"] == expected, "R03/R05: identity is the model without the map"


def test_a_shard_is_the_maps_content_whatever_names_the_file(tmp_path):
    packaged = Config().with_overrides({"topple.boosted_map": "boosted_map_s41"})
    copy = tmp_path / "elsewhere.json"
    copy.write_bytes(map_file("boosted_map_s41").read_bytes())
    moved = Config().with_overrides({"topple.boosted_map": str(copy)})
    assert shards.shard_inputs(SPEC, packaged) == shards.shard_inputs(SPEC, moved)


def test_a_missing_map_is_the_commands_one_line_error(tmp_path, capsys):
    from pipeline.cli import main

    code = main(["dataset", "--corpus", str(tmp_path / "none.csv"), "--out", str(tmp_path / "d"),
                 "--set", f"topple.boosted_map={tmp_path / 'nowhere.json'}"])
    err = capsys.readouterr().err
    assert code == 2 and "error: topple.boosted_map" in err and "nowhere.json" in err and "Traceback" not in err
    broken = tmp_path / "broken.json"
    broken.write_text(json.dumps({**_map(_stump(0, 0.0, -1.0, 1.0)), "features": None}))  # JSON, but no map
    code = main(["dataset", "--corpus", str(tmp_path / "none.csv"), "--out", str(tmp_path / "d"),
                 "--set", f"topple.boosted_map={broken}"])
    err = capsys.readouterr().err
    assert code == 2 and "features are not this version's" in err and "Traceback" not in err


def _walk_one_by_one(x, data):
    """The scalar reference of (C.19.1): one push, one tree, one node at a time, from the JSON layout."""
    raw = data["baseline"]
    for tree in data["trees"]:
        node = 0
        while not tree["leaf"][node]:
            value = x[tree["feature"][node]]
            left = tree["missing_left"][node] if np.isnan(value) else value <= tree["threshold"][node]
            node = tree["left"][node] if left else tree["right"][node]
        raw += tree["value"][node]
    return 1.0 / (1.0 + np.exp(-raw))


@pytest.mark.parametrize("shared", [(), (10, 13, 14, 15, 16, 17, 18, 19, 20, 21), tuple(range(F))])
def test_the_walk_skipping_shared_splits_reaches_the_scalar_walks_leaves(shared):
    data = json.loads(map_file("boosted_map_s41").read_text())
    trees = trees_from_dict(data)
    rng = np.random.default_rng(len(shared))
    thresholds = np.array([t for tree in data["trees"] for t, leaf in zip(tree["threshold"], tree["leaf"]) if not leaf])
    # Values drawn from the map's own thresholds, so pushes land on both sides of real splits and some exactly on one.
    x = rng.choice(thresholds, size=(40, F)) + rng.choice([0.0, 0.0, 1e-3, -1e-3], size=(40, F))
    x[rng.random((40, F)) < 0.05] = np.nan
    x[:, list(shared)] = x[0, list(shared)]  # what a pose's pushes share (its drop probability, the object's shape, ...)
    expected = np.array([_walk_one_by_one(row, data) for row in x])
    assert np.allclose(boosted_probability(x, trees), expected, rtol=0, atol=1e-12)
    assert np.allclose(boosted_probability(x[:1], trees), expected[:1], rtol=0, atol=1e-12), "one push: every split shared"
    assert boosted_probability(x[:0], trees).shape == (0,)


def test_splits_every_push_shares_are_resolved_before_the_walk():
    """One push shares every column with itself: each tree's root becomes the leaf the scalar walk reaches.
    Pushes that differ in every column share no split: the trees come back as they are."""
    data = json.loads(map_file("boosted_map_s41").read_text())
    trees = trees_from_dict(data)
    x = np.random.default_rng(5).normal(size=(2, F))
    roots, left, right = _skip_shared_splits(x[:1], trees)
    assert trees.leaf[roots].all() and (~trees.leaf[trees.roots]).all()
    assert _sigmoid(data["baseline"] + trees.value[roots].sum()) == pytest.approx(_walk_one_by_one(x[0], data), rel=1e-12)
    leaves = np.flatnonzero(trees.leaf)
    assert np.array_equal(left[leaves], leaves) and np.array_equal(right[leaves], leaves), "a leaf still points at itself"
    same = _skip_shared_splits(x, trees)
    assert all(np.array_equal(a, b) for a, b in zip(same, (trees.roots, trees.left, trees.right)))
