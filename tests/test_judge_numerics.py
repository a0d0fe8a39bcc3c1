"""The judge's-numerics comparison (pipeline.studies.judge_numerics): two logs of the same pushes and
noise draws compared trial by trial and through the model's metrics, checked on logs whose answer is
known: a log against itself, against a world where nothing topples, and against one that lacks an object."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pyarrow as pa
import pyarrow.compute
import pyarrow.parquet as pq
import pytest
from shapes import THESIS

from pipeline.model.config import Config
from pipeline.studies import judge_numerics, playlog
from pipeline.studies.logreader import read_log
from pipeline.studies.pushsim import FINGER_SPEED, PlayerSettings
from pipeline.studies.scoring import Scorer
from pipeline.studies.validation import push_metrics
from tests.test_pushsim import specs  # noqa: F401 (fixture: a box and random_002)

TINY = THESIS.with_overrides({"contacts.n_contacts": 40, "topple.n_trials": 8})
PARAMS = playlog.PlayParams(actions=3, repeats=3, eps=0.05, max_poses=2, seed=3, config=TINY)
RESAMPLES = 200


@pytest.fixture(scope="module")
def logs(specs, tmp_path_factory):  # noqa: F811 (fixture)
    """A log of a box and one pybullet_data object, and the same play with the finger at half speed."""
    root = tmp_path_factory.mktemp("judge")
    playlog.play(specs, PARAMS, root / "base", workers=1)
    playlog.play(specs, replace(PARAMS, player=PlayerSettings(finger_speed=FINGER_SPEED / 2)), root / "slow", workers=1)
    return root


def _rewritten(source, out, change):
    """A copy of a log directory with every part file's table passed through ``change`` (metadata kept)."""
    out.mkdir()
    for part in sorted(source.glob("*.parquet")):
        table = pq.read_table(part)
        changed = change(table)
        if changed is not None:
            pq.write_table(changed.replace_schema_metadata(table.schema.metadata), out / part.name)
    return out


def _compare(base, variant, rate=0.3):
    config = Config()
    return judge_numerics.compare(read_log([base], config), read_log([variant], config), config, rate, RESAMPLES)


def test_a_log_against_itself_agrees_in_every_trial_and_every_metric(logs):
    result = _compare(logs / "base", logs / "base")
    assert result["same_final_pose"] == result["same_toppled"] == 1.0 and result["push_tv"] == 0.0
    assert result["unpaired"] == {"base_only": 0, "variant_only": 0, "pushes_without_common_trials": 0, "trials_unpaired": 0}
    assert result["topple_rate"]["difference"] == 0.0 and result["topple_rate"]["ci"] == [0.0, 0.0]
    for predictor in judge_numerics.PREDICTORS:
        for key, d in result["predictors"][predictor]["difference"].items():
            assert d["difference"] == 0.0 or np.isnan(d["difference"]), (predictor, key)


def _tipped(table):
    """Every first repeat's final transform replaced by its start turned 90 degrees about the world's x
    axis: a trial that surely left its start pose (its down vector is 90 degrees from the start's)."""
    start = np.stack(table.column("start_transform").to_numpy(zero_copy_only=False)).reshape(-1, 4, 4)
    final = np.stack(table.column("final_transform").to_numpy(zero_copy_only=False)).reshape(-1, 4, 4)
    turn = np.eye(4)
    turn[1:3, 1:3] = [[0.0, -1.0], [1.0, 0.0]]
    first = table.column("repeat").to_numpy() == 0
    final[first] = turn @ start[first]
    column = pa.array(list(final.reshape(-1, 16)), type=table.schema.field("final_transform").type)
    return table.set_column(table.schema.get_field_index("final_transform"), "final_transform", column)


