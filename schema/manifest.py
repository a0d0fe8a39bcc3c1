"""``manifest.json``: what a finished dataset holds and how it was made, as a typed
model shared by the pipeline that writes it and the service and studies that read it.

The pipeline writes the manifest last; a directory without one is a build in
progress (or a failed one) and readers refuse it.  ``read_manifest`` is the one
reader: it checks that the file parses, fits this model, and has this code's
``SCHEMA_VERSION``.

``parameters`` holds the whole ``pipeline.model.config.Config``; the sections and
fields a reader relies on are typed here (the rest is kept as written), so a
manifest that lacks one is refused at load time, not at the first request.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from schema import layout
from schema.version import SCHEMA_VERSION

FILE_PARAMETERS = ("topple.boosted_map",)
"""The parameters that name a file the build reads (``Manifest.parameter_files``), as section.key."""


class ManifestError(ValueError):
    """A directory that is not a finished dataset this code can read (one-line message)."""


class _Open(BaseModel):
    """A section whose typed fields are what readers need; other fields are kept."""

    model_config = ConfigDict(extra="allow")


class _Closed(BaseModel):
    model_config = ConfigDict(extra="forbid")


class PoseParameters(_Open):
    same_pose_angle: float = Field(gt=0, description="rad; observed poses within this angle of a stable pose match it")


class ContactParameters(_Open):
    n_contacts: int = Field(ge=1)
    approach_offset: float = Field(ge=0, description="m; the finger starts this far outside the contact")
    push_depth: float = Field(ge=0, description="m; and ends this far inside it")


class ToppleParameters(_Open):
    variant: str
    n_trials: int = Field(ge=1)


class MDPParameters(_Open):
    gamma: float = Field(gt=0, le=1)
    min_direction_z: float = Field(-1.0, ge=-1, le=1)
    """Greedy and value iteration chose only pushes with u_z at least this (pose frame); a
    manifest from before the field chose from every push, which -1 is."""
    budget_min_direction_z: float = Field(-1.0, ge=-1, le=1)
    """The served budget (``pushes_left``) chooses only pushes with u_z at least this; a manifest from
    before the field chose as its policies did, so it reads as their ``min_direction_z``."""
    retry_failed: bool = True
    """Whether value iteration counted on pushing again where a push failed (the thesis, the
    default) or valued that pose at its grasp (docs/MODEL.md (12.9)); a manifest from before the
    field counted on it."""
    after_failure_power: float | None = Field(None, ge=1)
    """k of the after-failure map p^k that /plan serves with failed_actions (``schema.retry``);
    a manifest from before the field has none, and the service serves no such probability."""
    believe_failures: bool = False
    """Whether value iteration planned with the after-failure map from the first push on
    (docs/MODEL.md (12.13)): the stored Q is Q0 and after a failure /plan ranks by Q1.  A manifest
    from before the field was built with the thesis's equation."""
    choice_radius: float = Field(0.0, ge=0)
    """m: value iteration's push was the one of highest neighbourhood-mean Q_T within this (and
    ``choice_angle``, ``choice_neighbours``; docs/MODEL.md (12.15)); 0, the argmax
    of Q_T, which a manifest from before the field took."""
    choice_angle: float = Field(0.5, ge=0)
    choice_neighbours: int = Field(5, ge=1)

    @model_validator(mode="before")
    @classmethod
    def _budget_chose_as_the_policies(cls, data):
        """A manifest from before ``budget_min_direction_z`` (or with it null) reads it as the policies' cut:
        the service and ``Config.from_dict`` of its parameters then need no rule of their own."""
        if isinstance(data, dict) and data.get("budget_min_direction_z") is None:
            data = {**data, "budget_min_direction_z": data.get("min_direction_z", -1.0)}
        return data

    @property
    def plans_with_failures(self) -> bool:
        """``MDPConfig.plans_with_failures`` of the build: it believed failures with a map (k != 1),
        so its budgets are (12.14) too; k None (a manifest from before the map) believes nothing."""
        return self.believe_failures and self.after_failure_power not in (None, 1.0)

    @property
    def failure_power(self) -> float | None:
        """``MDPConfig.failure_power`` of the build: its k when it plans with its failures, else None."""
        return self.after_failure_power if self.plans_with_failures else None


class Parameters(_Open):
    """``Config.to_dict()``: every model parameter of the build."""

    seed: int
    poses: PoseParameters
    contacts: ContactParameters
    topple: ToppleParameters
    mdp: MDPParameters


class CodeVersion(_Open):
    package: str
    git_commit: str | None = None
    python: str
    libraries: dict[str, str | None] = {}
    blas: dict[str, str | None] = Field(default={}, description=(
        "numpy's BLAS in the building process: library, version, kernel, and the kernel requested by "
        "OPENBLAS_CORETYPE (pipeline.numerics pins one on x86-64); empty in manifests before stop 63"))
    simd: list[str] | None = Field(default=None, description=(
        "the SIMD targets numpy's own loops dispatched to in the building process (pipeline.numerics.numpy_simd): "
        "not pinned, and AVX-512 ones round some float64 functions otherwise; absent before stop 68"))


