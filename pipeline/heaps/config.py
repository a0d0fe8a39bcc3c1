"""Every parameter of the heap simulation and of heap grasp confidence, in one typed place.

Chapter 3 of the thesis (Correa 2019) names the experiment but few numbers; each default
says where it comes from: [thesis] Correa 2019 chapter 3, [DN2] Dex-Net 2.0 (Mahler et al.,
RSS 2017; the dex-net repository's robust grasp metric configuration), [DN3] Dex-Net 3.0
(Mahler et al., ICRA 2018; reused through ``pipeline.model.config.SuctionConfig``), [ours]
a choice of this project, with its reason.  docs/HEAPS.md lists them again as a table.

Units: metres, kilograms, seconds, radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields

from clutter.state import Bin

from ..model.config import SuctionConfig

GRAVITY = 9.81
"""m/s^2: the simulation's gravity and the one suction grasps must hold against (one number)."""


@dataclass(frozen=True)
class SimConfig:
    """pybullet settings for dropping, settling and pushing."""

    time_step: float = 1.0 / 240.0
    """s, Bullet's default step [ours: pybullet's default]."""
    solver_iterations: int = 10
    """Constraint solver iterations per step; Bullet's default.  The push player
    (``pipeline.studies.pushsim``) uses 50 for one object's topple; a heap only needs
    objects at rest in plausible places, and 10 is ~3x cheaper [ours]."""
    collision_margin: float = 1e-3
    """m, Bullet's convex margin.  Its default: objects float ~1 mm over the floor, which
    does not matter for grasp confidence and keeps stacked hulls stable [ours]."""
    drop_clearance: float = 0.02
    """m, gap left between the bounding spheres of objects placed above the bin before the drop [ours]."""
    drop_spread: float = 0.03
    """m, std of an object's drop position (in plan) about the heap's centre, itself uniform over
    the middle half of the bin floor.  [ours] Uniform drops over the whole floor leave 9 cm objects
    mostly apart; concentrated drops make the touching, overlapping heaps pushing is for."""
    settle_time: float = 3.0
    """s, most simulated time a drop is given to come to rest [ours: measured, 10-object heaps
    rest within ~1.5 s]."""
    resettle_time: float = 1.0
    """s, most simulated time after an object is picked out or a push ends [ours]."""
    rest_speed: float = 0.005
    """m/s, every object's centre of mass below this for ``rest_steps`` steps = at rest [ours]."""
    rest_spin: float = 0.05
    """rad/s, every object's angular speed below this too [ours]."""
    rest_steps: int = 24
    """Steps in a row at rest (0.1 s at 240 Hz) [ours]."""
    object_friction: tuple[float, float] = (0.3, 0.7)
    """Uniform range of the heap's friction coefficient mu (one draw per heap; each object gets it,
    the bin and the finger 1, and Bullet multiplies two bodies' coefficients: mu against the bin or
    the finger, mu squared between two objects).  [thesis] samples friction coefficients per heap without giving the
    distribution; [ours] the range brackets Dex-Net's mean 0.5 [DN2]."""
    finger_radius: float = 0.01
    """m, radius of the pushing finger, a vertical cylinder (a closed parallel-jaw gripper
    is about 2 cm across; [thesis] pushes with the closed YuMi gripper) [ours].  The experiment
    plans with the same radius (``clutter.policies.PushConfig.finger_radius``); the push length
    and approach are the planner's (``PushConfig``)."""
    finger_height: float = 0.10
    """m, length of the finger cylinder above its tip [ours]."""
    finger_speed: float = 0.2
    """m/s, finger speed along the push [ours: fast enough to be cheap, slow enough that the
    pushed object does not fly; the thesis's robot pushes at a similar pace]."""
    finger_max_force: float = 100.0
    """N, strength of the constraint that drags the finger [ours]."""
    max_object_extent: float = 0.20
    """m, objects larger than this are not dropped (none of the default corpus is) [ours]."""