def test_against_a_world_where_every_first_repeat_topples_exactly_those_trials_disagree(logs, tmp_path):
    """Base's trials all stay (the play draws pushes this small model rarely topples); the variant
    topples every first repeat of PARAMS.repeats: a third of the trials disagree, and never-topples,
    perfect on base, loses exactly what those topples cost it."""
    base = read_log([logs / "base"], Config())
    outcomes = np.concatenate([p.outcomes for p in base.pushes])
    starts = np.concatenate([np.full(len(p.outcomes), p.pose) for p in base.pushes])
    assert np.all(outcomes == starts), "the test reads base as a log where nothing topples"
    result = _compare(logs / "base", _rewritten(logs / "base", tmp_path / "tipped", _tipped))
    share = 1.0 / PARAMS.repeats
    assert result["trials"] == len(outcomes)
    assert result["topple_rate"]["base"] == 0.0 and result["topple_rate"]["variant"] == pytest.approx(share)
    assert result["same_toppled"] == pytest.approx(1.0 - share) and result["same_final_pose"] == pytest.approx(1.0 - share)
    assert result["topple_rate"]["difference"] == pytest.approx(share) and result["topple_rate"]["ci"] == pytest.approx([share, share])
    assert result["push_tv"] == pytest.approx(share), "each push: a third of its mass moved off the start pose"
    never = result["predictors"]["never_topples"]
    assert never["base"]["tv_all"] == 0.0 and never["base"]["brier"] == 0.0
    # Per push the empirical distribution is (2/3 on the start, 1/3 elsewhere): Brier (1/3)^2 + (1/3)^2.
    assert never["variant"]["brier"] == pytest.approx(2 * share**2) and never["variant"]["tv_all"] == pytest.approx(share)
    assert never["difference"]["brier"]["difference"] == pytest.approx(2 * share**2)
    model = result["predictors"]["default"]
    assert np.isnan(model["base"]["ap"]), "no push topples in base: no precision to average"
    # Nothing observed toppling in base: every bin's gap is its mean P, so ECE is the mean P.
    assert model["base"]["ece"] == pytest.approx(np.mean(read_p(logs / "base")))


def read_p(log_dir):
    """The default model's P(topple) per push of a log, as the comparison scores it."""
    config = Config()
    scorer = Scorer(read_log([log_dir], config), config.seed, config.contacts)
    return scorer.score_predictions(scorer.predict(config.topple)).p_topple


def test_pushes_one_log_lacks_are_counted_and_left_out(logs, tmp_path):
    fewer = _rewritten(logs / "base", tmp_path / "fewer", lambda t: None if t.column("object_id")[0].as_py() == "box" else t)
    result = _compare(logs / "base", fewer)
    base = read_log([logs / "base"], Config())
    box_pushes = sum(p.object_id == "box" for p in base.pushes)
    assert box_pushes > 0 and result["unpaired"]["base_only"] == box_pushes and result["unpaired"]["variant_only"] == 0
    assert result["objects"] == 1 and result["pushes"] == len(base.pushes) - box_pushes


def test_logs_of_other_pushes_are_refused(logs, tmp_path):
    def moved(table):
        return table.set_column(table.schema.get_field_index("point_x"), "point_x",
                                pa.array(table.column("point_x").to_numpy() + 0.001))

    other = _rewritten(logs / "base", tmp_path / "other", moved)
    with pytest.raises(judge_numerics.JudgeError, match="not the same play"):
        _compare(logs / "base", other)


def test_the_same_play_at_half_the_finger_speed_is_compared_push_by_push(logs, tmp_path, capsys):
    out = tmp_path / "judge.json"
    assert judge_numerics.main(["--base", str(logs / "base"), "--variant", f"slow={logs / 'slow'}",
                                "--rate-from", str(logs / "base"), "--bootstrap", str(RESAMPLES), "--json", str(out)]) == 0
    result = json.loads(out.read_text())["variants"]["slow"]
    base, slow = read_log([logs / "base"], Config()), read_log([logs / "slow"], Config())
    assert result["pushes"] == len(base.pushes) == len(slow.pushes) and result["unpaired"]["base_only"] == 0
    assert result["player"]["finger_speed"] == FINGER_SPEED / 2
    agree = np.mean(np.concatenate([a.outcomes == b.outcomes for a, b in zip(base.pushes, slow.pushes)]))
    assert result["same_final_pose"] == pytest.approx(agree)
    assert "slow:" in capsys.readouterr().out
    # The model's metrics against the slow log are what a scorer of that log alone gives.
    config = Config()
    alone = Scorer(slow, config.seed, config.contacts)
    scores = alone.score(config.topple)
    expected = push_metrics(scores.tv, scores.p_topple, alone.empirical_topple, alone.object_index, scores.brier)
    expected = {key: None if np.isnan(value) else value for key, value in expected.items()}  # NaN is null in JSON
    assert result["predictors"]["default"]["variant"] == pytest.approx(expected)
    assert judge_numerics.main(["--base", str(logs / "base"), "--variant", "slow"]) == 2
    assert "NAME=LOG" in capsys.readouterr().err
    assert judge_numerics.main(["--base", str(logs / "base"), "--variant", f"a={logs / 'slow'}", "--variant", f"a={logs / 'slow'}"]) == 2
    assert "given twice" in capsys.readouterr().err


