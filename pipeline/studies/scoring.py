"""Scoring model settings against a push log, cheaply enough to search over them.

Everything that does not depend on the noise parameters is computed once
(``Scorer.__init__``): meshes, stable poses, the explicit actions of every logged
push (contact snapped to the surface, normal, direction in the pose frame), the
empirical next-pose distributions.  Scoring one setting (``Scorer.score``) then
runs the vectorised engine (``pipeline.model.topple.evaluate_pose``) once per
(object, start pose) on all of its pushes.  The embree ray structure of each mesh
is built on first use and kept with the mesh, so later settings reuse it.

The trial noise of (object, pose) comes from ``stream(seed, object, pose, "trials")``
and numpy draws normal(mean, std) as mean + std * z, so every setting sees the same
standard draws z: differences between settings are the parameters' effect, not
resampling noise (common random numbers), and a search over settings is deterministic.

A model that smooths its rows over the pose's candidate pushes (``smoothing_radius``,
docs/MODEL.md C.12) or maps P(topple) with its neighbourhood's (``feature_map``, C.13) needs
those candidates: they are made once per (object, pose) exactly as the dataset job makes them
(same seed, same contact settings), a logged push that is one of them is read from the
candidate's row, and any other is evaluated beside them as a probe.  That costs a whole pose's evaluation per group, about 30 times a plain setting.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from schema.frames import transform_points
from schema.vocabulary import STATUS_OK

from ..model.boosted_map import FEATURES as BOOSTED_FEATURES
from ..model.boosted_map import boosted_features
from ..model.collision import collision_object
from ..model.config import ContactConfig, ToppleConfig
from ..model.contacts import OffSurface, explicit_actions, object_contacts, pose_actions
from ..model.contacts import with_probes as probed_candidates
from ..model.edges import EdgeGeometry, edge_geometry
from ..model.feature_map import DOWN_FEATURES, FEATURES, SIDE_FEATURES, down_features, landing_rows, pose_features, side_features, side_rows
from ..model.outcomes import Actions, StablePose, ToppleTable
from ..model.rng import stream
from ..model.topple import TrialNoise, Trials, evaluate_pose, noisy_trials, pose_noise
from .logreader import LogError, Push, PushLog, same_push


@dataclass
class Group:
    """The pushes of one (object, start pose): what the engine needs, built once.

    drop_probabilities : (P,) float, the object's pose set's (``PoseSet.probabilities``), what
      ``evaluate_pose`` takes;  rows : (n,) int, positions of these pushes in ``PushLog.pushes``
    empirical : (n, P + 1) float, observed next-pose frequencies (last: outside the pose set)
    """

    object_id: str
    pose: StablePose
    drop_probabilities: np.ndarray
    actions: Actions
    rows: np.ndarray
    empirical: np.ndarray

    @property
    def n_poses(self) -> int:
        """P, the size of the object's pose set."""
        return len(self.drop_probabilities)


@dataclass
class CandidatesAndProbes:
    """A group's pose's candidate pushes followed by the logged pushes that are none of them.

    actions : (n + k,) candidates then probes;  candidates : n
    index : (pushes,) int, the row of ``actions`` that predicts each of the group's pushes
    """

    actions: Actions
    candidates: int
    index: np.ndarray


@dataclass
class Scores:
    """One predictor against every push of a log.

    tv : (n,) float, sup-form total variation between predicted and empirical next-pose distributions
    p_topple : (n,) float, predicted P(topple) (1 - P(start pose))
    brier : (n,) float, multi-class Brier score: sum over next poses (and the outside bucket)
      of (predicted - empirical)^2.  A proper score: its expectation is least for the true
      probabilities, so neither sharpening nor spreading a prediction can lower it
    """

    tv: np.ndarray
    p_topple: np.ndarray
    brier: np.ndarray