@dataclass(frozen=True)
class JawConfig:
    """Parallel-jaw gripper and its analytic robust quality (robust force closure, Dex-Net 2.0 style)."""

    max_opening: float = 0.14
    """m, largest jaw opening.  [ours] The YuMi gripper of [DN2] opens 5 cm, but most of the default
    corpus (pybullet's random_urdfs) is ~9 cm across its narrowest side; 14 cm (a Robotiq 2F-140's
    stroke) lets the jaws take about half of the objects across some side."""
    clearance: float = 0.01
    """m, each finger opens this far outside its contact before closing (pre-grasp width =
    contact width + 2 clearance, capped at ``max_opening``) [ours]."""
    finger_thickness: float = 0.01
    """m, finger size along the grasp axis [ours]."""
    finger_width: float = 0.02
    """m, finger size across the grasp axis [ours]."""
    finger_length: float = 0.06
    """m, finger length along the approach, from tip to palm [ours]."""
    tip_depth: float = 0.005
    """m, fingertips reach this far past the contact line along the approach [ours]."""
    palm_thickness: float = 0.03
    """m, palm size along the approach (the palm spans the opening above the fingers) [ours]."""
    friction: float = 0.5
    """Coefficient of friction of the jaw contacts [DN2: friction_coef 0.5]."""
    friction_std: float = 0.1
    """Standard deviation of the friction coefficient [DN2: sigma_friction_coef 0.1]."""
    grasp_position_std: float = 0.005
    """m, std of the grasp centre [DN2: sigma_grasp_trans 0.005]."""
    object_position_std: float = 0.01
    """m, std of the object's position relative to the gripper, added to the grasp's [DN2: sigma_obj_trans 0.01]."""
    axis_std: float = 0.01
    """rad, std of the grasp axis direction [DN2: sigma_obj_rot 0.01 plus sigma_grasp_rot 0.001]."""
    n_samples: int = 25
    """Perturbed samples per grasp [DN2: num_quality_samples 25]."""
    n_candidates: int = 200
    """Antipodal candidates sampled per object (object frame, once per object) [ours; DN2 samples
    100 surface points x 2 directions]."""
    cone_spread: float = 0.5
    """Candidate axes are the inward normal tilted by up to this fraction of the friction cone
    angle atan(friction) [DN2's antipodal sampler draws in the cone; ours: half of it]."""
    max_axis_tilt: float = math.radians(45.0)
    """rad, largest angle between the grasp axis and the bin floor; the approach is the
    most vertical direction perpendicular to the axis, so it is as far from vertical [ours:
    "top-down-ish" as [DN2]'s planar grasps, widened to 45 degrees like suction's approach cone]."""
    min_width: float = 0.002
    """m, contacts closer than this are one point, not a grasp [DN2: min_contact_dist 0.0025]."""


@dataclass(frozen=True)
class HeapConfig:
    """The whole heap experiment's parameters; ``seed`` roots every random stream."""

    bin: Bin = field(default_factory=Bin)
    """Bin floor 0.50 x 0.40 m, walls 0.15 m high, 1 cm thick (``clutter.state.Bin``'s tote)."""
    min_objects: int = 2
    """[thesis] heaps of two to ten objects."""
    max_objects: int = 10
    """[thesis]."""
    sim: SimConfig = field(default_factory=SimConfig)
    jaw: JawConfig = field(default_factory=JawConfig)
    suction: SuctionConfig = field(default_factory=lambda: SuctionConfig(n_candidates=200))
    """[DN3] cup, seal, wrench and perturbation model, reused from the toppling model; 200
    candidates over the whole surface (object frame, once per object; about half face up in
    any pose) instead of 100 over one pose's upward faces."""
    grasp_threshold: float = 0.9
    """A heap is hard (thesis 3.3.1) when neither gripper's best accessible grasp reaches this
    confidence.  [thesis] its grasping policy "has confidence below a threshold", not given.
    [ours, measured on the default corpus] an object alone reaches a parallel-jaw robust quality
    of 0.9-1.0 and keeps it in a loose heap, so below 0.9 its better grasps are blocked or it is
    a poor object; at 0.5 grasping out goes on until one poor object is left (8 of 30 heaps hard,
    all with one object), which leaves the multi-object policies nothing to push apart."""
    max_removals: int = 10
    """Most objects picked out while searching for the hard state (= max_objects) [ours]."""
    seed: int = 0
    """Experiment seed; heap k's streams derive from (seed, k, purpose) (``pipeline.heaps.seeds``)."""

    def __post_init__(self) -> None:
        if not (1 <= self.min_objects <= self.max_objects):
            raise ValueError(f"need 1 <= min_objects <= max_objects, got {self.min_objects}, {self.max_objects}")
        low, high = self.sim.object_friction
        if not (0 < low <= high):
            raise ValueError(f"object_friction must be 0 < low <= high, got {self.sim.object_friction}")
        if not (0.0 <= self.grasp_threshold <= 1.0):
            raise ValueError(f"grasp_threshold must be in [0, 1], got {self.grasp_threshold}")
        if self.seed < 0:
            raise ValueError(f"seed must be >= 0, got {self.seed}")


def to_dict(config: HeapConfig) -> dict:
    """Plain nested dict of every parameter, for reports."""
    def plain(value):
        if hasattr(value, "__dataclass_fields__"):
            return {f.name: plain(getattr(value, f.name)) for f in fields(value)}
        if isinstance(value, tuple):
            return list(value)
        return value

    return plain(config)
