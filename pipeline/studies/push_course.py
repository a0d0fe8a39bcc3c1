"""How a policy's pushes go in physics, step by step, by push direction.

``candidate_choice`` says where the tables choose worse than physics would; this study says how the
pushes they choose go.  For each push direction (from above: u_z < -0.3 in the pose frame; from the
side; from below: u_z >= 0.3, as ``candidate_choice`` splits them) it takes one start pose of each of
up to ``--per-class`` objects where the policy pushes that way, plays the policy's push ``--repeats``
times in pybullet under the simulated world's noise (the thesis preset, as ``policies-physics``) and
traces every step of the finger's stroke.  Each play is then described three ways:

- its course (``course_kind``): the object tips before it slides, slides and then tips, tips and falls
  back once the finger withdraws, slides or turns without tipping, stalls at the finger's force limit,
  stays under a lighter finger (which slid over or off it), or is never touched (a pose it leaves on its own);
- for a topple, the side it tips to (``tip_side``), seen from above: away from the finger (within 45
  degrees of the push), sideways, or towards the finger;
- for a topple, where it lands (``landing_kind``), against the chain of poses the model derives for
  the base edge it tipped over (the edge whose outward normal is nearest the tip direction): that
  edge's first pose (``edge_final_pose``), the pose a fall rolls on to (``edge_momentum_pose``, C.8),
  the one beyond it (``edge_onward_pose``, C.18), or elsewhere.

For a topple, the edge it tipped over is set beside two predictions of it: the edge the model's own trials of
the push tip over most often (``model_edge``) and the edge the line from the centre of mass's foot through the
contact's crosses (``line_edge``, where a vertical press would tip it), overall and for the topples that tip back,
more than 90 degrees from the push's horizontal direction.

Beside them the rows: the predicted P(topple), the value the rows expect of a topple
(sum over x' != x of P(x') V_s(x') / P(topple)) against the V_s where the plays landed (0 outside the
pose set), and the rows' probability of the pose each topple landed in.  Standard errors are
clustered by object (``pooled_gain.clustered_mean_se``).  A few minutes for 70 objects a class:

    python -m pipeline.studies.push_course data/dataset --per-class 70 --repeats 5 --seed 53

Run on the corpus's own dataset it describes the model on the objects its maps were fitted on: a
description of mechanisms for the next model step, not a judgement of the model.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from schema.frames import transform_points, unit
from schema.vocabulary import NO_OP, POLICIES

from ..build.atomic import write_text_atomic
from ..model.config import Config, ToppleConfig
from ..model.outcomes import StablePose
from ..model.rng import stream
from .candidate_choice import CLASSES, direction_class
from .policies_physics import PURPOSE, ExperimentError, ObjectPlan, dataset_config, load_planned, object_plans, world_config
from .pooled_gain import clustered_entry
from .robust_policy import next_pose_rows

KINDS = ("tips first", "slides, then tips", "tips, falls back", "slides or turns, no tip", "stalls", "stays", "no contact")
"""A play's course (``course_kind``)."""
SIDES = ("away", "sideways", "towards")
"""The side a topple tips to, seen from above (``tip_side``)."""
LANDINGS = ("first pose", "rolled on", "onward", "elsewhere")
"""Where a topple lands against its edge's chain of poses (``landing_kind``)."""
TILT_ONSET = 3.0
"""deg: the object has begun to tip once it has turned this far out of its start pose's plane."""
TIP_TILT = 8.0
"""deg: the tilt at which the tip's direction is read (past the rocking of a settling contact)."""
SLIDE_ONSET = 0.003
"""m: the base has begun to slide once the table point under the centre of mass has moved this far."""
MOVED_SLIDE, MOVED_YAW = 0.005, 5.0
"""m and deg: a play that stayed moved it if it slid or turned this far."""
STALL_SHARE = 0.9
"""A play that neither tipped nor moved stalled if the finger pressed with this share of its limit."""
TIP_BACK_FORCE = ToppleConfig().tip_back_force
"""N: the model's mean force over which a push from above is a hard press (``topple.tip_back_force``, 0.7 N since
stop 56; stop 55's hypothesis, reports/tip_back_rule_s55.md, split at 1.4 N, the top quartile of the corpus's), for
``landing_chains``."""


