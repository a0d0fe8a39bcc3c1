"""The typed config: defaults from the thesis, overrides from a file and the CLI."""

import math

import pytest

from pipeline.model.config import Config


def test_defaults_are_the_thesis_values():
    config = Config()
    assert config.topple.mu_table_mean == 0.43 and config.topple.mu_finger_mean == 0.98
    assert config.topple.n_trials == 100 and config.contacts.n_contacts == 1000
    assert config.topple.rotation_std == 0.22 and config.topple.contact_std == 5.05e-4
    assert config.mdp.gamma == 0.95
    assert math.isclose(config.poses.same_pose_angle, math.radians(10))


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
    ],
)
def test_bad_overrides_are_clear_errors(overrides, message):
    with pytest.raises(ValueError, match=message):
        Config().with_overrides(overrides)