def test_trials_are_paired_by_their_repeat_number(logs, tmp_path):
    """Base lacks every repeat 0, the variant every repeat 1: only repeat 2 is a trial of both. Both
    copies of one log, so those trials agree, whatever the outcomes of the others."""
    def without(repeat):
        return lambda t: t.filter(pa.compute.not_equal(t.column("repeat"), repeat))

    a = _rewritten(logs / "base", tmp_path / "a", without(0))
    b = _rewritten(logs / "base", tmp_path / "b", _tipped)  # every repeat 0 toppled ...
    b = _rewritten(b, tmp_path / "b1", without(1))  # ... and repeat 1 gone
    result = _compare(a, b)
    pushes = len(read_log([logs / "base"], Config()).pushes)
    assert result["pushes"] == pushes and result["trials"] == pushes
    assert result["unpaired"]["trials_unpaired"] == 2 * pushes
    assert result["same_final_pose"] == result["same_toppled"] == 1.0 and result["topple_rate"]["difference"] == 0.0


def test_only_one_play_under_two_settings_is_compared(logs, specs, tmp_path, capsys):  # noqa: F811 (fixture)
    """A replay (other noise draws), a log with the sides swapped, and a push named twice are refused."""
    replay = tmp_path / "replay"
    playlog.play(specs, replace(PARAMS, noise_draws=1), replay, workers=1)
    assert judge_numerics.main(["--base", str(logs / "base"), "--variant", f"replay={replay}"]) == 2
    assert "noise_draws" in capsys.readouterr().err
    assert judge_numerics.main(["--base", str(logs / "slow"), "--variant", f"base={logs / 'base'}"]) == 2
    assert "not played with the player's defaults" in capsys.readouterr().err
    assert judge_numerics.main(["--base", str(logs / "base"), str(logs / "base" / "box.parquet"), "--variant",
                                f"slow={logs / 'slow'}"]) == 2
    assert "in two files" in capsys.readouterr().err
    config = Config()
    twice = read_log([logs / "base", logs / "slow"], config)
    with pytest.raises(judge_numerics.JudgeError, match="in two of the base logs"):
        judge_numerics.compare(twice, read_log([logs / "slow"], config), config, None, RESAMPLES)


def test_base_is_predicted_once_for_every_variant_that_pairs_its_pushes(logs, monkeypatch):
    """The model's rows depend on the pushes, not on what physics made of them: a second variant of the same
    pushes reuses base's predictions, and reads as it does without them."""
    config = Config()
    base, slow = read_log([logs / "base"], config), read_log([logs / "slow"], config)
    alone = judge_numerics.compare(base, slow, config, 0.3, RESAMPLES)
    calls = []
    predict = Scorer.predict
    monkeypatch.setattr(Scorer, "predict", lambda self, topple: calls.append(1) or predict(self, topple))
    predicted: dict = {}
    first = judge_numerics.compare(base, slow, config, 0.3, RESAMPLES, predicted)
    second = judge_numerics.compare(base, base, config, 0.3, RESAMPLES, predicted)
    assert len(calls) == 1 and len(predicted) == 1
    assert json.dumps(first, sort_keys=True) == json.dumps(alone, sort_keys=True)  # NaN (no AP) reads as NaN
    assert second["predictors"]["default"]["difference"]["brier"]["difference"] == 0.0