@dataclass
class Course:
    """One play's stroke, step by step (S steps).

    tilt : (S,) float, deg, the angle between the object's up direction and its start's
    slide : (S,) float, m, how far the base has moved on the table, in any horizontal direction: the table point
      under the centre of mass at the start (a push straight down has no direction along it to measure by)
    yaw : (S,) float, deg, the turn about the vertical, read as the heading of the object's x axis seen from
      above (a tilt about a diagonal adds a few degrees; read where the tilt stays small);  pressing : (S,) float, N, the finger's normal
      force on the object (summed over its contact points; 0 when not touching)
    tip_direction : (2,) float, unit, where the up direction leans (world x, y) at ``TIP_TILT``
      (at the largest tilt when it never got there)
    """

    tilt: np.ndarray
    slide: np.ndarray
    yaw: np.ndarray
    pressing: np.ndarray
    tip_direction: np.ndarray


def course(start: np.ndarray, transforms: np.ndarray, pressing: np.ndarray, center_mass: np.ndarray) -> Course:
    """A stroke's ``Course`` from the object's transforms at each step.

    start : (4, 4) float, object -> world before the finger came;  transforms : (S, 4, 4) float, the same
    at each step;  pressing : (S,) float, N;  center_mass : (3,) float, m, object frame
    """
    relative = transforms[:, :3, :3] @ start[:3, :3].T  # (S, 3, 3), the turn since the start
    up = relative[:, :, 2]  # (S, 3), where the start's vertical went
    tilt = np.degrees(np.arccos(np.clip(up[:, 2], -1.0, 1.0)))
    yaw = np.degrees(np.arctan2(relative[:, 1, 0], relative[:, 0, 0]))
    # The base slides where the table point under the centre of mass moves: a tip about a base edge
    # hardly moves it (by d (1 - cos tilt)), where it moves the centre of mass by its height times the tilt.
    base = transform_points(start, center_mass[None])[0] * [1.0, 1.0, 0.0]  # (3,), world
    held = transform_points(np.linalg.inv(start), base[None])[0]  # (3,), the same point, object frame
    slide = np.linalg.norm((transforms[:, :3, :3] @ held + transforms[:, :3, 3] - base)[:, :2], axis=1)
    at = int(np.argmax(tilt >= TIP_TILT)) if (tilt >= TIP_TILT).any() else int(np.argmax(tilt))
    lean = np.array([up[at, 0], up[at, 1], 0.0])
    return Course(tilt, slide, yaw, np.asarray(pressing, dtype=float), unit(lean)[:2])


def course_kind(c: Course, toppled: bool, limit: float) -> str:
    """The play's course, one of ``KINDS``: whether and in which order it tipped and slid.

    toppled : the play left its start pose;  limit : N, the finger's force limit
    """
    touched = c.pressing > 0.0
    if not touched.any():
        return "no contact"
    tips = np.flatnonzero(c.tilt > TILT_ONSET)
    slides = np.flatnonzero(np.abs(c.slide) > SLIDE_ONSET)
    if toppled:
        return "tips first" if len(tips) and (not len(slides) or tips[0] <= slides[0]) else "slides, then tips"
    if c.tilt.max() > TIP_TILT:
        return "tips, falls back"
    if abs(c.slide[-1]) > MOVED_SLIDE or abs(c.yaw[-1]) > MOVED_YAW:
        return "slides or turns, no tip"
    # Neither tipped nor moved: held against the finger's limit, or the finger slid over or off it.
    return "stalls" if np.median(c.pressing[touched]) >= STALL_SHARE * limit else "stays"


def tip_angle(tip_direction: np.ndarray, push: np.ndarray) -> float:
    """deg in (-180, 180]: the tip direction's angle from the push's horizontal direction, seen from above."""
    h = unit(np.array([push[0], push[1], 0.0]))[:2]
    return float(np.degrees(np.arctan2(h[0] * tip_direction[1] - h[1] * tip_direction[0], h @ tip_direction)))


def tip_side(angle: float) -> str:
    """One of ``SIDES``: away within 45 degrees of the push, towards within 45 of its reverse."""
    return "away" if abs(angle) < 45.0 else "towards" if abs(angle) > 135.0 else "sideways"


