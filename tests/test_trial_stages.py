"""Where the model says no (``topple.trial_stages``, ``pipeline.studies.trial_stages``).

The standing 0.05 x 0.08 x 0.15 m box pushed horizontally across its 5 cm side at the thesis's frictions
(mu_T 0.43, mu_f 0.98) has C.2's closed form (tests/test_model_corrections.py): below h = mu_f w the finger's
friction leaves no tipping moment, up to h* = d / mu_T + mu_f (w - d) the table slides, above it the box tips.
"""

import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
from shapes import explicit_trials, noise_free, overhanging_frustum, random_object, standing_box, stroke_to_apex

from pipeline.model.collision import collision_object
from pipeline.model.config import Config, ContactConfig
from pipeline.model.contacts import object_contacts, pose_actions
from pipeline.model.edges import edge_geometry
from pipeline.model.poses import stable_poses
from pipeline.model.rng import stream
from pipeline.model.topple import TRIAL_STAGES, Trials, evaluate_pose, noisy_trials, pose_noise, trial_outcomes, trial_stages
from pipeline.studies import trial_stages as study
from pipeline.studies.logreader import read_log
from pipeline.studies.scoring import Scorer
from schema.frames import transform_points
from schema.vocabulary import STATUS_OK
from tests.test_validation import model_logs  # noqa: F401 (fixture)

MU_T, MU_F = 0.43, 0.98
FRUSTUM_HEIGHT = 0.06


def _stage_names(shape, points, direction, topple):
    obj, trials, edges = explicit_trials(shape, points, np.tile(direction, (len(points), 1)), topple)
    return [TRIAL_STAGES[s] for s in trial_stages(trials, edges, obj.mass, topple)]


@pytest.fixture(scope="module")
def box():
    return standing_box()


def test_the_standing_box_stops_where_the_closed_form_says(box):
    d, w = 0.025, 0.05
    threshold = d / MU_T + MU_F * (w - d)  # 8.3 cm
    heights = [MU_F * w - 0.005, MU_F * w + 0.005, threshold - 0.001, threshold + 0.001, 0.14]
    points = [[-d, 0.0, h] for h in heights]
    names = _stage_names(box, points, [1.0, 0.0, 0.0], noise_free(corrections="finger_friction,force_limit"))
    assert names == ["friction_holds", "table_slides", "table_slides", "tips", "tips"]


def test_a_push_over_the_force_limit_or_away_from_the_face_is_named_so(box):
    obj, _, _ = box
    d, w, h = 0.025, 0.05, 0.12
    force = obj.mass * 9.81 * d / (h - MU_F * w) * np.hypot(1.0, MU_F)  # C.2's finger force there
    for limit, expected in ((force * 1.001, "tips"), (force * 0.999, "over_force_limit")):
        topple = noise_free(corrections="finger_friction,force_limit", max_finger_force=limit)
        assert _stage_names(box, [[-d, 0.0, h]], [1.0, 0.0, 0.0], topple) == [expected]
    # Pushed along the face's outward normal the finger never advances into it.
    assert _stage_names(box, [[-d, 0.0, h]], [-1.0, 0.0, 0.0], noise_free(corrections="finger_friction")) == ["face_never_recedes"]


@pytest.mark.parametrize("height", [0.135, 0.145])
def test_a_stroke_short_of_the_apex_stops_the_trial_before_it(box, height):
    travel = stroke_to_apex(height)
    for stroke, expected in ((travel - 1e-3, "stops_before_apex"), (travel + 1e-3, "tips")):
        topple = noise_free(corrections="finger_friction,stroke", stroke=stroke)
        assert _stage_names(box, [[0.0, -0.04, height]], [0.0, 1.0, 0.0], topple) == [expected]


def test_the_stuck_finger_is_named_where_it_tips_what_c2_leaves():
    frustum = overhanging_frustum()
    direction = np.array([0.87, 0.0, -0.5]) / np.hypot(0.87, 0.5)
    point = [[0.03, 0.0, FRUSTUM_HEIGHT]]
    assert _stage_names(frustum, point, direction, noise_free(corrections="finger_friction")) != ["tips"]
    stuck = noise_free(corrections="finger_friction,stuck_finger", stuck_finger_share=1.0)
    assert _stage_names(frustum, point, direction, stuck) == ["stuck_finger_tips"]


def _pose_trials(obj, pose, topple):
    """The engine's trials of one pose's ok candidates (60 contacts), and its edges."""
    contacts = ContactConfig(n_contacts=60)
    points, normals = object_contacts(obj, contacts, 11)
    actions = pose_actions(points, normals, obj.mesh, collision_object(obj.mesh), pose.transform, contacts)
    ok = actions.status == STATUS_OK
    center_mass = transform_points(pose.transform, obj.center_mass[None])[0]
    noise = pose_noise(stream(0, obj.name, pose.index, "trials"), int(ok.sum()), int(ok.sum()), topple)
    trials = noisy_trials(obj, pose.transform, center_mass, actions.points[ok], actions.normals[ok], actions.directions[ok],
                          noise, topple)
    return trials, edge_geometry(pose.base_edges, center_mass)


