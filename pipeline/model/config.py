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

VARIANTS = ("baseline", "rotations", "robustness", "robust")
"""Model variants of thesis table 4.1: (predicts planar rotations, robust estimates)."""


@dataclass(frozen=True)
class MeshConfig:
    """Loading and validation of corpus meshes."""

    default_mass: float = 0.25
    """kg, used when the corpus gives no mass."""
    min_extent: float = 0.01
    """m; an object whose largest bounding-box side is smaller is rejected as too small."""
    max_extent: float = 0.5
    """m; an object whose largest bounding-box side is larger is rejected as too large for a tabletop."""
    fill_holes: bool = True
    """Let trimesh fill small holes before the watertightness check."""


@dataclass(frozen=True)
class PoseConfig:
    """Stable poses and their identity."""

    min_probability: float = 0.01
    """Stable poses dropped with lower probability are left out unless a topple reaches them."""
    same_pose_angle: float = math.radians(10.0)
    """rad; two orientations are the same stable pose when their down vectors differ by at most this."""
    base_tolerance: float = 1e-3
    """m; hull vertices this close to the table form the base (docs/MODEL.md 5)."""


@dataclass(frozen=True)
class ContactConfig:
    """Candidate pushes (thesis 4.4.1) and the finger that executes them."""

    n_contacts: int = 1000
    """Candidate contact points per pose, exactly this many, spread evenly over the surface."""
    oversample: int = 10
    """Uniform surface samples per candidate from which the even subset is chosen."""
    min_height_fraction: float = 0.15
    """Contacts lower than this fraction of the object's height in the pose are ``too_low``."""
    max_up_angle: float = math.radians(60.0)
    """rad; a push pointing up more than this above horizontal is ``pushes_up``."""
    finger_radius: float = 0.004
    """m, radius of the finger capsule."""
    finger_length: float = 0.06
    """m, length of the finger capsule."""
    approach_offset: float = 0.015
    """m; the finger starts this far outside the contact along the normal."""
    push_depth: float = 0.04
    """m; the executed motion ends this far inside the contact (p - push_depth n)."""
    max_height_normal_angle: float = math.radians(15.0)
    """rad; Max-Height baseline pushes the highest point whose normal is this close to horizontal."""


@dataclass(frozen=True)
class ToppleConfig:
    """The quasi-static toppling model (thesis 4.2) and its Monte Carlo noise (4.2.5).

    Standard deviations, as in the authors' released code.
    """

    variant: str = "robust"
    """One of ``baseline``, ``rotations``, ``robustness``, ``robust`` (thesis table 4.1)."""
    n_trials: int = 100
    """Noisy trials per action for the robust variants; noise-free variants use one."""
    gravity: float = 9.81
    """m/s^2."""
    mu_table_mean: float = 0.43
    mu_table_std: float = 0.1
    mu_finger_mean: float = 0.98
    mu_finger_std: float = 0.2
    contact_std: float = 5.05e-4
    """m, isotropic standard deviation of the contact position."""
    direction_std: float = 0.055
    """Isotropic standard deviation added to the unit push direction before renormalising."""
    rotation_std: float = 0.22
    """rad, standard deviation of the object rotation about a uniformly random axis."""
    ray_offset: float = 0.015
    """m; the finger ray that re-finds a noisy contact starts this far outside it."""
    chunk_actions: int = 256
    """Actions evaluated per vectorised block; bounds peak memory, not results."""

    def __post_init__(self) -> None:
        if self.variant not in VARIANTS:
            raise ValueError(f"unknown variant {self.variant!r}; choose one of {', '.join(VARIANTS)}")
        if self.n_trials < 1:
            raise ValueError("n_trials must be at least 1")

    @property
    def predicts_rotations(self) -> bool:
        return self.variant in ("rotations", "robust")

    @property
    def robust(self) -> bool:
        return self.variant in ("robustness", "robust")

    @property
    def trials(self) -> int:
        """Trials actually run per action: one noise-free trial for the non-robust variants."""
        return self.n_trials if self.robust else 1


