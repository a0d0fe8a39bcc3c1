"""Every parameter of toppledb in one typed, documented place.

Defaults are the thesis's values (Correa 2019, chapter 4) or, where it is silent,
the project's own choices; ``docs/MODEL.md`` section 13 gives each one's source.  A ``Config`` is overridable from a TOML file
(``Config.from_toml``) and from dotted ``section.field=value`` strings
(``Config.with_overrides``, what the CLI uses), and is written whole into every
dataset manifest (``Config.to_dict``).

All quantities are SI: metres, kilograms, newtons, radians.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields, is_dataclass
from pathlib import Path
from typing import Any

import numpy as np

from . import fitted_map
from .feature_map import SIDE_BAND, SIDE_Z, check_down_weights, check_side_band, check_side_weights, check_weights
from .recalibration import check_knots

PRESETS = Path(__file__).with_name("presets")
"""Named parameter sets shipped with the package (``--config thesis``)."""

@dataclass(frozen=True)
class Range:
    """The values a numeric parameter accepts: ``lo``/``hi`` bounds (None: unbounded),
    inclusive unless ``lo_open``/``hi_open``.  Kept on the field as ``metadata["range"]``
    (``bounded``), checked wherever a config is read (TOML, ``--set``, flags)."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False

    def contains(self, value: float) -> bool:
        if not math.isfinite(value):
            return False
        if self.lo is not None and (value <= self.lo if self.lo_open else value < self.lo):
            return False
        return self.hi is None or (value < self.hi if self.hi_open else value <= self.hi)

    def text(self) -> str:
        """``> 0``, ``>= 1``, ``in [0, 1)``."""
        def number(x: float) -> str:
            return f"{x:.6g}"

        if self.hi is None:
            return f"{'>' if self.lo_open else '>='} {number(self.lo)}" if self.lo is not None else "finite"
        if self.lo is None:
            return f"{'<' if self.hi_open else '<='} {number(self.hi)}"
        return f"in {'(' if self.lo_open else '['}{number(self.lo)}, {number(self.hi)}{')' if self.hi_open else ']'}"


POSITIVE = Range(0.0, None, lo_open=True)
NON_NEGATIVE = Range(0.0, None)
AT_LEAST_ONE = Range(1, None)
FRACTION = Range(0.0, 1.0)
RIGHT_ANGLE = Range(0.0, math.pi / 2)
"""rad, an angle between 0 and 90 degrees."""


def bounded(default: Any, accepted: Range) -> Any:
    """A dataclass field with its accepted range as metadata."""
    return field(default=default, metadata={"range": accepted})


def field_range(cls: type, name: str) -> Range | None:
    """The accepted range of ``cls.name``, None when it has none (strings, booleans)."""
    return next((f.metadata.get("range") for f in fields(cls) if f.name == name), None)


MAP_FIELDS = ("recalibration_x", "recalibration_y", "feature_map", "down_map", "side_map")
"""The ``topple`` fields that hold a map of P(topple) (MODEL.md C.7, C.13, C.15, C.16); all empty: no map."""
NO_MAP = {**{name: () for name in MAP_FIELDS}, "boosted_map": ""}
"""``topple`` values of a model with no map (the boosted map of C.19 too): what a file writes to clear the default's."""

THESIS_VARIANTS = ("baseline", "rotations", "robustness", "robust")
"""Model variants of thesis table 4.1: (predicts planar rotations, robust estimates)."""

VARIANTS = THESIS_VARIANTS + ("corrected",)
"""Every selectable variant: the thesis's four, and ``corrected`` (the robust model with the
corrections of docs/MODEL.md "Corrections beyond the thesis" named in ``topple.corrections``)."""

CORRECTIONS = ("finger_friction", "force_limit", "stability_margin", "rolling", "momentum", "edge_spin", "stroke", "stuck_finger",
               "tip_path", "tip_back", "carried_finger")
"""Corrections the ``corrected`` variant can apply (docs/MODEL.md, "Corrections beyond the thesis"):
``finger_friction``: the finger's force follows Coulomb sliding at the contact while the object
tips (friction in the moment balance, pushes from above, faces the finger wedges under);
``force_limit``: a push that needs more than ``max_finger_force`` does not topple;
``stability_margin``: a pose whose centre of mass is within ``min_stability_margin`` of a
base edge falls over that edge whatever the push;
``rolling``: a blocked topple rolls on while the finger pushes;
``momentum``: the energy of a topple's fall may roll the object on past the pose it lands in;
``edge_spin``: a push's moment about the vertical turns the object without stopping the topple;
``stroke``: a topple needs the finger to reach its apex within ``stroke`` of the contact;
``stuck_finger``: a push down onto a part that overhangs a base edge tips the object over it
when nothing else does and the push can drag the base (the finger sticks, the base slides);
``tip_path``: ``finger_friction``'s balance must hold on the way to the apex too, at
``tip_path_points`` angles between, not only at the start (it needs ``finger_friction``);
``tip_back``: a push from above (u_z < ``FROM_ABOVE_U_Z``) that topples with a force over ``tip_back_force``,
by the least force or by ``stuck_finger``, presses the overhang down and tips the object back over the
edge the line from the centre of mass's foot through the contact crosses (docs/MODEL.md C.22; in the
default since stop 56);
``carried_finger``: where C.2 (after ``stroke`` and ``tip_path``) tips no push from above (u_z < ``FROM_ABOVE_U_Z``,
the trial's noisy push), a tip whose face
would slide at most ``carried_slide`` along the fingertip before the apex carries the finger with it instead:
it presses along the face's normal, without friction (it needs ``finger_friction``; docs/MODEL.md C.23,
opt-in since stop 60)."""
FROM_ABOVE_U_Z = -0.3
"""A push is from above when its direction's vertical component (pose frame) is below this: the split of
``candidate_choice`` and the validation report, the pushes ``tip_back`` looks at and LD's first class
(``landing_direction``)."""


MESH_SUFFIXES = (".obj", ".stl", ".ply")
"""The mesh formats ``mesh.load_mesh`` reads, and so the files a directory corpus picks up
(``pipeline.build.corpus``); here, not in ``mesh``, so the corpus reads it without importing trimesh."""