def lean_in_pose_frame(tip_direction: np.ndarray, transform: np.ndarray, start: np.ndarray) -> np.ndarray:
    """(2,) float, unit: a lean seen in the world, in the pose frame its edges are given in.

    tip_direction : (2,) float, unit, world x, y;  transform : (4, 4) float, object -> pose frame, where the
    object was placed;  start : (4, 4) float, object -> world once it had come to rest.  Settling turns it
    by a fraction of a degree about the vertical; that turn is undone rather than assumed away.
    """
    to_pose = transform[:3, :3] @ start[:3, :3].T
    return unit(to_pose @ np.array([tip_direction[0], tip_direction[1], 0.0]))[:2]


def tipped_edge(pose: StablePose, center_mass: np.ndarray, tip_direction: np.ndarray) -> tuple[int, float]:
    """The base edge whose outward normal is nearest the tip direction, and the angle between them.

    center_mass : (3,) float, m, pose frame;  tip_direction : (2,) float, unit, pose frame
    returns : (edge index, deg)
    """
    from ..model.edges import edge_geometry

    outward = edge_geometry(pose.base_edges, center_mass).outward[:, :2]  # (E, 2)
    outward = outward / np.linalg.norm(outward, axis=1)[:, None]
    angles = np.degrees(np.arccos(np.clip(outward @ tip_direction, -1.0, 1.0)))
    edge = int(np.argmin(angles))
    return edge, float(angles[edge])


def landing_kind(pose: StablePose, edge: int, landed: int) -> str:
    """Where a topple over ``edge`` landed against that edge's chain of poses, one of ``LANDINGS``."""
    if landed == pose.edge_final_pose[edge]:
        return "first pose"
    if landed == pose.edge_momentum_pose[edge]:
        return "rolled on"
    if landed == pose.edge_onward_pose[edge]:
        return "onward"
    return "elsewhere"


def landing_given_topple(row: np.ndarray, pose: int, landed: int) -> float:
    """P(landed | x, u, it left x) of a row: its share of the landed pose over everything but the stay (0 when the
    row never leaves).  row : (P,) float, P(x' | x, u);  pose : x;  landed : a pose of the set"""
    row = np.nan_to_num(np.asarray(row, dtype=float))
    leaving = 1.0 - row[pose]
    return float(row[landed] / leaving) if leaving > 0 else 0.0


def in_chain(pose: StablePose, edge: int, landed: int) -> bool:
    """Whether pose ``landed`` is in the chain of ``edge`` (its first, rolled-on or onward pose); False for edge -1."""
    return edge >= 0 and landing_kind(pose, edge, landed) != "elsewhere"


def line_edge(pose: StablePose, center_mass: np.ndarray, contact: np.ndarray) -> int:
    """The base edge that the ray from the centre of mass's foot through the contact's foot crosses first:
    where a vertical press on the contact would tip the object (``topple.line_edges``, C.22's edge).

    center_mass, contact : (3,) float, m, pose frame;  returns : edge index; -1 when the two feet coincide
    """
    from ..model.edges import edge_geometry
    from ..model.topple import line_edges

    return int(line_edges(np.asarray(contact, dtype=float)[None], edge_geometry(pose.base_edges, center_mass))[0])


def model_edge(obj, pose_set, pose: int, point: np.ndarray, direction: np.ndarray, config: Config, seed: int) -> tuple[int, float]:
    """The base edge the model's trials of one push (pose frame) topple over most often, and their mean force.

    The push alone, evaluated with the dataset's model and noise (``evaluation.evaluate``, the topple stream of
    ``seed``) as its counts (``ToppleConfig.counted``): its own trials' edges and forces, which no smoothing or
    map changes, and which need none of the pose's other candidates; the first of equally frequent edges.
    returns : edge (-1 when no trial topples), N, the mean required force of the trials that topple (NaN when none)"""
    from ..model.evaluation import evaluate

    counts = replace(config, topple=config.topple.counted())
    table = evaluate(obj, pose_set, pose, points=point[None], directions=direction[None], config=counts, seed=seed).table
    outcomes = table.outcomes[0]
    toppled = outcomes[outcomes >= 0]
    return (int(np.bincount(toppled).argmax()) if len(toppled) else -1), float(table.mean_force[0])