class CorpusObject(_Closed):
    object_id: str
    path: str
    scale: float
    mass: float
    source: str
    sha256: str


class Corpus(_Closed):
    name: str
    objects: list[CorpusObject]


class Counts(_Closed):
    objects: int
    failed: int
    poses: int
    actions: int
    ok_actions: int
    transitions: int


class TableFile(_Closed):
    sha256: str
    rows: int


class ShardCounts(_Closed):
    poses: int
    actions: int
    ok_actions: int
    transitions: int


class Shard(_Closed):
    files: dict[str, str] = Field(description="path relative to the dataset -> SHA-256")
    counts: ShardCounts
    fingerprint: str = Field(description="SHA-256 of the shard's inputs (parameters, object, schema version)")


class Failure(_Closed):
    object_id: str
    path: str
    reason: str
    kind: Literal["mesh", "corpus", "error"]
    detail: str = ""


class Timings(_Closed):
    wall_s: float
    cpu_s_by_stage: dict[str, float]
    cpu_s_total: float


class Manifest(_Closed):
    schema_version: str
    code_version: CodeVersion
    created: str = Field(description="UTC, ISO 8601, when the build finished")
    seed: int
    parameters: Parameters
    corpus: Corpus
    counts: Counts
    tables: dict[str, TableFile]
    shards: dict[str, Shard]
    failures: list[Failure]
    timings: Timings
    run: dict[str, object] = Field(description="workers, backend, scheduler, computed, reused")
    parameter_files: dict[str, str] = Field(default_factory=dict, description=(
        "a parameter that names a file (section.key, e.g. topple.boosted_map) -> SHA-256 of the content the build "
        "read: the file's name says nothing of what it held; empty when no parameter names a file, and before stop 66"))

    @field_validator("parameter_files")
    @classmethod
    def _files_name_parameters(cls, files: dict[str, str]) -> dict[str, str]:
        for name, digest in files.items():
            if name not in FILE_PARAMETERS:
                raise ValueError(f"{name!r} is no parameter that names a file ({', '.join(FILE_PARAMETERS)})")
            if not re.fullmatch(r"[0-9a-f]{64}", digest):
                raise ValueError(f"{name}: {digest!r} is no SHA-256 (64 hex digits)")
        return files

    def to_json(self) -> str:
        return json.dumps(self.model_dump(mode="json"), indent=1)

    def parameters_sha256(self) -> str:
        """SHA-256 of ``parameters`` as canonical JSON, each parameter of ``parameter_files`` taken as
        ``sha256:<its content's digest>``: equal digests, equal model, wherever its files lie and
        whatever was written to their names since (a manifest without files: the parameters alone)."""
        parameters = self.parameters.model_dump(mode="json")
        for name, digest in self.parameter_files.items():
            section, key = name.split(".", 1)
            parameters[section][key] = f"sha256:{digest}"
        return hashlib.sha256(json.dumps(parameters, sort_keys=True, separators=(",", ":")).encode()).hexdigest()

    def recorded_sha256(self, relative: str) -> str | None:
        """The SHA-256 this build recorded for a file (a consolidated table or a shard's file, by
        its path relative to the dataset), None when it recorded none."""
        if relative in self.tables:
            return self.tables[relative].sha256
        for shard in self.shards.values():
            if relative in shard.files:
                return shard.files[relative]
        return None


def read_manifest(root: str | Path, raw: bytes | None = None) -> Manifest:
    """The dataset's manifest; ``ManifestError`` with a one-line reason when the
    directory is missing, unfinished, unreadable, malformed or of another schema version.
    ``raw``: the file's bytes as the caller read them (and hashed them), parsed instead of reading it again."""
    root = Path(root)
    path = root / layout.MANIFEST
    try:
        if not root.is_dir():
            raise ManifestError(f"{root}: no such dataset directory")
        if not path.is_file():
            raise ManifestError(f"no {layout.MANIFEST} in {root}: not a dataset, or its build did not finish")
    except OSError as err:  # a directory on the way this user may not enter (Python 3.11 raises there)
        raise ManifestError(f"{root}: cannot be read ({err.strerror or err})") from None
    try:
        data = json.loads(path.read_bytes() if raw is None else raw)
    except (OSError, ValueError) as err:
        raise ManifestError(f"{path}: not valid JSON ({err})") from None
    version = data.get("schema_version") if isinstance(data, dict) else None
    if version != SCHEMA_VERSION:
        raise ManifestError(
            f"{root}: dataset schema version {version!r}, this code reads {SCHEMA_VERSION!r}; "
            "rebuild the dataset with this code (make dataset) or read it with the code that wrote it"
        )
    try:
        return Manifest.model_validate(data)
    except ValidationError as err:
        first = err.errors()[0]
        where = ".".join(str(part) for part in first["loc"])
        raise ManifestError(f"{path}: {where}: {first['msg']}") from None