@dataclass(frozen=True)
class MeshConfig:
    """Loading and validation of corpus meshes."""

    default_mass: float = bounded(0.25, POSITIVE)
    """kg, used when the corpus gives no mass."""
    min_extent: float = bounded(0.01, POSITIVE)
    """m; an object whose largest bounding-box side is smaller is rejected as too small."""
    max_extent: float = bounded(0.5, POSITIVE)
    """m; an object whose largest bounding-box side is larger is rejected as too large for a tabletop."""
    fill_holes: bool = True
    """Let trimesh fill small holes before the watertightness check."""


@dataclass(frozen=True)
class PoseConfig:
    """Stable poses and their identity."""

    min_probability: float = bounded(0.01, Range(0.0, 1.0, hi_open=True))
    """Stable poses dropped with lower probability are left out unless a topple reaches them."""
    same_pose_angle: float = bounded(math.radians(10.0), Range(0.0, math.pi, lo_open=True))
    """rad; two orientations are the same stable pose when their down vectors differ by at most this."""
    base_tolerance: float = bounded(1e-3, POSITIVE)
    """m; hull vertices this close to the table form the base (docs/MODEL.md 5)."""
    merge_symmetric: bool = True
    """Merge stable poses that are one resting pose turned about the vertical (a cylinder, a
    can, a prism: docs/MODEL.md "Symmetric objects"); the thesis did not (presets/thesis.toml)."""


@dataclass(frozen=True)
class ContactConfig:
    """Candidate pushes (thesis 4.4.1) and the finger that executes them."""

    n_contacts: int = bounded(1000, Range(1, 100_000))
    """Candidate contact points per pose, exactly this many, spread evenly over the surface; at
    most 100 times the thesis's 1,000 (each is evaluated in every pose, so 10^10 would only fail
    every object for want of memory, far into the run)."""
    oversample: int = bounded(10, AT_LEAST_ONE)
    """Uniform surface samples per candidate from which the even subset is chosen."""
    min_height_fraction: float = bounded(0.15, FRACTION)
    """Contacts lower than this fraction of the object's height in the pose are ``too_low``."""
    max_up_angle: float = bounded(math.radians(60.0), RIGHT_ANGLE)
    """rad; a push pointing up more than this above horizontal is ``pushes_up``."""
    finger_radius: float = bounded(0.004, POSITIVE)
    """m, radius of the finger capsule."""
    finger_length: float = bounded(0.06, POSITIVE)
    """m, length of the finger capsule."""
    approach_offset: float = bounded(0.015, NON_NEGATIVE)
    """m; the finger starts this far outside the contact along the normal."""
    push_depth: float = bounded(0.04, NON_NEGATIVE)
    """m; the executed motion ends this far inside the contact (p - push_depth n)."""
    max_height_normal_angle: float = bounded(math.radians(15.0), RIGHT_ANGLE)
    """rad; Max-Height baseline pushes the highest point whose normal is this close to horizontal."""