def traced_play(body, transform: np.ndarray, point: np.ndarray, direction: np.ndarray, config: Config, noise):
    """``pushsim.play_push`` with every step of the stroke traced: (the played push, its ``Course``).

    point, direction : object frame, as ``play_push`` takes them
    """
    from .pushsim import _observe, play_push

    transforms, pressing = [], []

    def observe(pb, client, pushed, force):
        transforms.append(_observe(pb, client, pushed, body))
        pressing.append(force)  # the player's own per-step sum, not asked of Bullet again

    played = play_push(body, transform, point, direction, config, noise, observe=observe)
    return played, course(played.start_transform, np.array(transforms), np.array(pressing), body.center_mass)


@dataclass
class Play:
    """One traced play and what the rows say of its push.

    pose, action : the start and the push;  landed : the pose it came to rest in (-1: outside the pose
    set; ``pose`` where it stayed)
    edge : for a topple, the base edge it tipped over (``tipped_edge``), else -1;  model_edge : the edge the
      model's trials of the push topple over most often (``model_edge``; -1: none topples);  line_edge : the
      edge the line from the centre of mass's foot through the contact's crosses (``line_edge``)
    tip_angle : for a topple, deg in [0, 180], the lean's angle from the push's horizontal direction, else None
    slide : m, the most the base slid during the stroke;  model_force : N, the mean force of the model's trials
      that topple (``model_edge``; NaN when none does)
    in_model_chain, in_line_chain : for a topple, whether it landed in a pose of the chain (``landing_kind``
      other than elsewhere) of ``model_edge`` and of ``line_edge``; False otherwise"""

    object_id: str
    direction: str
    predicted: float
    toppled: bool
    kind: str
    side: str | None
    landing: str | None
    value_expected: float | None
    value_landed: float | None
    landing_probability: float | None
    pose: int
    action: int
    landed: int
    edge: int
    model_edge: int
    line_edge: int
    tip_angle: float | None
    slide: float
    model_force: float
    in_model_chain: bool
    in_line_chain: bool


def chosen_pushes(plans: dict[str, ObjectPlan], policy: str, per_class: int, seed: int) -> list[tuple[str, int, int]]:
    """(object, pose, action): for each direction class, one start of each of up to ``per_class``
    objects where ``policy`` pushes that way, drawn with ``seed``."""
    rng = np.random.default_rng(seed)
    chosen = []
    for k in range(len(CLASSES)):
        starts = {}
        for object_id in sorted(plans):
            plan = plans[object_id]
            mine = [(pose, int(action)) for pose, action in enumerate(plan.actions[policy]) if action != NO_OP
                    and direction_class(np.array([plan.pushes[(pose, int(action))][1][2]]))[0] == k]
            if mine:
                starts[object_id] = mine[rng.integers(len(mine))]
        objects = sorted(starts)
        for i in np.sort(rng.permutation(len(objects))[:per_class]):
            chosen.append((objects[i], *starts[objects[i]]))
    return chosen