class Scorer:
    """A log prepared for scoring many settings; see the module docstring.

    log : a ``PushLog``;  seed : root of the model's trial streams
    empirical_topple : (n,) float, observed topple rate of each push
    object_index : (n,) int, index into ``object_ids`` of each push's object
    """

    def __init__(self, log: PushLog, seed: int = 0, contacts: ContactConfig | None = None) -> None:
        self.log = log
        self.seed = seed
        self.contacts = ContactConfig() if contacts is None else contacts
        self._candidates: dict[int, CandidatesAndProbes] = {}
        self.object_ids = sorted({p.object_id for p in log.pushes})
        index = {name: i for i, name in enumerate(self.object_ids)}
        self.object_index = np.array([index[p.object_id] for p in log.pushes], dtype=int)
        self.empirical_topple = np.array([p.topple_rate for p in log.pushes])
        self.repeats = np.array([len(p.outcomes) for p in log.pushes])
        self.groups: list[Group] = []
        by_group: dict[tuple[str, int], list[int]] = {}
        for row, push in enumerate(log.pushes):
            by_group.setdefault((push.object_id, push.pose), []).append(row)
        for (object_id, pose_index), rows in by_group.items():
            logged = log.objects[object_id]
            pose = logged.poses.poses[pose_index]
            pushes = [log.pushes[r] for r in rows]
            points = np.array([p.point for p in pushes])
            directions = np.array([p.direction for p in pushes])
            drop = logged.poses.probabilities
            n_poses = len(drop)
            try:
                actions = explicit_actions(logged.model, pose.transform, points, directions)
            except OffSurface as error:  # the log was recorded on another mesh, scale or frame
                raise LogError(f"{object_id}, pose {pose_index}, pushes {[p.push_id for p in pushes][:10]}: a logged push "
                               f"is not on the surface of the mesh read here ({error.where}): was the log "
                               "recorded with another mesh or scale?") from None
            self.groups.append(
                Group(
                    object_id=object_id,
                    pose=pose,
                    drop_probabilities=drop,
                    actions=actions,
                    rows=np.array(rows),
                    empirical=np.array([p.empirical(n_poses) for p in pushes]),
                )
            )

    def __len__(self) -> int:
        return len(self.log.pushes)

    def score(self, topple: ToppleConfig, spread_share: float = 0.0) -> Scores:
        """The toppling model with these parameters against every push (``predict``, then
        ``score_predictions``)."""
        return self.score_predictions(self.predict(topple), spread_share)

    def predict(self, topple: ToppleConfig) -> list[tuple[np.ndarray, np.ndarray]]:
        """The model's prediction of every push, per group (``self.groups``' order): next-pose
        distribution (pushes, P + 1) (the last bucket, outside the pose set, 0) and P(topple) (pushes,)."""
        out = []
        for group in self.groups:
            table, _, index = self._evaluate(group, topple)
            next_pose, p_topple = table.next_pose[index], table.p_topple[index]
            out.append((np.hstack([next_pose, np.zeros((len(group.rows), 1))]), p_topple))
        return out

    def features(self, topple: ToppleConfig) -> tuple[np.ndarray, np.ndarray]:
        """The feature map's features f(u) (docs/MODEL.md C.13) of every push, in log order,
        from ``topple`` with no map (what a feature map is fitted on).

        returns : features (n, F) float;  p_topple (n,) float, the unmapped P(topple)"""
        topple = topple.without_recalibration()
        out = np.full((len(self), len(FEATURES)), np.nan)
        p = np.full(len(self), np.nan)
        for group in self.groups:
            table, actions, index = self._evaluate(group, topple, candidates=True)
            weight = self.log.objects[group.object_id].model.mass * topple.gravity
            out[group.rows] = pose_features(table.p_topple, actions.points, actions.directions, table.mean_force, weight,
                                            pool=self.pose_candidates(group).candidates, rows=index)
            p[group.rows] = table.p_topple[index]
        return out, p

    def down_map_inputs(self, topple: ToppleConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the down map (docs/MODEL.md C.15) reads of every push, in log order, from ``topple``
        with no map (what the map is fitted on), each push evaluated among its pose's candidates
        as the engine maps it.

        returns : features (n, len(DOWN_FEATURES)) float;  p_topple (n,) float, the unmapped
          P(topple);  lands (n,) bool, whether the model knows where the push would land (C.13.2;
          where it does not, the engine keeps P = 0 whatever the map says)"""
        topple = topple.without_recalibration()
        out = np.full((len(self), len(DOWN_FEATURES)), np.nan)
        p = np.full(len(self), np.nan)
        lands = np.zeros(len(self), dtype=bool)
        for group in self.groups:
            table, actions, index = self._evaluate(group, topple, candidates=True)
            center_mass, edges = self.pose_edges(group)
            out[group.rows] = down_features(table.p_topple[index], actions.points[index], actions.normals[index],
                                            actions.directions[index], edges, center_mass)
            p[group.rows] = table.p_topple[index]
            lands[group.rows] = self._lands(group, table, actions, index)
        return out, p, lands

    def side_map_inputs(self, topple: ToppleConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the side map (docs/MODEL.md C.16) reads of every push, in log order, from ``topple``
        with no side map (what the map is fitted on: the other maps applied, as the engine has them).

        returns : features (n, len(SIDE_FEATURES)) float;  p_topple (n,) float;  taken (n,) bool,
          the pushes the map takes (``feature_map.side_rows``)"""
        topple = replace(topple, side_map=(), boosted_map="")  # the boosted map comes after the side map (C.19)
        out = np.full((len(self), len(SIDE_FEATURES)), np.nan)
        p = np.full(len(self), np.nan)
        taken = np.zeros(len(self), dtype=bool)
        for group in self.groups:
            table, actions, index = self._evaluate(group, topple)
            _, edges = self.pose_edges(group)
            p[group.rows] = table.p_topple[index]
            out[group.rows] = side_features(table.p_topple[index], actions.points[index], actions.directions[index], edges)
            taken[group.rows] = side_rows(table.p_topple[index], actions.directions[index, 2], topple.side_map_band)
        return out, p, taken

    def boosted_inputs(self, topple: ToppleConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the boosted map (docs/MODEL.md C.19) reads of every push, in log order, from ``topple``
        with no boosted map (what the map is fitted on: the other maps applied, as the engine has them),
        each push evaluated among its pose's candidates.

        returns : features (n, len(boosted_map.FEATURES)) float;  p_topple (n,) float, P without the
          boosted map;  lands (n,) bool, whether the model knows where the push would land (where it
          does not, the engine keeps the row whatever the map says)"""
        topple = replace(topple, boosted_map="")
        unmapped_model = topple.without_recalibration()
        out = np.full((len(self), len(BOOSTED_FEATURES)), np.nan)
        p = np.full(len(self), np.nan)
        lands = np.zeros(len(self), dtype=bool)
        for group in self.groups:
            table, actions, index = self._evaluate(group, topple, candidates=True)
            unmapped, _, _ = self._evaluate(group, unmapped_model, candidates=True)
            center_mass, edges = self.pose_edges(group)
            pool = self.pose_candidates(group).candidates
            obj = self.log.objects[group.object_id].model
            features = boosted_features(table.p_topple, unmapped.p_topple, table.mean_force, actions, edges, center_mass,
                                        group.drop_probabilities, group.pose.index, obj, topple.gravity, pool=pool)
            out[group.rows] = features[index]
            p[group.rows] = table.p_topple[index]
            lands[group.rows] = self._lands(group, table, actions, index)
        return out, p, lands

    def _lands(self, group: Group, table: ToppleTable, actions: Actions, index: np.ndarray) -> np.ndarray:
        """Whether the model knows where each of ``group``'s pushes would land (C.13.2, over its pose's
        candidates), (pushes,) bool: where it does not, the engine's maps keep the row as it is."""
        landing = landing_rows(table.next_pose, group.pose.index, actions.points, actions.directions,
                               pool=self.pose_candidates(group).candidates, rows=index)
        return landing.sum(axis=1) > 0

    def pose_edges(self, group: Group) -> tuple[np.ndarray, EdgeGeometry]:
        """The centre of mass of ``group``'s object in its pose's frame, (3,) float, m (not the
        mesh's: the engine's maps read the pose frame's), and the pose's ``edge_geometry``."""
        model = self.log.objects[group.object_id].model
        center_mass = transform_points(group.pose.transform, model.center_mass[None])[0]
        return center_mass, edge_geometry(group.pose.base_edges, center_mass)

    def _evaluate(self, group: Group, topple: ToppleConfig, candidates: bool = False) -> tuple[ToppleTable, Actions, np.ndarray]:
        """``group``'s table (``_evaluated_actions``' actions).
        returns : the table, its actions, and (pushes,) int, the row that predicts each push"""
        obj = self.log.objects[group.object_id].model
        actions, n_candidates, index = self._evaluated_actions(group, topple, candidates)
        table = evaluate_pose(obj, group.pose, group.drop_probabilities, actions, topple, self._trial_stream(group),
                              candidates=n_candidates)
        return table, actions, index

    def _evaluated_actions(self, group: Group, topple: ToppleConfig, candidates: bool = False) -> tuple[Actions, int, np.ndarray]:
        """What ``group``'s table is evaluated over: its pose's candidates and its probes when the model needs
        them (``ToppleConfig.needs_candidates``) or ``candidates`` asks, else its pushes alone.
        returns : the actions, how many of them lead as the candidate set (``evaluate_pose``'s ``candidates``),
          and (pushes,) int, each logged push's action"""
        if topple.needs_candidates or candidates:
            pool = self.pose_candidates(group)
            return pool.actions, pool.candidates, pool.index
        return group.actions, len(group.rows), np.arange(len(group.rows))

    def _trial_stream(self, group: Group) -> np.random.Generator:
        """The engine's stream of ``group``'s pose's trials for this scorer's seed (``rng.stream``)."""
        return stream(self.seed, self.log.objects[group.object_id].model.name, group.pose.index, "trials")

    def logged_trials(self, group: Group, topple: ToppleConfig) -> tuple[Trials, EdgeGeometry, np.ndarray]:
        """The engine's trials of ``group``'s logged pushes, drawn as ``_evaluate``'s ``evaluate_pose`` draws them
        (``topple.pose_noise``: the candidates' noise first, the logged pushes' as probes), and the pose's edges.

        returns : trials (pushes T, ...), action-major;  edges;  (pushes,) bool, the pushes the engine evaluates
          (``ok``; the others' trials are drawn but never decided)"""
        obj = self.log.objects[group.object_id].model
        actions, n_candidates, index = self._evaluated_actions(group, topple)
        noise = pose_noise(self._trial_stream(group), len(actions.status), n_candidates, topple)
        noise = TrialNoise(*(getattr(noise, f).take(index, axis=0) for f in TrialNoise.__dataclass_fields__))
        center_mass, edges = self.pose_edges(group)
        trials = noisy_trials(obj, group.pose.transform, center_mass, actions.points[index], actions.normals[index],
                              actions.directions[index], noise, topple)
        return trials, edges, actions.status[index] == STATUS_OK

    def pose_candidates(self, group: Group) -> CandidatesAndProbes:
        """The candidate pushes of ``group``'s pose as the dataset job makes them, plus its logged
        pushes that are none of them (probes).  Built on first use for every logged pose of the
        object, whose contacts and collision mesh are shared by its poses (as in the dataset
        job), and kept."""
        if id(group) not in self._candidates:
            obj = self.log.objects[group.object_id].model
            points, normals = object_contacts(obj, self.contacts, self.seed)
            collision = collision_object(obj.mesh)
            for other in self.groups:
                if other.object_id == group.object_id:
                    pool = pose_actions(points, normals, obj.mesh, collision, other.pose.transform, self.contacts)
                    self._candidates[id(other)] = with_probes(pool, other.actions, [self.log.pushes[r] for r in other.rows])
        return self._candidates[id(group)]

    def score_predictions(self, predictions: list[tuple[np.ndarray, np.ndarray]], spread_share: float = 0.0) -> Scores:
        """Scores of ``predict``'s predictions, with ``spread_share`` of every push's probability
        moved to ``topple_spread`` (0: as predicted; the report's check of what informative TV
        rewards, docs/VALIDATION.md "Reading informative TV")."""
        by_group = dict(zip(map(id, self.groups), predictions))

        def prediction(group: Group) -> tuple[np.ndarray, np.ndarray]:
            predicted, p = by_group[id(group)]
            if spread_share:
                spread = topple_spread(group)  # (P + 1,)
                predicted = (1.0 - spread_share) * predicted + spread_share * spread
                p = (1.0 - spread_share) * p + spread_share * (1.0 - spread[group.pose.index])
            return predicted, p

        return self._scores(prediction)

    def score_variant(self, topple: ToppleConfig, variant: str) -> Scores:
        return self.score(replace(topple, variant=variant))

    def never_topples(self) -> Scores:
        """The trivial predictor "it stays": all mass on the start pose."""
        return self.constant_rate(0.0)

    def constant_rate(self, rate: float) -> Scores:
        """The trivial predictor "it topples with probability ``rate``", whatever the push.

        The topple mass is spread evenly over the start pose's base edges that are not
        blocked, onto the pose each one leads to (geometry only, nothing learnt from the log);
        a pose without such an edge keeps all its mass.
        """

        def prediction(group: Group) -> tuple[np.ndarray, float]:
            stays = np.zeros(group.n_poses + 1)
            stays[group.pose.index] = 1.0
            predicted = (1.0 - rate) * stays + rate * topple_spread(group)  # (P + 1,)
            return predicted[None], 1.0 - predicted[group.pose.index]

        return self._scores(prediction)

    def replay(self, replay: PushLog) -> Scores:
        """Physics predicting itself: every push predicted by the next-pose frequencies of a
        replay of it (the same push played with other noise draws, ``toppledb play
        --noise-draws``).  With enough replayed repeats this is the best any predictor of the
        push can do; what it still scores is the log's own repeat noise.

        Raises ``LogError`` when a push has no replay, or its replay is another push.
        """
        # Push ids are unique within one log, so a replay of several logs names them in the same order.
        replayed = {p.key: p for p in replay.pushes}
        missing = [p for p in self.log.pushes if p.key not in replayed]
        if missing:
            first = missing[0]
            raise LogError(f"the replay has no usable rows for {len(missing)} of the log's {len(self)} pushes "
                           f"(first: object {first.object_id}, push_id {first.push_id}, log {self.log.log_name(first.log)}); "
                           "replay the same objects and pushes, one replay per log in the logs' order")
        for push in self.log.pushes:
            twin = replayed[push.key]
            if not same_push(twin, push):
                raise LogError(f"push_id {push.push_id} of object {push.object_id} is another push in the replay "
                               "(start pose, point or direction differ); replay with the log's own seed and parameters")

        def prediction(group: Group) -> tuple[np.ndarray, np.ndarray]:
            twins = [replayed[self.log.pushes[r].key] for r in group.rows]
            predicted = np.array([t.empirical(group.n_poses) for t in twins])
            return predicted, 1.0 - predicted[:, group.pose.index]

        return self._scores(prediction)

    def brier_floor(self) -> np.ndarray:
        """Per push, the part of any predictor's Brier score that is the log's own repeat noise
        (``brier_floor``).  returns : (n,) float, NaN for a push with one repeat"""
        out = np.full(len(self), np.nan)
        for group in self.groups:
            out[group.rows] = brier_floor(group.empirical, self.repeats[group.rows])
        return out

    def _scores(self, prediction) -> Scores:
        """Every push scored against a predictor given per group: ``prediction(group)`` is the
        next-pose distribution ((pushes, P + 1), or (1, P + 1) for all of them) and P(topple)."""
        tv, p_topple, brier = np.empty(len(self)), np.empty(len(self)), np.empty(len(self))
        for group in self.groups:
            predicted, p = prediction(group)
            tv[group.rows] = sup_tv(predicted, group.empirical)
            brier[group.rows] = brier_score(predicted, group.empirical)
            p_topple[group.rows] = p
        return Scores(tv, p_topple, brier)


def with_probes(pool: Actions, logged: Actions, pushes: list[Push]) -> CandidatesAndProbes:
    """``pool`` (a pose's candidates) followed by the logged pushes that are not ok candidates of it
    (``contacts.with_probes``, as ``pipeline.evaluate`` places explicit pushes).

    logged : the pushes as explicit actions;  pushes : the log's ``Push`` of each, whose recorded
    point and direction (pose frame) are matched to a candidate
    """
    actions, candidates, index = probed_candidates(
        pool, logged, np.array([p.point for p in pushes]).reshape(-1, 3), np.array([p.direction for p in pushes]).reshape(-1, 3))
    return CandidatesAndProbes(actions=actions, candidates=candidates, index=index)


def topple_spread(group: Group) -> np.ndarray:
    """A topple that knows nothing about the push: mass 1 spread evenly over the poses the start
    pose's unblocked base edges lead to, or all on the start pose when there is none (geometry
    only, nothing learnt from a log).  returns : (P + 1,) float, the last bucket (unknown) 0"""
    spread = np.zeros(group.n_poses + 1)
    targets = group.pose.edge_final_pose[~group.pose.edge_blocked]
    targets = targets[targets != group.pose.index]
    if len(targets):
        np.add.at(spread, targets, 1.0 / len(targets))
    else:
        spread[group.pose.index] = 1.0
    return spread


def brier_score(predicted: np.ndarray, empirical: np.ndarray) -> np.ndarray:
    """Row-wise multi-class Brier score, sum over buckets of (predicted - empirical)^2.

    predicted : (n, B) or (1, B) float;  empirical : (n, B) float
    returns : (n,) float in [0, 2]
    """
    return np.square(predicted - empirical).sum(axis=1)


def brier_floor(empirical: np.ndarray, repeats: np.ndarray) -> np.ndarray:
    """The Brier score a push's true next-pose distribution p is expected to get against R
    observed repeats, sum over buckets of p (1 - p) / R, estimated without bias from the observed
    frequencies e as sum e (1 - e) / (R - 1).  No predictor, physics included, can expect less.

    empirical : (n, B) float, observed frequencies;  repeats : (n,) int, R per push
    returns : (n,) float, NaN where R = 1 (one repeat says nothing about the spread)
    """
    spread = (empirical * (1.0 - empirical)).sum(axis=1)
    repeats = np.asarray(repeats, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(repeats > 1, spread / (repeats - 1), np.nan)


def sup_tv(predicted: np.ndarray, empirical: np.ndarray) -> np.ndarray:
    """Row-wise sup-form total variation, max over buckets of |predicted - empirical|.

    predicted : (n, B) or (1, B) float;  empirical : (n, B) float
    returns : (n,) float in [0, 1]
    """
    return np.abs(predicted - empirical).max(axis=1)