@dataclass(frozen=True)
class ToppleConfig:
    """The quasi-static toppling model (thesis 4.2) and its Monte Carlo noise (4.2.5).

    Standard deviations, as in the authors' released code.
    """

    variant: str = "corrected"
    """One of ``baseline``, ``rotations``, ``robustness``, ``robust`` (thesis table 4.1), or
    ``corrected`` (docs/MODEL.md "Corrections beyond the thesis"), the default: chosen over
    ``robust`` by cross-validation on the corpus push log and confirmed on objects outside the
    corpus (docs/VALIDATION.md).  ``--config thesis`` restores the thesis's model exactly."""
    n_trials: int = bounded(100, AT_LEAST_ONE)
    """Noisy trials per action for the robust variants; noise-free variants use one."""
    gravity: float = bounded(9.81, POSITIVE)
    """m/s^2."""
    # The noise below, and finger_friction_scale, are calibrated (reports/calibrated_corrected.toml:
    # 6-fold cross-validation grouped by object on the corpus push log, 101 settings per fold);
    # the thesis's values (4.2.5) are in presets/thesis.toml and given after each field.
    mu_table_mean: float = bounded(0.382, NON_NEGATIVE)
    """Mean table friction coefficient (thesis 0.43)."""
    mu_table_std: float = bounded(0.196, NON_NEGATIVE)
    """(thesis 0.1)"""
    mu_finger_mean: float = bounded(0.300, NON_NEGATIVE)
    """Mean finger friction coefficient (thesis 0.98)."""
    mu_finger_std: float = bounded(0.464, NON_NEGATIVE)
    """(thesis 0.2)"""
    contact_std: float = bounded(2.66e-3, NON_NEGATIVE)
    """m, isotropic standard deviation of the contact position (thesis 5.05e-4)."""
    direction_std: float = bounded(0.0405, NON_NEGATIVE)
    """Isotropic standard deviation added to the unit push direction before renormalising (thesis 0.055)."""
    rotation_std: float = bounded(0.280, NON_NEGATIVE)
    """rad, standard deviation of the object rotation about a uniformly random axis (thesis 0.22)."""
    ray_offset: float = bounded(0.015, POSITIVE)
    """m; the finger ray that re-finds a noisy contact starts this far outside it."""
    chunk_actions: int = bounded(256, AT_LEAST_ONE)
    """Actions evaluated per vectorised block; bounds peak memory, not results."""
    corrections: str = "finger_friction,force_limit,momentum,stuck_finger,tip_path,tip_back"
    """Comma-separated corrections the ``corrected`` variant applies (``CORRECTIONS``), or
    ``all`` or ``none``; the thesis's variants apply none, whatever this says.  The default
    leaves out ``stability_margin``, which physics does not support as a rule (docs/MODEL.md C.3),
    ``rolling``, which did not help (C.6), ``edge_spin``, which makes the pushes the
    policies choose overconfident in physics (C.9), and ``stroke`` (C.10).  ``stuck_finger``
    (C.11) joined it with the recalibration map refitted on it (candidate S, docs/VALIDATION.md),
    and ``tip_path`` (C.14) the same way (candidate T)."""
    finger_friction_scale: float = bounded(1.0, FRACTION)
    """Share of the finger's Coulomb friction that resists tipping (``finger_friction``
    correction): 1 is Coulomb's law, which the standing box in pybullet follows, and what the
    calibration on the corpus push log chose (docs/MODEL.md C.2)."""
    min_stability_margin: float = bounded(1e-3, NON_NEGATIVE)
    """m; a pose whose centre of mass projects closer than this to a base edge is marginal
    (``stability_margin`` correction): it falls over that edge with or without a push.  1 mm
    is ``poses.base_tolerance``, the height below which a hull vertex counts as touching."""
    max_finger_force: float = bounded(20.0, POSITIVE)
    """N, the largest finger force (magnitude) of a push (``force_limit`` correction): about
    the sustained Cartesian force of a light collaborative arm's fingertip, 8 times a 0.25 kg
    object's weight; docs/MODEL.md "Corrections beyond the thesis" gives the reasoning."""
    stroke: float = bounded(0.04, POSITIVE)
    """m, how far past the contact the finger travels (``stroke`` correction, docs/MODEL.md
    C.10): the executed push's ``contacts.push_depth``, which it must equal (``Config`` checks;
    setting the push depth alone sets it too)."""
    stuck_finger_share: float = bounded(0.5, FRACTION)
    """Share of the trials ``stuck_finger`` qualifies that topple (a uniform draw per trial,
    made after every other draw, decides).  0.5: on the corpus log, pushes that qualify
    noise-free topple 0.43-0.53 of the time; 1, the rule taken at its word, scores the same
    there but makes the pushes the policies choose overconfident (docs/MODEL.md C.11)."""
    tip_back_force: float = bounded(0.7, NON_NEGATIVE)
    """N; a push from above that topples with a force over this tips the object back (``tip_back``,
    docs/MODEL.md C.22): of 0.7, 1.4 and 2.8 N, the one whose rows scored the corpus's traced plays from
    above best (stop 56; 1.4 N, the top quartile of value iteration's pushes from above, was stop 55's)."""
    carried_slide: float = bounded(0.016, NON_NEGATIVE)
    """m; a tip whose face would slide at most this far along the fingertip on the way to the apex carries
    the finger with it (``carried_finger``, docs/MODEL.md C.23): the 16 mm the push player's finger was
    carried sideways with a rod's face while the rod rolled, traced at stop 59 (docs/VALIDATION.md)."""
    tip_path_points: int = bounded(2, AT_LEAST_ONE)
    """How many angles between the start and the apex ``tip_path`` checks the balance at:
    k / (n + 1) of the apex angle for k = 1..n (docs/MODEL.md C.14)."""
    smoothing_radius: float = bounded(0.01, NON_NEGATIVE)
    """m; when positive, each candidate push's next-pose row is replaced by the mean row of the
    pose's candidates around it: contacts within this distance, directions within
    ``smoothing_angle``, itself included (docs/MODEL.md C.12).  It is applied before any
    recalibration, so a map is fitted on the smoothed P(topple).  0 leaves the rows as counted.
    10 mm had the lowest Brier score of seven neighbourhoods on the corpus's drawn pushes, and
    the pushes value iteration chooses from it topple as often as predicted (C.12).  Only the
    ``corrected`` variant smooths (the thesis's variants never do)."""
    smoothing_angle: float = bounded(0.35, POSITIVE)
    """rad, largest angle between the push directions of two neighbours (``smoothing_radius``)."""
    recalibration_x: tuple[float, ...] = bounded(fitted_map.RECALIBRATION_X, FRACTION)
    """Knots x_k of the monotone map g of P(topple) (docs/MODEL.md C.7), strictly increasing in
    [0, 1]; empty is the identity.  The default (``pipeline.model.fitted_map``) is the centred
    isotonic map fitted on the corpus's drawn pushes (data/logs/corpus_all) under the default
    model, adopted by rules written down before it was played (docs/VALIDATION.md, candidates C
    and S); it belongs to the default's corrections and noise, and another model needs its own.
    Only the ``corrected`` variant applies it (the thesis's variants never do).  A list in
    TOML (``[]`` for the identity), comma-separated with ``--set``."""
    recalibration_y: tuple[float, ...] = bounded(fitted_map.RECALIBRATION_Y, FRACTION)
    """Knots g(x_k), non-decreasing in [0, 1], as many as ``recalibration_x``."""
    feature_map: tuple[float, ...] = bounded((), Range())
    """Weights w of the feature map of P(topple) (docs/MODEL.md C.13), one per feature (bias,
    logit_p, logit_neighbourhood, log_force_ratio, no_own_topple, direction_z), or empty (the
    default): no map.  Fitted by ``toppledb recalibrate --features`` on observed pushes; applied
    after the smoothing (C.12), to candidates and probes alike.  Not together with
    ``recalibration_x``/``_y`` (two maps of one probability): a file that sets it sets those to ``[]``.
    Only the ``corrected`` variant applies it."""
    down_map: tuple[float, ...] = bounded(fitted_map.DOWN_MAP, Range())
    """Weights of the map of P(topple) for pushes that press down (docs/MODEL.md C.15), one per
    feature (bias, logit_p, direction_z, overhang, height, normal_z, stability, offset), or empty
    (no map).  The default's weights are fitted by ``toppledb recalibrate --down`` on the drawn
    pushes of two logs of every corpus object (data/logs/corpus_all and corpus_s1; only the
    weights are taken, ``fitted_map.DOWN_MAP``).  It replaces the recalibration map (C.7) for the pushes with
    u_z below ``down_map_z``, read from their unmapped P; the rest keep C.7's.  Only the
    ``corrected`` variant applies it."""
    down_map_z: float = bounded(-0.3, Range(-1.0, 1.0))
    """Pushes whose direction's z (pose frame) is below this are mapped by ``down_map``: the
    default was ``mdp.min_direction_z``'s until stop 44, so no push the policies chose was mapped;
    since stop 45 value iteration chooses among them by its neighbourhood over the boosted map
    (``Config``'s check, docs/MODEL.md C.15)."""
    side_map: tuple[float, ...] = bounded(fitted_map.SIDE_MAP, Range())
    """Weights of the map of P(topple) for pushes from the side (docs/MODEL.md C.16), one per
    feature (bias, logit_p, log_force_ratio: the noise-free force the push needs over the
    object's weight), or empty (no map).  Applied after the other maps (C.7, C.13, C.15) to the
    pushes with -0.3 <= u_z < 0.3 whose P is strictly inside ``side_map_band`` (``feature_map.side_rows``);
    not with a down map whose cut ``down_map_z`` is above -0.3, which would map some of the same pushes.  The default is
    fitted by ``toppledb recalibrate --side`` on the corpus's drawn pushes (data/logs/corpus).
    Only the ``corrected`` variant applies it."""
    side_map_band: tuple[float, ...] = bounded(SIDE_BAND, FRACTION)
    """(lo, hi): the side map takes the pushes with lo < P < hi (and P > 0), P after the other
    maps; it is part of the fit (``recalibrate --side`` fits on the pushes inside it and writes
    it beside the weights).  The default keeps to the pushes the model is unsure of."""

    boosted_map: str = "boosted_map_s41"
    """A gradient-boosted map of P(topple) applied after every other map (docs/MODEL.md C.19,
    ``pipeline.model.boosted_map``): the name of a packaged map (``presets/<name>.json``; the
    default, ``boosted_map_s41``, was fitted on the corpus's drawn pushes under this model without
    it and adopted at stop 42 by the rules of reports/boosted_map_rule*_s41.md) or a path to a
    ``.json`` one; empty: none.  Only the ``corrected`` variant applies it."""

    landing_spread: float = bounded(0.0, FRACTION)
    """Share eps of every toppling push's landing moved to the start pose's most probable other
    stable poses (docs/MODEL.md C.17, ``pipeline.model.landing_spread``): the model's landing is
    sharp, and physics lands elsewhere a fifth of the time.  P(topple) is unchanged.  0: the
    landing as the maps leave it.  Only the ``corrected`` variant applies it."""
    landing_spread_poses: int = bounded(3, AT_LEAST_ONE)
    """k, how many of the start pose's other stable poses, the most probable when dropped,
    share the spread landing (``landing_spread``), in proportion to their drop probability."""
    landing_onward: float = bounded(0.4, FRACTION)
    """Share alpha of a topple's landing carried on one fall further when the momentum chain
    (C.8) ends in a marginal pose, one of drop probability at most ``landing_onward_below``
    (docs/MODEL.md C.18): in physics such landings often roll on.  P(topple) is unchanged.  0:
    the landing as C.8 leaves it.  It carries on C.8's landings: only the ``corrected`` variant
    with the ``momentum`` correction applies it.  The value is fitted by object-grouped
    cross-validation of the Brier score on the corpus's drawn pushes (data/logs/corpus_all and
    corpus_s1); on since stop 35."""
    landing_onward_below: float = bounded(0.1, FRACTION)
    """tau: a landing pose whose drop probability is at most this is marginal for
    ``landing_onward``."""

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; choose one of {', '.join(VARIANTS)}")
        if self.n_trials < 1:
            raise ValueError("n_trials must be at least 1")
        self.applied_corrections  # noqa: B018, validates ``corrections``
        check_knots(self.recalibration_x, self.recalibration_y)
        check_weights(self.feature_map)
        check_down_weights(self.down_map)
        check_side_weights(self.side_map)
        check_side_band(self.side_map_band)
        if self.applied_down_map and self.applied_side_map and self.down_map_z > -SIDE_Z:
            # Each map belongs to the pushes it was fitted on (MODEL.md C.15, C.16): none is both.
            raise ValueError(f"topple.down_map_z ({self.down_map_z:g}) is above -{SIDE_Z:g}: the down map and the side map "
                             "would both map the pushes between; lower topple.down_map_z or set no side map "
                             "(topple.side_map = [], --set topple.side_map=)")
        if self.feature_map and self.recalibration_x:
            raise ValueError("topple.feature_map and topple.recalibration_x/_y are two maps of one P(topple); set one "
                             "(the defaults carry a recalibration map: with a feature map set recalibration_x = [] and "
                             "recalibration_y = [], or --set topple.recalibration_x= --set topple.recalibration_y=)")

    @property
    def predicts_rotations(self) -> bool:
        return self.variant in ("rotations", "robust", "corrected")

    @property
    def robust(self) -> bool:
        return self.variant in ("robustness", "robust", "corrected")

    @property
    def applied_corrections(self) -> frozenset[str]:
        """The corrections this configuration applies: none for the thesis's variants."""
        names = {c.strip() for c in self.corrections.split(",") if c.strip()}
        if names == {"all"}:
            names = set(CORRECTIONS)
        elif names == {"none"}:
            names = set()
        unknown = names - set(CORRECTIONS)
        if unknown:
            raise ValueError(
                f"unknown correction(s) {', '.join(sorted(unknown))} in topple.corrections; "
                f"choose from {', '.join(CORRECTIONS)}, or all / none"
            )
        if "tip_path" in names and "finger_friction" not in names:
            raise ValueError("topple.corrections: tip_path checks finger_friction's balance on the way to the apex; "
                             "add finger_friction")
        if "carried_finger" in names and "finger_friction" not in names:
            raise ValueError("topple.corrections: carried_finger takes finger_friction's balance without its friction; "
                             "add finger_friction")
        return frozenset(names) if self.variant == "corrected" else frozenset()

    @property
    def applied_recalibration(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Knots (x, y) of the recalibration this configuration applies: empty (the identity)
        for the thesis's variants, whatever the fields say, as with the corrections."""
        if self.variant != "corrected":
            return (), ()
        return self.recalibration_x, self.recalibration_y

    @property
    def applied_smoothing(self) -> float:
        """m, the neighbourhood radius this configuration smooths over: 0 (no smoothing) for the
        thesis's variants, whatever the field says, as with the corrections."""
        return self.smoothing_radius if self.variant == "corrected" else 0.0

    @property
    def applied_feature_map(self) -> tuple[float, ...]:
        """Weights of the feature map (MODEL.md C.13) this configuration applies: empty for the
        thesis's variants, whatever the field says."""
        return self.feature_map if self.variant == "corrected" else ()

    @property
    def applied_down_map(self) -> tuple[float, ...]:
        """Weights of the down map (MODEL.md C.15) this configuration applies: empty for the
        thesis's variants, whatever the field says."""
        return self.down_map if self.variant == "corrected" else ()

    @property
    def applied_side_map(self) -> tuple[float, ...]:
        """Weights of the side map (MODEL.md C.16) this configuration applies: empty for the
        thesis's variants, whatever the field says."""
        return self.side_map if self.variant == "corrected" else ()

    @property
    def applied_boosted_map(self) -> str:
        """The boosted map (MODEL.md C.19) this configuration applies: empty for the thesis's
        variants, whatever the field says."""
        return self.boosted_map if self.variant == "corrected" else ""

    @property
    def applied_landing_spread(self) -> float:
        """The share of landing this configuration spreads (MODEL.md C.17): 0 for the thesis's
        variants, whatever the field says."""
        return self.landing_spread if self.variant == "corrected" else 0.0

    @property
    def applied_landing_onward(self) -> float:
        """The share of a marginal landing this configuration carries on (MODEL.md C.18): 0 for
        the thesis's variants and without the ``momentum`` correction, whatever the field says."""
        return self.landing_onward if "momentum" in self.applied_corrections else 0.0

    @property
    def needs_candidates(self) -> bool:
        """Whether a push's prediction depends on the pose's other candidates (the smoothing of
        C.12, the neighbourhood feature of C.13 and C.19, the borrowed landing of C.15 and C.19): a
        probe must then be evaluated beside them."""
        return (self.applied_smoothing > 0 or bool(self.applied_feature_map) or bool(self.applied_down_map)
                or bool(self.applied_boosted_map))

    def without_recalibration(self) -> "ToppleConfig":
        """This model with no map: what a recalibration (MODEL.md C.7), a feature map (C.13) or the
        down map (C.15) is fitted on (the side map of C.16 and the boosted map of C.19 cleared too), the Monte Carlo counts of (9.1)-(9.2) smoothed as configured (C.12),
        their landing neither spread (C.17) nor carried on (C.18)."""
        return dataclasses.replace(self, **NO_MAP, landing_spread=0.0, landing_onward=0.0)

    def counted(self) -> "ToppleConfig":
        """This model as the Monte Carlo counts of MODEL.md (9.1)-(9.2), neither smoothed (C.12) nor
        recalibrated (C.7): what the noise calibration searches.  Smoothing and the map are
        layers over the counts, fitted after the noise, never the other way round."""
        return dataclasses.replace(self.without_recalibration(), smoothing_radius=0.0)

    @property
    def trials(self) -> int:
        """Trials actually run per action: one noise-free trial for the non-robust variants."""
        return self.n_trials if self.robust else 1


@dataclass(frozen=True)
class SuctionConfig:
    """Suction grasp quality V_s (Dex-Net 3.0 style); see docs/MODEL.md for sources."""

    cup_radius: float = bounded(0.015, POSITIVE)
    """m, radius of the suction cup's perimeter ring."""
    ring_samples: int = bounded(16, Range(3, None))
    """Points on the perimeter ring checked for a seal."""
    max_approach_angle: float = bounded(math.radians(45.0), RIGHT_ANGLE)
    """rad; grasps approach from above within this angle of vertical."""
    n_candidates: int = bounded(100, AT_LEAST_ONE)
    """Candidate grasp points sampled per pose."""
    n_samples: int = bounded(20, AT_LEAST_ONE)
    """Monte Carlo perturbations per candidate grasp."""
    max_strain: float = bounded(0.1, POSITIVE)
    """Max relative change of a perimeter ring edge length for a seal (Dex-Net 3.0)."""
    max_deflection: float = bounded(0.004, POSITIVE)
    """m; max spread of ring contact depths along the approach for a seal."""
    vacuum_force: float = bounded(250.0, NON_NEGATIVE)
    """N, vacuum force of the cup (Dex-Net 3.0: V = 250 N)."""
    friction: float = bounded(0.5, NON_NEGATIVE)
    """Coefficient of friction of cup and surface (Dex-Net 3.0: mu = 0.5)."""
    torsional_friction: float = bounded(0.0025, NON_NEGATIVE)
    """m; lever arm r_t of the ring's friction against twisting: it resists |tau_z| <= r_t mu f_N
    (Dex-Net 3.0's form; r / sqrt(3) would be 8.7 mm, this is more conservative)."""
    elastic_limit: float = bounded(0.1, NON_NEGATIVE)
    """N m; largest torque about the contact's tangent axes before the cup peels (Dex-Net 3.0's
    form). 0.1 N m is about a 30 mm cup's peel torque at typical vacuum (0.3 N m) with a safety
    factor of 3; see docs/MODEL.md 11.5 for why not 0.005."""
    position_std: float = bounded(0.001, NON_NEGATIVE)
    """m, standard deviation of the grasp position."""
    axis_std: float = bounded(0.05, NON_NEGATIVE)
    """rad, standard deviation of the approach axis."""
    friction_std: float = bounded(0.1, NON_NEGATIVE)
    """Standard deviation of the friction coefficient."""
    mass_std_fraction: float = bounded(0.1, NON_NEGATIVE)
    """Relative standard deviation of the object's mass."""
    gripper_radius: float = bounded(0.0125, POSITIVE)
    """m, radius of the gripper body cylinder above the cup."""
    gripper_length: float = bounded(0.1, POSITIVE)
    """m, length of the gripper body above the cup."""


@dataclass(frozen=True)
class MDPConfig:
    """Value iteration over an object's stable poses (thesis 4.3.3)."""

    gamma: float = bounded(0.95, Range(0.0, 1.0, lo_open=True))
    tolerance: float = bounded(1e-9, POSITIVE)
    """Stop when no value changes by more than this."""
    max_iterations: int = bounded(10_000, AT_LEAST_ONE)
    min_direction_z: float = bounded(-1.0, Range(-1.0, 1.0))
    """Greedy and value iteration choose only pushes whose direction's vertical component
    (pose frame, z up) is at least this; -1 lets them choose any (the thesis, and the default
    since stop 45).  From stop 26 to 44 it was -0.3: the model ranked pushes from above poorly
    among themselves (docs/VALIDATION.md, "Plan on the pushes the model can judge").  With the
    boosted map (C.19) and value iteration choosing by its neighbourhood (``choice_radius``), the
    choice among every push gained +0.028 V_s over the argmax from the side on held-out objects, its
    pushes honest; the argmax among every push was over-predicted by 0.107 (docs/VALIDATION.md,
    "Tuning the planners out of fold").  Every push keeps its P(topple), Q and greedy value."""
    choice_radius: float = bounded(0.02, Range(0.0, None))
    """m.  Value iteration's push is the choosable one of highest mean Q_T over the ok pushes whose
    contact lies within this of its own and whose direction within ``choice_angle`` of its own
    (itself included), among those with at least ``choice_neighbours`` of them (docs/MODEL.md
    (12.15)); 0: the argmax of Q_T (the thesis).  The study's ``smoothed_vi`` limits (20 mm,
    0.5 rad, 5), tuned on corpus objects out of fold and judged on held-out ones at stop 44."""
    choice_angle: float = bounded(0.5, Range(0.0, None))
    """rad; see ``choice_radius``."""
    choice_neighbours: int = bounded(5, AT_LEAST_ONE)
    """See ``choice_radius``."""
    budget_min_direction_z: float = bounded(-1.0, Range(-1.0, 1.0))
    """The pushes the served budget (``/plan``'s ``pushes_left``, docs/MODEL.md (12.14)) may choose: u_z at
    least this; -1, every ok push.  With the boosted map (C.19) the budget that chooses from above gained
    +0.022 V_s over the one that chooses as value iteration does, its pushes honest (predicted 0.507, toppled
    0.481), on six held-out runs no rule had seen, by a rule written before they were played
    (docs/VALIDATION.md, "Choosing from above again"; value iteration's argmax among the pushes from above
    was over-predicted, so ``min_direction_z`` stayed -0.3 until its choice by neighbourhood, stop 45).  A build from before the field chose its budget's pushes
    as value iteration did.  The budget's P of a push from above is the boosted map's; a configuration
    without it but with a down map (C.15) lets the budget choose down-mapped pushes, which no rule judged."""
    retry_failed: bool = True
    """Whether value iteration may push again where a push failed (the thesis's Bellman
    equation).  False (opt-in): a push that leaves the object in its pose is worth grasping
    there (docs/MODEL.md (12.9)), which assumes the robot grasps after a failed push.  In physics
    a push's outcome is nearly fixed by the push, and without retries value iteration gained
    +0.016 V_s over six seeds, but its chosen pushes were over-predicted by 0.103 on the two fresh
    ones (played re-planning, so pushing a failed push again), past the 0.10 its rule allowed, so
    the thesis's equation stays the default (docs/VALIDATION.md, "A failed push is not retried")."""
    after_failure_power: float = bounded(2.1, Range(1.0, None))
    """k of the map g(p) = p^k from a push's P(topple) to its topple rate once a push from the
    same pose has failed: what ``/plan`` serves as ``p_topple_given_failures`` when a client
    reports its failed pushes (``schema.retry``), and what value iteration plans with when
    ``believe_failures`` (else the build does not use it).  A failure says
    the pose topples less than the table thinks: in pybullet value iteration's next pushes after
    one were predicted 0.244 and toppled 0.122 on corpus objects, while its first tries were
    honest.  Value iteration also ranks the untried pushes by it after a failure
    (docs/MODEL.md (12.13) when ``believe_failures``, else (12.12)).  Fitted on corpus objects only (docs/VALIDATION.md, "After a failed
    push"); 1 is no map (the thesis preset: the service then serves no such probability and value
    iteration ranks by Q_T)."""
    believe_failures: bool = True
    """Whether value iteration plans with the after-failure map from the first push on
    (docs/MODEL.md (12.13)): two states per pose, fresh and failed-here, a push from a pose where
    one has failed toppling with P^k, so the stored Q values a failure at the failed state's value
    V1(x), and after a failure ``/plan`` ranks the untried pushes by Q1.  k = 1 (the thesis preset)
    is the thesis's value iteration.  Played in pybullet against the thesis's equation, rule written
    before it was played: +0.012 V_s on four corpus seeds, +0.018 on two held-out ones, with a sixth
    fewer pushes (docs/VALIDATION.md, "Value iteration that believes its failures").  False: the
    thesis's Bellman equation, and after a failure (12.12)."""
    choose_for_repeats: bool = False
    """Whether value iteration's stored push is chosen for a client that pushes it again after it fails
    (docs/MODEL.md (12.16)): ranked (by its neighbourhood, as ``choice_radius`` says) by Q_R, the value
    of the pose -> push map whose failed pushes are repeated at P^k (``after_failure_power``), instead of by
    Q0, which counts a failure at the best untried push.  Only the choice moves: the stored Q, V and the
    ranking after a reported failure stay (12.13)'s.  Opt-in: played in pybullet by a rule written before its
    plays, it lost 0.0056 +/- 0.0017 V_s to Q0's choice over 24 held-out runs, its pushes toppling more often
    into poorer poses (docs/VALIDATION.md, "The stored push chosen for the client that repeats it")."""
    repeats_then_grasp: bool = False
    """With ``choose_for_repeats``: the repeating client grasps where its push failed once repeating is worth
    less, as a robot whose push budget runs out does (docs/MODEL.md (12.17)), instead of repeating for ever.
    Q_G only ranks the stored push; the grasp after a failure is not served.  Opt-in: +0.0033 +/- 0.0061 V_s
    over Q0's choice on held-out seed 13, short of the two standard errors its rule asked
    (``reports/repeat_grasp_rule_s47.md``)."""

    @property
    def plans_with_failures(self) -> bool:
        """Whether value iteration is (12.13) with a map: ``believe_failures`` and k != 1 (k = 1
        believes nothing, the thesis's equation to the bit)."""
        return self.believe_failures and self.after_failure_power != 1.0

    @property
    def failure_power(self) -> float | None:
        """k of (12.13)-(12.14) when the build plans with its failures, else None: what
        ``schema.horizon.solve_budgets`` takes to choose between (12.14) and (12.8)."""
        return self.after_failure_power if self.plans_with_failures else None

    def __post_init__(self) -> None:
        if self.believe_failures and not self.retry_failed:
            raise ValueError("mdp.retry_failed = false values a failure at the grasp (MODEL.md (12.9)) and "
                             "mdp.believe_failures = true at the failed state's value (12.13): two answers to one "
                             "question; set mdp.believe_failures = false with mdp.retry_failed = false")
        if self.repeats_then_grasp and not self.choose_for_repeats:
            raise ValueError("mdp.repeats_then_grasp says how the client of mdp.choose_for_repeats ends: set both")
        if self.choose_for_repeats and not self.retry_failed:
            raise ValueError("mdp.choose_for_repeats chooses for a client that pushes again after a failure and "
                             "mdp.retry_failed = false for one that grasps (MODEL.md (12.9)): set one of them")
        if self.choose_for_repeats and not self.plans_with_failures:
            # (12.16) believes a repeat as (12.13) believes any push after a failure, and moves (12.13)'s choice.
            raise ValueError("mdp.choose_for_repeats ranks by (12.13)'s belief (MODEL.md (12.16)): it needs "
                             "mdp.believe_failures = true and mdp.after_failure_power != 1")


@dataclass(frozen=True)
class Config:
    """The whole parameter set; ``seed`` roots every random stream (see ``pipeline.model.rng``)."""

    seed: int = bounded(0, Range(0, None))
    mesh: MeshConfig = field(default_factory=MeshConfig)
    poses: PoseConfig = field(default_factory=PoseConfig)
    contacts: ContactConfig = field(default_factory=ContactConfig)
    topple: ToppleConfig = field(default_factory=ToppleConfig)
    suction: SuctionConfig = field(default_factory=SuctionConfig)
    mdp: MDPConfig = field(default_factory=MDPConfig)

    def __post_init__(self) -> None:
        # The model's stroke is the executed push's depth; two values would predict one push
        # and execute another.
        if self.topple.stroke != self.contacts.push_depth:
            raise ValueError(
                f"topple.stroke ({self.topple.stroke:g} m) must equal contacts.push_depth "
                f"({self.contacts.push_depth:g} m): the model predicts the push the robot executes; set both"
            )
        if maps_unjudged_choices(self.topple, self.mdp):
            raise ValueError(
                f"topple.down_map_z ({self.topple.down_map_z:g}) is above mdp.min_direction_z ({self.mdp.min_direction_z:g}): "
                "the down map would map pushes the policies may choose, which only the boosted map with a choice by "
                "neighbourhood (mdp.choice_radius > 0) keeps honest; lower topple.down_map_z, raise mdp.min_direction_z, "
                "or set no down map (topple.down_map = [], --set topple.down_map=)"
            )

    def to_dict(self) -> dict[str, Any]:
        """Every parameter as plain JSON types (tuples of knots as lists, as JSON reads them back)."""
        return _lists(dataclasses.asdict(self))

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Config":
        """Build from nested sections; a ``contacts.push_depth`` given without ``topple.stroke``
        (a config file, or a manifest written before the stroke existed) sets the stroke too, and
        a ``[topple]`` map of its own given without ``down_map`` or ``side_map`` comes without that map."""
        contacts, topple = data.get("contacts"), data.get("topple")
        # Only into a [topple] table or none: a topple that is not a table must stay one, to be refused
        # (``_build``), not replaced by a table holding the stroke alone and every other default.
        if (isinstance(contacts, dict) and "push_depth" in contacts
                and (topple is None or (isinstance(topple, dict) and "stroke" not in topple))):
            data = {**data, "topple": {**(topple or {}), "stroke": contacts["push_depth"]}}
        topple = data.get("topple")
        if isinstance(topple, dict) and _own_map(topple):
            # A map belongs to the probabilities it was fitted on: a file with a map of its own,
            # written before the down map (MODEL.md C.15) or the side map (C.16) existed, does not
            # take the default's.  (``--set`` changes one key of a whole configuration and keeps them.)
            data = {**data, "topple": {**topple, **{name: () for name in ("down_map", "side_map") if name not in topple}}}
        mdp = data.get("mdp")
        if isinstance(mdp, dict) and "after_failure_power" in mdp and mdp["after_failure_power"] is None:
            # A manifest from before the after-failure map reads it as none (schema.manifest); the
            # build never used it, so such a manifest's configuration takes the default.
            data = {**data, "mdp": {k: v for k, v in mdp.items() if k != "after_failure_power"}}
        return _build(cls, data, "")

    @classmethod
    def from_toml(cls, path: str | Path) -> "Config":
        """The file's configuration.  A boosted map it names by a relative path (``topple.boosted_map``
        ending in .json) is the file beside it, as ``toppledb recalibrate`` writes the two: they move
        together, to another directory or machine.  (On the command line, ``--set`` names a path from
        the working directory.)"""
        with open(path, "rb") as f:
            data = tomllib.load(f)
        topple = data.get("topple")
        name = topple.get("boosted_map") if isinstance(topple, dict) else None
        if isinstance(name, str) and name.endswith(".json") and not Path(name).is_absolute():
            data = {**data, "topple": {**topple, "boosted_map": str((Path(path).parent / name).resolve())}}
        return cls.from_dict(data)

    def with_overrides(self, overrides: dict[str, Any]) -> "Config":
        """Return a copy with dotted keys replaced, e.g. ``{"topple.n_trials": 10}``; the stroke
        follows a new ``contacts.push_depth`` unless ``topple.stroke`` is given too."""
        if "contacts.push_depth" in overrides and "topple.stroke" not in overrides:
            overrides = {**overrides, "topple.stroke": overrides["contacts.push_depth"]}
        data = self.to_dict()
        for key, value in overrides.items():
            *path, leaf = key.split(".")
            node = data
            for depth, part in enumerate(path):
                section = ".".join(path[: depth + 1])
                if part in node and not isinstance(node[part], dict):
                    raise ValueError(f"config key {section!r} is a value, not a section (in {key!r})")
                if part not in node:
                    known = ", ".join(sorted(k for k, v in node.items() if isinstance(v, dict)))
                    raise ValueError(f"unknown config section {section!r} in {key!r} (sections: {known})")
                node = node[part]
            if leaf not in node:
                raise ValueError(f"unknown config key {key!r}")
            if isinstance(node[leaf], dict):
                raise ValueError(f"config key {key!r} is a section, not a value: set one of its keys, e.g. {key}.{next(iter(node[leaf]))}")
            node[leaf] = value
        return Config.from_dict(data)


def maps_unjudged_choices(topple: ToppleConfig, mdp: MDPConfig) -> bool:
    """Whether the down map (MODEL.md C.15) maps pushes the policies may choose in a way no rule judged.

    The down map is safe only on pushes no policy chooses: a map of chosen pushes makes them
    over-confident (C.7, C.13).  The boosted map (C.19) maps those pushes after it, and value
    iteration choosing by its neighbourhood kept them honest (stops 44-45); its argmax did not, so
    both are needed.  Greedy shares the cut and keeps its argmax: no rule judged it (its pushes 0.564
    predicted, 0.508 toppled on held-out seed 9).  ``Config`` refuses such a pair; ``toppledb
    recalibrate`` writes the cut into a file that would be one."""
    chooses_safely = bool(topple.applied_boosted_map) and mdp.choice_radius > 0
    return bool(topple.applied_down_map) and topple.down_map_z > mdp.min_direction_z and not chooses_safely


def _own_map(topple: dict[str, Any]) -> bool:
    """Whether a ``[topple]`` section sets a map of P(topple) of its own: any recalibration knots
    (a manifest written before the down map has them, and was built without it), or a feature
    map other than the default's (a file restating ``feature_map = []`` has none)."""
    if "recalibration_x" in topple or "recalibration_y" in topple:
        return True
    if "feature_map" not in topple:
        return False
    try:
        return tuple(float(v) for v in topple["feature_map"]) != ToppleConfig().feature_map
    except (TypeError, ValueError):
        return True  # not a list of numbers: ``_build`` says what is wrong with it


def _lists(node: Any) -> Any:
    if isinstance(node, dict):
        return {k: _lists(v) for k, v in node.items()}
    if isinstance(node, tuple):
        return [_lists(v) for v in node]
    return node


def _build(cls, data: dict[str, Any], prefix: str):
    known = {f.name: f for f in fields(cls)}
    unknown = set(data) - set(known)
    if unknown:
        raise ValueError(f"unknown config key(s): {', '.join(prefix + k for k in sorted(unknown))}")
    kwargs = {}
    for name, value in data.items():
        f = known[name]
        default = f.default_factory() if f.default_factory is not dataclasses.MISSING else f.default
        if is_dataclass(default):
            if not isinstance(value, dict):
                raise ValueError(f"config section {prefix + name!r} must be a table")
            kwargs[name] = _build(type(default), value, f"{prefix}{name}.")
        else:
            kwargs[name] = _coerce(value, default, prefix + name)
            accepted = f.metadata.get("range")
            # A tuple field (knots) is checked element by element.
            items = kwargs[name] if isinstance(kwargs[name], tuple) else (kwargs[name],)
            what = "every entry of " if isinstance(kwargs[name], tuple) else ""
            if accepted is not None and not all(math.isfinite(v) for v in items):  # nan, inf: no range holds them
                raise ValueError(f"config key {what}{prefix + name!r} must be a finite number, got {value!r}")
            if accepted is not None and not all(accepted.contains(v) for v in items):
                raise ValueError(f"config key {what}{prefix + name!r} must be {accepted.text()}, got {value!r}")
    return cls(**kwargs)


def parameter_table(config: "Config | None" = None) -> list[tuple[str, Any, str]]:
    """Every ``section.key`` with its value in ``config`` (default: the defaults) and
    accepted range, for ``--help`` and error messages."""
    config = config or Config()
    rows = []

    def walk(node: Any, prefix: str) -> None:
        for f in fields(node):
            value = getattr(node, f.name)
            if is_dataclass(value):
                walk(value, f"{prefix}{f.name}.")
            else:
                accepted = f.metadata.get("range")
                rows.append((prefix + f.name, value, accepted.text() if accepted else ""))

    walk(config, "")
    return rows


def _coerce(value: Any, default: Any, key: str) -> Any:
    kind = type(default)
    if kind is tuple:
        return _numbers(value, key)
    if isinstance(value, (bool, np.bool_)) != (kind is bool) and not isinstance(value, str):
        # bool is an int to Python: a TOML ``mass = true`` must not become 1.0, nor a 1 a switch.
        raise ValueError(f"config key {key!r} expects {kind.__name__}, got {value!r}")
    if isinstance(value, kind):
        return value
    if kind is bool and isinstance(value, np.bool_):
        return bool(value)
    try:
        if kind is bool and isinstance(value, str):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(value)
        if kind is int and isinstance(value, float):
            if not value.is_integer():  # int() would cut a TOML 1.5 trials to 1
                raise TypeError(value)
            return int(value)
        if kind is float and isinstance(value, int):
            return float(value)
        return kind(value)
    except (TypeError, ValueError):
        raise ValueError(f"config key {key!r} expects {kind.__name__}, got {value!r}") from None


def _numbers(value: Any, key: str) -> tuple[float, ...]:
    """A list of numbers: a TOML/JSON array, or a comma-separated string (``--set``)."""
    if isinstance(value, str):
        value = [v for v in value.replace(" ", "").split(",") if v]
    bad = ValueError(f"config key {key!r} expects a list of numbers, got {value!r}")
    if not isinstance(value, (list, tuple)) or any(isinstance(v, bool) for v in value):
        raise bad
    try:
        return tuple(float(v) for v in value)
    except (TypeError, ValueError):
        raise bad from None