def play_object(plan: ObjectPlan, starts: list[tuple[int, int]], rows: list[np.ndarray], config: Config, world: Config,
                repeats: int, seed: int) -> list[Play] | str:
    """Each start's push played ``repeats`` times, traced (runs in a worker); or a one-line reason the
    object cannot be played (its mesh does not load, or its stable poses are not the dataset's).

    rows : per pose (A_x, P) float, the rows' P(x' | x, u)
    """
    from ..model.poses import settle
    from .pushsim import body_model, draw_noise

    loaded = load_planned(plan, config)
    if isinstance(loaded, str):
        return loaded
    obj, pose_set = loaded
    body = body_model(obj)
    values = np.append(plan.v_s, 0.0)  # the last entry: outside the pose set
    plays = []
    for pose, action in starts:
        point, direction, predicted = plan.pushes[(pose, action)]
        transform = plan.transforms[pose]
        to_object = np.linalg.inv(transform)
        row = rows[pose][action]  # (P,)
        topple = 1.0 - row[pose]
        others = np.delete(np.arange(len(row)), pose)
        expected = float(row[others] @ plan.v_s[others] / topple) if topple > 0 else None
        name = CLASSES[direction_class(np.array([direction[2]]))[0]]
        center_mass = transform_points(transform, obj.center_mass[None])[0]  # (3,), pose frame
        modelled, force = model_edge(obj, pose_set, pose, point, direction, config, seed)
        crossed = line_edge(pose_set.poses[pose], center_mass, point)
        rng = stream(seed, f"{plan.spec.object_id}/course/{pose}/{action}", pose, PURPOSE)
        for _ in range(repeats):
            played, c = traced_play(body, transform, to_object[:3, :3] @ point + to_object[:3, 3], to_object[:3, :3] @ direction,
                                    config, draw_noise(world, rng, noise=True))
            landed = settle(pose_set, obj, played.final_transform[:3, :3])
            toppled = landed != pose
            side = landing = probability = landed_value = angle = None
            edge = -1
            if toppled:
                angle = tip_angle(c.tip_direction, played.direction)
                side = tip_side(angle)
                lean = lean_in_pose_frame(c.tip_direction, transform, played.start_transform)
                edge, _ = tipped_edge(pose_set.poses[pose], center_mass, lean)
                landing = landing_kind(pose_set.poses[pose], edge, landed)
                landed_value = float(values[landed])
                probability = landing_given_topple(row, pose, landed) if landed >= 0 else 0.0
            plays.append(Play(plan.spec.object_id, name, float(predicted), bool(toppled),
                              course_kind(c, toppled, config.topple.max_finger_force), side, landing,
                              expected if toppled else None, landed_value, probability, pose, action, int(landed),
                              int(edge), modelled, crossed, None if angle is None else abs(angle), float(c.slide.max()), force,
                              bool(toppled) and in_chain(pose_set.poses[pose], modelled, landed),
                              bool(toppled) and in_chain(pose_set.poses[pose], crossed, landed)))
    return plays


def _play_named(object_id: str, *arguments) -> tuple[str, list[Play] | str]:
    """``play_object``'s result with the object it is for (``map_unordered`` hands results back as they finish)."""
    return object_id, play_object(*arguments)


def summary(plays: list[Play]) -> dict:
    """By direction class: calibration, the courses' shares, and for the topples their sides, landings and values."""

    def described(values, groups):
        return clustered_entry(values, groups, "plays")

    def shares(labels, names):
        labels = list(labels)
        return {name: labels.count(name) / len(labels) for name in names} if labels else {}

    result = {}
    for name in CLASSES:
        mine = [p for p in plays if p.direction == name]
        if not mine:
            continue
        objects = [p.object_id for p in mine]
        # A start that falls with no finger on it is a marginal pose, not the push's doing: its lean and landing
        # say nothing of how pushes topple, so only the pushed topples are described below.
        topples = [p for p in mine if p.toppled and p.kind != "no contact"]
        entry = {
            "plays": len(mine), "objects": len(set(objects)),
            "predicted": described([p.predicted for p in mine], objects),
            "toppled": described([p.toppled for p in mine], objects),
            "toppled_minus_predicted": described([p.toppled - p.predicted for p in mine], objects),
            "courses": shares((p.kind for p in mine), KINDS),
            "topples": len(topples),
            "untouched_topples": sum(p.toppled and p.kind == "no contact" for p in mine),
        }
        if topples:
            valued = [p for p in topples if p.value_expected is not None]
            landed = [p for p in topples if p.landed >= 0]  # into the pose set: on some chain or elsewhere
            of = [p.object_id for p in valued]
            entry.update({
                "sides": shares((p.side for p in topples), SIDES),
                "landings": shares((p.landing for p in topples), LANDINGS),
                "landing_probability": described([p.landing_probability for p in topples], [p.object_id for p in topples]),
                "value_expected": described([p.value_expected for p in valued], of) if valued else None,
                "value_landed": described([p.value_landed for p in valued], of) if valued else None,
                "value_landed_minus_expected": described([p.value_landed - p.value_expected for p in valued], of) if valued else None,
                "edge_named": edge_named(topples),
                "edge_named_tipped_back": edge_named([p for p in topples if p.tip_angle is not None and p.tip_angle > 90.0]),
                "landing_chains": {"hard": landing_chains([p for p in landed if p.model_force > TIP_BACK_FORCE]),
                                   "light": landing_chains([p for p in landed if not p.model_force > TIP_BACK_FORCE])},
            })
        result[name] = entry
    return result