@dataclass(frozen=True)
class SuctionConfig:
    """Suction grasp quality V_s (Dex-Net 3.0 style); see docs/MODEL.md for sources."""

    cup_radius: float = 0.015
    """m, radius of the suction cup's perimeter ring."""
    ring_samples: int = 16
    """Points on the perimeter ring checked for a seal."""
    max_approach_angle: float = math.radians(45.0)
    """rad; grasps approach from above within this angle of vertical."""
    n_candidates: int = 100
    """Candidate grasp points sampled per pose."""
    n_samples: int = 20
    """Monte Carlo perturbations per candidate grasp."""
    max_strain: float = 0.1
    """Max relative change of a perimeter ring edge length for a seal (Dex-Net 3.0)."""
    max_deflection: float = 0.004
    """m; max spread of ring contact depths along the approach for a seal."""
    vacuum_force: float = 250.0
    """N, vacuum force of the cup (Dex-Net 3.0: V = 250 N)."""
    friction: float = 0.5
    """Coefficient of friction of cup and surface (Dex-Net 3.0: mu = 0.5)."""
    torsional_friction: float = 0.0025
    """m; lever arm r_t of the ring's friction against twisting: it resists |tau_z| <= r_t mu f_N
    (Dex-Net 3.0's form; r / sqrt(3) would be 8.7 mm, this is more conservative)."""
    elastic_limit: float = 0.1
    """N m; largest torque about the contact's tangent axes before the cup peels (Dex-Net 3.0's
    form). 0.1 N m is about a 30 mm cup's peel torque at typical vacuum (0.3 N m) with a safety
    factor of 3; see docs/MODEL.md 11.5 for why not 0.005."""
    position_std: float = 0.001
    """m, standard deviation of the grasp position."""
    axis_std: float = 0.05
    """rad, standard deviation of the approach axis."""
    friction_std: float = 0.1
    """Standard deviation of the friction coefficient."""
    mass_std_fraction: float = 0.1
    """Relative standard deviation of the object's mass."""
    gripper_radius: float = 0.0125
    """m, radius of the gripper body cylinder above the cup."""
    gripper_length: float = 0.1
    """m, length of the gripper body above the cup."""


@dataclass(frozen=True)
class MDPConfig:
    """Value iteration over an object's stable poses (thesis 4.3.3)."""

    gamma: float = 0.95
    tolerance: float = 1e-9
    """Stop when no value changes by more than this."""
    max_iterations: int = 10_000


@dataclass(frozen=True)
class Config:
    """The whole parameter set; ``seed`` roots every random stream (see ``pipeline.model.rng``)."""

    seed: int = 0
    mesh: MeshConfig = field(default_factory=MeshConfig)
    poses: PoseConfig = field(default_factory=PoseConfig)
    contacts: ContactConfig = field(default_factory=ContactConfig)
    topple: ToppleConfig = field(default_factory=ToppleConfig)
    suction: SuctionConfig = field(default_factory=SuctionConfig)
    mdp: MDPConfig = field(default_factory=MDPConfig)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> "Config":
        return _build(cls, data, "")

    @classmethod
    def from_toml(cls, path: str | Path) -> "Config":
        with open(path, "rb") as f:
            return cls.from_dict(tomllib.load(f))

    def with_overrides(self, overrides: dict[str, Any]) -> "Config":
        """Return a copy with dotted keys replaced, e.g. ``{"topple.n_trials": 10}``."""
        data = self.to_dict()
        for key, value in overrides.items():
            *path, leaf = key.split(".")
            node = data
            for part in path:
                if part not in node or not isinstance(node[part], dict):
                    raise ValueError(f"unknown config section {key!r}")
                node = node[part]
            if leaf not in node:
                raise ValueError(f"unknown config key {key!r}")
            node[leaf] = value
        return Config.from_dict(data)


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
    return cls(**kwargs)


def _coerce(value: Any, default: Any, key: str) -> Any:
    kind = type(default)
    if isinstance(value, kind):
        return value
    try:
        if kind is bool and isinstance(value, str):
            if value.lower() in ("1", "true", "yes", "on"):
                return True
            if value.lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError(value)
        if kind is int and isinstance(value, float) and value.is_integer():
            return int(value)
        if kind is float and isinstance(value, int):
            return float(value)
        return kind(value)
    except (TypeError, ValueError):
        raise ValueError(f"config key {key!r} expects {kind.__name__}, got {value!r}") from None