def test_stages_agree_with_the_engine_trial_by_trial():
    """On a random shape's candidates with the default's noise and corrections and the carried finger, each
    toppling stage is what the engine decides with the later corrections left out, trial by trial: "tips" is
    C.2's topple (after C.10 and C.14), "carried_finger_tips" what C.23 adds, "stuck_finger_tips" what C.11
    adds; "invalid" is a finger that missed, and no trial the engine topples is at an earlier stage."""
    obj = random_object(44)
    base = Config().topple.without_recalibration()
    topple = replace(base, corrections=base.corrections + ",carried_finger")

    def without(*names):
        return replace(topple, corrections=",".join(sorted(topple.applied_corrections - set(names))))

    seen = set()
    for pose in stable_poses(obj).poses[:4]:
        trials, edges = _pose_trials(obj, pose, topple)
        stages = trial_stages(trials, edges, obj.mass, topple)
        by_c2, by_carried, by_all = (trial_outcomes(trials, edges, obj.mass, model)[0] >= 0 for model in
                                     (without("carried_finger", "stuck_finger", "tip_back"), without("stuck_finger", "tip_back"), topple))
        assert np.array_equal(stages == TRIAL_STAGES.index("tips"), by_c2)
        assert np.array_equal(stages == TRIAL_STAGES.index("carried_finger_tips"), by_carried & ~by_c2)
        assert np.array_equal(stages == TRIAL_STAGES.index("stuck_finger_tips"), by_all & ~by_carried)
        assert np.array_equal(stages == TRIAL_STAGES.index("invalid"), ~trials.valid)
        assert not (by_all & (stages < TRIAL_STAGES.index("tips"))).any()
        seen |= {TRIAL_STAGES[s] for s in np.unique(stages)}
    expected = {"tips", "carried_finger_tips", "stuck_finger_tips", "friction_holds", "table_slides"}
    assert expected <= seen, f"the poses' trials should reach every one of these stages, missing {expected - seen}"


def test_a_lone_valid_trial_leaves_the_invalid_ones_invalid(box):
    """With fewer than two valid trials the engine computes every row; the invalid ones still read "invalid"."""
    obj, trials, edges = explicit_trials(box, [[-0.025, 0.0, 0.12]] * 3, [[1.0, 0.0, 0.0]] * 3, noise_free(corrections="finger_friction"))
    trials = Trials(trials.contact, trials.normal, trials.push, trials.mu_table, trials.mu_finger,
                    np.array([True, False, False]), trials.stuck_draw)
    names = [TRIAL_STAGES[s] for s in trial_stages(trials, edges, obj.mass, noise_free(corrections="finger_friction"))]
    assert names == ["tips", "invalid", "invalid"]


def test_the_thesis_variants_are_refused(box):
    obj, trials, edges = explicit_trials(box, [[-0.025, 0.0, 0.12]], [[1.0, 0.0, 0.0]], noise_free("robust"))
    with pytest.raises(ValueError, match="finger_friction"):
        trial_stages(trials, edges, obj.mass, noise_free("robust"))


def test_the_study_replays_the_engine_trials_of_every_logged_push(model_logs, tmp_path):  # noqa: F811
    """The study's shares are the engine's trials: with the default's maps (candidates first, the logged
    pushes as probes), a push's toppling share is the share of its trials ``evaluate_pose`` topples."""
    from pipeline.studies.synthetic_log import CANDIDATES_PER_POSE

    config = Config().with_overrides({"contacts.n_contacts": CANDIDATES_PER_POSE})
    path = str(model_logs / "reported.parquet")
    table = study.push_table(path, config)
    shares = table[list(TRIAL_STAGES)].to_numpy()
    assert np.allclose(shares.sum(axis=1), 1.0)
    scorer = Scorer(read_log([path]), config.seed, config.contacts)
    assert np.array_equal(table.physics.to_numpy(), scorer.empirical_topple)
    for group in scorer.groups:
        obj = scorer.log.objects[group.object_id].model
        pool = scorer.pose_candidates(group)
        engine = evaluate_pose(obj, group.pose, group.drop_probabilities, pool.actions, config.topple,
                               stream(config.seed, obj.name, group.pose.index, "trials"), candidates=pool.candidates)
        toppled = (engine.outcomes[pool.index] >= 0).mean(axis=1)
        np.testing.assert_array_equal(table[list(study.TOPPLING)].to_numpy()[group.rows].sum(axis=1), toppled)

    out = tmp_path / "stages.json"
    assert study.main([path, "--json", str(out), "--table", str(tmp_path / "stages.csv")]) == 0
    result = json.loads(out.read_text())
    assert result["stages"] == list(TRIAL_STAGES)
    assert {direction for directions in result["by_log"].values() for direction in directions} <= {"above", "side", "below"}
    assert len(pd.read_csv(tmp_path / "stages.csv")) == len(table)
    # Another model's trials by --set; the thesis's variants have no stages and are refused.
    carried = tmp_path / "carried.json"
    assert study.main([path, "--json", str(carried), "--set", "topple.corrections=finger_friction,carried_finger"]) == 0
    assert json.loads(carried.read_text())["corrections"] == ["carried_finger", "finger_friction"]
    with pytest.raises(SystemExit):
        study.main([path, "--json", str(tmp_path / "thesis.json"), "--config", "thesis"])


def test_the_summary_counts_every_toppling_stage_and_splits_by_physics():
    """Two pushes from above, one that physics topples: the model's toppling share is every toppling stage's."""
    shares = {name: [0.0, 0.0] for name in TRIAL_STAGES}
    shares["tips"], shares["carried_finger_tips"], shares["stuck_finger_tips"] = [0.2, 0.0], [0.5, 0.1], [0.1, 0.0]
    shares["friction_holds"] = [0.2, 0.9]
    table = pd.DataFrame({"log": "L", "object_id": ["a", "b"], "start_pose": 0, "u_z": -0.9, "direction": "above",
                          "physics": [0.8, 0.1], "repeats": 10, "served_p": [0.6, 0.2], **shares})
    above = study.summarise(table)["L"]["above"]
    assert above["toppled_in_physics"]["model_trials_topple"] == pytest.approx(0.8)
    assert above["stayed_in_physics"]["model_trials_topple"] == pytest.approx(0.1)
    assert above["all"]["pushes"] == 2 and above["all"]["stages"]["friction_holds"] == pytest.approx(0.55)