def edge_named(topples: list[Play]) -> dict | None:
    """How often the model's most frequent edge, and the centre-of-mass-to-contact line's, is the edge the topples
    tipped over (``_model_against_line``)."""
    return _model_against_line(topples, lambda p: p.edge == p.model_edge, lambda p: p.edge == p.line_edge)


def landing_chains(topples: list[Play]) -> dict | None:
    """How often topples landed in the chain of the model's most frequent edge and of the line's edge
    (``_model_against_line``).  ``summary`` splits them at ``TIP_BACK_FORCE``: "hard" over it, "light" at or
    under it or where the model's trials never topple (NaN)."""
    return _model_against_line(topples, lambda p: p.in_model_chain, lambda p: p.in_line_chain)


def _model_against_line(topples: list[Play], model, line) -> dict | None:
    """The share of ``topples`` for which ``model(play)`` and ``line(play)`` hold, and the difference, clustered by
    object; None for no topples."""
    if not topples:
        return None
    objects = [p.object_id for p in topples]
    by_model = np.array([model(p) for p in topples], dtype=float)
    by_line = np.array([line(p) for p in topples], dtype=float)
    return {"model": clustered_entry(by_model, objects, "topples"), "line": clustered_entry(by_line, objects, "topples"),
            "line_minus_model": clustered_entry(by_line - by_model, objects, "topples")}


def study(root: str | Path, policy: str = "value_iteration", per_class: int = 70, repeats: int = 5, seed: int = 53,
          world: Config | None = None, workers: int | None = 1, keep_plays: bool = False) -> dict:
    """The chosen pushes of ``policy`` on the dataset at ``root``, traced in physics (``summary``); with
    ``keep_plays`` every play too, under ``"plays"`` (``Play`` fields, in the draw's order)."""
    from schema.reader import Dataset, DatasetUnreadable

    from ..build.fanout import map_unordered
    from .landing_trust import pose_columns

    if policy not in POLICIES:
        raise ExperimentError(f"unknown policy {policy!r}; one of {', '.join(POLICIES)}")
    try:
        dataset = Dataset.open(root)
        n_actions = {object_id: c["n_actions"].tolist() for object_id, c in pose_columns(dataset, ["n_actions"]).items()}
    except DatasetUnreadable as err:
        raise ExperimentError(str(err)) from None
    config = dataset_config(dataset)
    world = world_config("thesis") if world is None else world
    plans = object_plans(dataset, sorted(n_actions))
    chosen = chosen_pushes(plans, policy, per_class, seed)
    by_object: dict[str, list[tuple[int, int]]] = {}
    for object_id, pose, action in chosen:
        by_object.setdefault(object_id, []).append((pose, action))
    tasks = [(object_id, plans[object_id], starts, next_pose_rows(dataset, object_id, n_actions[object_id]), config, world, repeats, seed)
             for object_id, starts in by_object.items()]
    found = dict(map_unordered(_play_named, tasks, workers, description="objects"))
    played = {object_id: found[object_id] for object_id in by_object}  # in the draw's order, whatever order they finished in
    failed = {object_id: found for object_id, found in played.items() if isinstance(found, str)}
    plays = [p for found in played.values() if not isinstance(found, str) for p in found]
    result = {"dataset": str(root), "policy": policy, "per_class": per_class, "repeats": repeats, "seed": seed,
              "pushes": len(chosen), "failed_objects": failed, "by_direction": summary(plays)}
    if keep_plays:
        result["plays"] = [vars(p) for p in plays]
    return result


def _se(entry: dict) -> str:
    return "" if entry["se"] is None else f" +/- {entry['se']:.3f}"


