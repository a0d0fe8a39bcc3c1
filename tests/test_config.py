"""The typed config: defaults from the thesis, overrides from a file and the CLI."""

import math
import re

import numpy as np
import pytest

from pipeline.model.config import NO_MAP, PRESETS, Config, ContactConfig, Range, field_range, parameter_table


def test_defaults_are_the_calibrated_corrected_model_and_the_thesis_preset_is_the_thesis():
    config = Config()
    assert config.topple.variant == "corrected" and config.topple.applied_corrections == {"finger_friction", "force_limit", "momentum", "stuck_finger", "tip_path", "tip_back"}
    assert config.topple.n_trials == 100 and config.contacts.n_contacts == 1000
    assert config.mdp.gamma == 0.95
    assert math.isclose(config.poses.same_pose_angle, math.radians(10))
    thesis = Config.from_toml(PRESETS / "thesis.toml")
    assert thesis.topple.variant == "robust" and thesis.topple.applied_corrections == frozenset()
    assert thesis.topple.mu_table_mean == 0.43 and thesis.topple.mu_finger_mean == 0.98
    assert thesis.topple.rotation_std == 0.22 and thesis.topple.contact_std == 5.05e-4
    assert (thesis.topple.mu_table_std, thesis.topple.mu_finger_std, thesis.topple.direction_std) == (0.1, 0.2, 0.055)
    # Only the model's noise and variant differ: everything else is the same config.
    # (The corrected variant with the thesis's choice from every push needs no down map, MODEL.md C.15.)
    assert thesis.with_overrides({"topple.variant": "corrected", "topple.down_map": ""}).contacts == config.contacts


def test_the_calibrated_defaults_are_the_shipped_calibration_rounded():
    """config.py's noise defaults are reports/calibrated_corrected.toml to three significant digits."""
    import tomllib
    from pathlib import Path

    calibrated = tomllib.loads((Path(__file__).parents[1] / "reports" / "calibrated_corrected.toml").read_text())["topple"]
    noise = {key: value for key, value in calibrated.items() if key not in NO_MAP}  # it clears every map
    assert noise, "the calibration file holds no noise parameters"
    for key, value in noise.items():
        assert math.isclose(getattr(Config().topple, key), float(f"{value:.3g}")), key


def test_the_default_map_is_the_shipped_recalibration_exactly():
    """config.py's default recalibration knots are reports/recalibrated_centred.toml's, unrounded,
    fitted under the default smoothing; the thesis's variants ignore them."""
    import tomllib
    from pathlib import Path

    fitted = tomllib.loads((Path(__file__).parents[1] / "reports" / "recalibrated_centred.toml").read_text())["topple"]
    topple = Config().topple
    assert topple.applied_recalibration == (tuple(fitted["recalibration_x"]), tuple(fitted["recalibration_y"]))
    assert (topple.smoothing_radius, topple.smoothing_angle) == (fitted["smoothing_radius"], fitted["smoothing_angle"])
    assert Config.from_toml(PRESETS / "thesis.toml").topple.applied_recalibration == ((), ())


def test_round_trip_and_overrides(tmp_path):
    config = Config().with_overrides({"topple.n_trials": "10", "topple.variant": "baseline", "seed": 3})
    assert config.topple.n_trials == 10 and config.topple.trials == 1 and config.seed == 3
    assert Config.from_dict(config.to_dict()) == config
    path = tmp_path / "params.toml"
    path.write_text('seed = 5\n[contacts]\nn_contacts = 20\n[topple]\nvariant = "robustness"\n')
    loaded = Config.from_toml(path)
    assert loaded.seed == 5 and loaded.contacts.n_contacts == 20 and loaded.topple.robust


@pytest.mark.parametrize(
    "overrides, message",
    [
        ({"topple.nope": 1}, "unknown config key"),
        ({"nope.n_trials": 1}, "unknown config section"),
        ({"topple.n_trials": "many"}, "expects int"),
        ({"topple.variant": "magic"}, "unknown variant"),
        # A TOML boolean is no number (Python's bool is an int), nor a number a switch.
        ({"topple.mu_table_mean": True}, "expects float, got True"),
        ({"contacts.n_contacts": True}, "expects int, got True"),
        ({"mdp.believe_failures": 1}, "expects bool, got 1"),
        ({"topple.landing_spread": np.True_}, "expects float, got"),
    ],
)
def test_bad_overrides_are_clear_errors(overrides, message):
    with pytest.raises(ValueError, match=message):
        Config().with_overrides(overrides)


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("contacts.n_contacts", "0", "must be in [1, 100000]"),
        ("contacts.n_contacts", "10000000000", "must be in [1, 100000]"),
        ("topple.mu_table_mean", "-3", "must be >= 0"),
        ("topple.mu_table_mean", "nan", "must be a finite number, got 'nan'"),  # not ">= 0": nan is no number to compare
        ("mdp.gamma", "0", "must be in (0, 1]"),
        ("mdp.gamma", "1.5", "must be in (0, 1]"),
        ("poses.min_probability", "1", "must be in [0, 1)"),
        ("suction.ring_samples", "2", "must be >= 3"),
        ("contacts.max_up_angle", "2", "must be in [0, 1.5708]"),
        ("seed", "-1", "must be >= 0"),
    ],
)
def test_every_parameter_is_range_checked(key, value, message):
    with pytest.raises(ValueError, match=re.escape(f"config key '{key}' {message}")):
        Config().with_overrides({key: value})


