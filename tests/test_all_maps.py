"""``toppledb recalibrate --all-maps``: every map of P(topple) refitted in the engine's order in one run
(docs/MODEL.md C.19), the same file as ``--down``, ``--side`` and ``--boosted`` run in turn, each on the
file the one before wrote."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from pipeline.model.config import Config, MDPConfig
from tests.test_validation import model_logs  # noqa: F401 (fixture)

pytest.importorskip("sklearn")  # the boosted map's fit


def _options(folds: int = 3, seed: int = 2) -> list[str]:
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    return ["--corpus", "none", "--folds", str(folds), "--seed", str(seed), "--set", f"contacts.n_contacts={CANDIDATES_PER_POSE}"]


def _maps(path: Path) -> dict:
    """The [topple] section a config file gives, the boosted map's trees read in place of its file name."""
    topple = Config.from_toml(path).topple
    values = {name: getattr(topple, name) for name in topple.__dataclass_fields__}
    values["boosted_map"] = json.loads(Path(topple.boosted_map).read_text())
    return values


@pytest.mark.parametrize("base_model", [None, "[topple]\nmu_table_mean = 0.5\nrotation_std = 0.3\n"])
def test_all_maps_is_the_three_fits_run_in_turn_on_each_others_files(base_model, model_logs, tmp_path, capsys):  # noqa: F811
    """From the defaults, and from a file of [topple] values (a ``toppledb calibrate`` result, say), whose
    values every step's file carries on."""
    from pipeline.studies.recalibrate import main

    log = str(model_logs / "reported.parquet")
    by_hand = []
    base: list[str] = []
    if base_model is not None:
        (tmp_path / "base.toml").write_text(base_model)
        base = ["--config", str(tmp_path / "base.toml")]
    first_base = base
    for step in ("--down", "--side", "--boosted"):
        out = tmp_path / f"{step[2:]}.toml"
        assert main([log, step, *_options(), *base, "--out", str(out), "--json", str(out.with_suffix(".json"))]) == 0
        by_hand.append(out)
        base = ["--config", str(out)]
    out, record = tmp_path / "all.toml", tmp_path / "all.json"
    assert main([log, "--all-maps", *_options(), *first_base, "--out", str(out), "--json", str(record)]) == 0
    printed = capsys.readouterr().out
    assert "1. the centred and down maps" in printed and "3. the boosted map" in printed
    assert "note: steps 2 and 3 score the maps under them as fitted on every push of this log" in printed, \
        "the steps' 'without' rows are in-sample, and the output says so"

    chained, one_run = _maps(by_hand[-1]), _maps(out)
    assert chained == one_run, {k: (chained[k], one_run[k]) for k in chained if chained[k] != one_run[k]}
    default = Config().topple
    assert all(one_run[name] != getattr(default, name) for name in ("recalibration_x", "down_map", "side_map")), \
        "every map is refitted, none is the default's"
    assert Config.from_toml(out).mdp == MDPConfig(), "with the boosted map over the down map, planners choose from above"
    if base_model is not None:
        assert (one_run["mu_table_mean"], one_run["rotation_std"]) == (0.5, 0.3), "the base model's values are written"

    # The TOML names its trees beside it: the two files copied elsewhere are the same model.
    assert 'boosted_map = "all.trees.json"' in out.read_text()
    moved = tmp_path / "robot_machine"
    moved.mkdir()
    for name in ("all.toml", "all.trees.json"):
        (moved / name).write_bytes((tmp_path / name).read_bytes())
    assert Config.from_toml(moved / "all.toml").topple.boosted_map == str((moved / "all.trees.json").resolve())
    assert _maps(moved / "all.toml") == one_run

    result = json.loads(record.read_text())
    assert result["down"]["fold_objects"] == result["side"]["fold_objects"] == result["boosted"]["fold_objects"], \
        "the steps share their folds"
    assert result["trees_file"] == str(tmp_path / "all.trees.json") and "fold_trees" not in result["boosted"]
    # Each step's record is its own command's, the same folds, the same maps under it.
    for step, path in zip(("down", "side", "boosted"), by_hand):
        alone = json.loads(path.with_suffix(".json").read_text())
        assert result[step]["cross_validated"] == alone["cross_validated"], step


@pytest.mark.parametrize("extra, message", [
    (["--boosted"], "choose one"),
    (["--fold-maps", "DIR"], "--fold-maps is for the boosted map fitted alone"),
    (["--folds-from", "DIR"], "--folds-from is for the boosted map fitted alone"),
])
def test_all_maps_refuses_what_it_cannot_keep_out_of_fold_before_reading_a_log(extra, message, tmp_path, capsys):
    from pipeline.studies.recalibrate import main

    extra = [str(tmp_path / "folds") if part == "DIR" else part for part in extra]
    # The log does not exist: the options are refused first.
    code = main([str(tmp_path / "no_log.parquet"), "--all-maps", *extra, "--out", str(tmp_path / "m.toml"),
                 "--json", str(tmp_path / "m.json")])
    assert code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "m.toml").exists() and not (tmp_path / "m.trees.json").exists()


@pytest.mark.parametrize("fit", ["--boosted", "--all-maps"])
def test_trees_a_config_file_may_name_are_never_replaced(fit, tmp_path, capsys):
    """A config file names its trees by path (a copy of it, a dataset's parameters): a second fit to the same
    --out is refused before any log is read, and the trees stay as they were."""
    from pipeline.studies.recalibrate import main

    trees = tmp_path / "robot.trees.json"
    trees.write_text("{}")
    code = main([str(tmp_path / "no_log.parquet"), fit, "--out", str(tmp_path / "robot.toml"), "--json", str(tmp_path / "r.json")])
    assert code == 2 and f"{trees} exists" in capsys.readouterr().err
    assert trees.read_text() == "{}" and not (tmp_path / "robot.toml").exists()


def test_fold_maps_a_dataset_may_name_are_never_replaced(tmp_path, capsys):
    from pipeline.studies.recalibrate import main

    folds = tmp_path / "folds"
    folds.mkdir()
    (folds / "fold_0.trees.json").write_text("{}")
    code = main([str(tmp_path / "no_log.parquet"), "--boosted", "--fold-maps", str(folds), "--out", str(tmp_path / "b.toml"),
                 "--json", str(tmp_path / "b.json")])
    assert code == 2 and f"{folds} holds fold maps already" in capsys.readouterr().err
    assert (folds / "fold_0.trees.json").read_text() == "{}"


def test_trees_written_since_the_check_are_not_replaced(tmp_path):
    """Two runs to one --out both pass the check before fitting; the second to write its trees is refused."""
    from pipeline.studies.recalibrate import trees_path, write_trees

    out = tmp_path / "robot.toml"
    assert write_trees({"first": 1}, out) == str(trees_path(out))
    with pytest.raises(FileExistsError, match="robot.trees.json exists"):
        write_trees({"second": 2}, out)
    assert json.loads(trees_path(out).read_text()) == {"first": 1}