def text(result: dict) -> str:
    lines = [f"{result['policy']}'s pushes on {result['dataset']}, {result['pushes']} pushes x {result['repeats']} plays (seed {result['seed']}):"]
    lines += [f"  not played: {reason}" for reason in result["failed_objects"].values()]
    for name, e in result["by_direction"].items():
        lines.append(f"from {'the ' if name == 'side' else ''}{name}: {e['plays']} plays on {e['objects']} objects; predicted "
                     f"{e['predicted']['mean']:.3f}, toppled {e['toppled']['mean']:.3f}{_se(e['toppled'])} (difference "
                     f"{e['toppled_minus_predicted']['mean']:+.3f}{_se(e['toppled_minus_predicted'])})")
        lines.append("  courses: " + ", ".join(f"{k} {v:.2f}" for k, v in e["courses"].items()))
        if e["topples"]:
            untouched = f" (and {e['untouched_topples']} with no finger on it)" if e["untouched_topples"] else ""
            lines.append(f"  {e['topples']} pushed topples{untouched}; sides: " + ", ".join(f"{k} {v:.2f}" for k, v in e["sides"].items()))
            lines.append("  landings against the tipped edge's poses: " + ", ".join(f"{k} {v:.2f}" for k, v in e["landings"].items()))
            lines.append(f"  the rows' probability of the landing pose {e['landing_probability']['mean']:.3f}")
            for label, key in (("", "edge_named"), (" (tipped back, over 90 degrees from the push)", "edge_named_tipped_back")):
                named = e.get(key)
                if named:
                    lines.append(f"  the edge it tipped over{label}, {named['model']['topples']} topples: the model's most frequent "
                                 f"{named['model']['mean']:.2f}, the centre of mass to contact line's {named['line']['mean']:.2f} "
                                 f"(difference {named['line_minus_model']['mean']:+.2f}{_se(named['line_minus_model'])})")
            for band, chains in (e.get("landing_chains") or {}).items():
                if chains:
                    lines.append(f"  landed in the chain of the model's edge / the line's, {band} pushes (mean force "
                                 f"{'over' if band == 'hard' else 'at most'} {TIP_BACK_FORCE} N), {chains['model']['topples']} "
                                 f"topples: {chains['model']['mean']:.2f} / {chains['line']['mean']:.2f} (difference "
                                 f"{chains['line_minus_model']['mean']:+.2f}{_se(chains['line_minus_model'])})")
            if e["value_expected"]:
                lines.append(f"  V_s of a topple: expected {e['value_expected']['mean']:.3f}, landed {e['value_landed']['mean']:.3f}"
                             f" (difference {e['value_landed_minus_expected']['mean']:+.3f}{_se(e['value_landed_minus_expected'])})")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from ..cli import positive_int, print_and_record, refused_outputs

    parser = argparse.ArgumentParser(prog="python -m pipeline.studies.push_course", description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path, help="a dataset directory (toppledb dataset)")
    parser.add_argument("--policy", default="value_iteration", choices=POLICIES, help="whose chosen pushes to play")
    parser.add_argument("--per-class", type=positive_int, default=70, help="objects per push direction")
    parser.add_argument("--repeats", type=positive_int, default=5, help="plays of each push")
    parser.add_argument("--seed", type=int, default=53, help="draws the starts and the plays' noise")
    parser.add_argument("--workers", type=positive_int, default=1)
    parser.add_argument("--world", default="thesis", help="the simulated world's noise: a preset or a TOML file")
    parser.add_argument("--json", type=Path, help="write the result here")
    parser.add_argument("--plays", type=Path, metavar="FILE.jsonl",
                        help="write every play here, a JSON line each (what python -m pipeline.studies.landing_direction reads)")
    args = parser.parse_args(argv)
    if refused_outputs(args.json, args.plays):
        return 2
    try:
        result = study(args.dataset, args.policy, args.per_class, args.repeats, args.seed, world_config(args.world), args.workers,
                       keep_plays=args.plays is not None)
    except ExperimentError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    plays = result.pop("plays", None)
    if print_and_record(text(result), result, args.json):
        return 2
    if plays is not None:
        write_text_atomic(args.plays, "".join(json.dumps(p) + "\n" for p in plays))
    return 0


if __name__ == "__main__":
    from pipeline.cli import run_command

    sys.exit(run_command(main))