def test_ranges_live_on_the_fields_and_accept_the_defaults():
    rows = parameter_table()
    numeric = [(key, value) for key, value, _ in rows if isinstance(value, (int, float)) and not isinstance(value, bool)]
    assert all(accepted for key, value, accepted in rows if (key, value) in numeric), "every number has a range"
    assert Config.from_dict(Config().to_dict()) == Config(), "the defaults pass their own checks"
    assert field_range(ContactConfig, "n_contacts") == Range(1, 100_000)
    assert Range(0.0, 1.0, lo_open=True).contains(1.0) and not Range(0.0, 1.0, lo_open=True).contains(0.0)


def test_config_accepts_a_preset_name_and_lists_the_presets_when_it_is_neither():
    from pipeline.cli import UsageError, make_config, parser

    config = make_config(parser().parse_args(["dataset", "--config", "thesis"]))
    assert config.topple.variant == "robust" and config.topple.mu_finger_mean == 0.98
    with pytest.raises(UsageError, match=r"config file not found: nothing \(presets: thesis\)"):
        make_config(parser().parse_args(["dataset", "--config", "nothing"]))


def test_numpy_booleans_set_switches_and_only_switches():
    assert Config().with_overrides({"mdp.retry_failed": np.False_, "mdp.believe_failures": np.False_}).mdp.retry_failed is False


def test_a_boosted_map_a_config_file_names_by_a_relative_path_is_the_file_beside_it(tmp_path, monkeypatch):
    """As ``toppledb recalibrate`` writes a TOML and its trees: the two move together.  An absolute path and a
    packaged map's name are taken as written; ``--set`` on the command line reads from the working directory."""
    (tmp_path / "robot").mkdir()
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    for value, expected in [("robot.trees.json", str((tmp_path / "robot" / "robot.trees.json").resolve())),
                            ("maps/robot.trees.json", str((tmp_path / "robot" / "maps" / "robot.trees.json").resolve())),
                            ("/srv/maps/robot.trees.json", "/srv/maps/robot.trees.json"),
                            ("boosted_map_s41", "boosted_map_s41"), ("", "")]:
        (tmp_path / "robot" / "robot.toml").write_text(f'[topple]\nboosted_map = "{value}"\n'
                                                      + ("[mdp]\nmin_direction_z = -0.3\n" if not value else ""))
        assert Config.from_toml(tmp_path / "robot" / "robot.toml").topple.boosted_map == expected, value
    on_the_line = Config().with_overrides({"topple.boosted_map": "robot.trees.json"})
    assert on_the_line.topple.boosted_map == "robot.trees.json"


@pytest.mark.parametrize(
    "accepted, text",
    [
        (Range(0.0, None, lo_open=True), "> 0"),
        (Range(1, None), ">= 1"),
        (Range(None, 2.5, hi_open=True), "< 2.5"),
        (Range(None, 2.5), "<= 2.5"),
        (Range(), "finite"),
        (Range(0.0, 1.0, hi_open=True), "in [0, 1)"),
        (Range(0.0, 1.0, lo_open=True), "in (0, 1]"),
    ],
)
def test_a_range_names_its_bounds_and_whether_each_is_open(accepted, text):
    assert accepted.text() == text


@pytest.mark.parametrize("accepted", [Range(), Range(0.0, None), Range(None, 1.0), Range(0.0, 1.0, lo_open=True, hi_open=True)])
def test_no_range_holds_a_non_finite_number(accepted):
    assert not any(accepted.contains(v) for v in (math.nan, math.inf, -math.inf))


def test_a_config_file_s_bad_keys_and_sections_are_named_with_their_section(tmp_path):
    path = tmp_path / "params.toml"
    for text, message in [("[topple]\nnope = 1\nalso = 2\n", "unknown config key(s): topple.also, topple.nope"),
                          ("topple = 3\n", "config section 'topple' must be a table"),
                          ("[topple]\nrecalibration_x = [0.0, nan]\n", "config key every entry of 'topple.recalibration_x' must be a finite number"),
                          ("[topple]\nn_trials = 'many'\n", "config key 'topple.n_trials' expects int")]:
        path.write_text(text)
        with pytest.raises(ValueError, match=re.escape(message)):
            Config.from_toml(path)
