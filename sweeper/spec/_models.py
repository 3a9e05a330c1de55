"""Study specs: the schema of a spec, and reading a YAML file into a frozen ``StudySpec``.

This module's one job is the schema: the pydantic models of a spec (``EnvSpec``,
``SACSpace``, ``Budget``, ``Execution``, ``ConfirmSpec``, ``Halving``, ``StudySpec``),
documented field by field below (and in ``studies/*.yaml``), with the checks that tie
fields together.
``load_spec(path)`` reads and validates a spec; any problem raises ``SpecError`` whose
message names the dotted field (``sac.lr[1]``, ``methods.vae.beta``), what is allowed, and
a close name for a typo.

YAML is read by ``sweeper.spec._yaml.load_yaml`` (YAML 1.2 core scalars, no duplicate keys);
the search spaces and methods are derived from the hyperparameter declarations by
``sweeper.spec._space``; validation errors are made and formatted by ``sweeper.spec._errors``.

Numbers are then validated strictly: an integer field refuses ``2.0``, ``"2"`` and ``true``;
a float field accepts integers.
"""

from __future__ import annotations

import argparse
import inspect
import math
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple

from pydantic import (
    AfterValidator,
    BeforeValidator,
    Field,
    PlainValidator,
    Strict,
    ValidationError,
    field_serializer,
    field_validator,
    model_validator,
)

from agent.config import EPISODE_STEPS, PRECISIONS, SACConfig
from encoders.options import hyperparameters
from sweeper.spec._errors import excerpt, format_errors, spec_error, suggest
from sweeper.spec._space import (
    Method,
    StrictModel,
    as_choices,
    describe,
    distinct,
    method_names,
    method_options,
    parse_method,
    search_space,
)
from sweeper.spec._words import plural
from sweeper.spec._yaml import SpecError, load_yaml

_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]+$")

#: limits that keep every input within what the filesystem, the database and this
#: machine hold: a study name is a path component (``<study>-<16 hex>`` checkpoint folders,
#: 255 bytes at most); a trial's curve is held in memory and stored as one JSON attr; the
#: plan is built and synced whole; a spec is a few kB of YAML
MAX_STUDY_NAME = 128
MAX_ENV_STEPS = 10**9
MAX_GRID_POINTS = 10_000
MAX_PLAN_KEYS = 20_000
MAX_SPEC_BYTES = 1 << 20
#: the most errors a SpecError's message lists (its ``errors`` holds them all)
MAX_ERRORS = 5
_URL_RE = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")


# ---- value types ---------------------------------------------------------------------------


PosInt = Annotated[int, Strict(), Field(ge=1)]
NonNegInt = Annotated[int, Strict(), Field(ge=0)]
SeedInt = Annotated[int, Strict(), Field(ge=0, le=2**32 - 1)]
#: the seeds of a study: one seed or a list of distinct ones
SeedChoices = Annotated[tuple[SeedInt, ...], BeforeValidator(as_choices), AfterValidator(distinct)]
PosFloat = Annotated[float, Strict(), Field(gt=0)]
NonNegFloat = Annotated[float, Strict(), Field(ge=0)]


def _reward_scale(value: Any) -> str | float:
    if value == "auto":
        return value
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < math.inf:
        raise spec_error(f"must be 'auto' or a positive number, got {excerpt(value)}")
    return float(value)


RewardScale = Annotated[str | float, PlainValidator(_reward_scale)]


def _video_steps(value: Any) -> str | tuple[int, ...]:
    if value in ("last", "none"):
        return value
    steps = value if isinstance(value, list | tuple) else [value]
    for step in steps:
        if isinstance(step, bool) or not isinstance(step, int) or step < 0:
            raise spec_error(
                f"must be 'last', 'none' or a list of env steps >= 0, got {excerpt(value)}"
            )
    return tuple(sorted(set(steps)))


def _check_env_option(value: Any, like: Any, at: str) -> None:
    """Check an env option against the type of its default ``like`` (``None`` or no
    default: any scalar)."""
    kind = type(like) if isinstance(like, bool | int | float | str) else None
    if kind is bool:
        ok, what = isinstance(value, bool), "true or false"
    elif kind is int:
        ok, what = isinstance(value, int) and not isinstance(value, bool), "an integer"
    elif kind is float:
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        ok, what = ok and math.isfinite(value), "a finite number"
    elif kind is str:
        ok, what = isinstance(value, str), "a string"
    else:
        ok, what = isinstance(value, bool | int | float | str), "a string, number or boolean"
    if not ok:
        raise spec_error(f"must be {what}, got {excerpt(value)}", at=at)


# ---- the spec -------------------------------------------------------------------------------


class EnvSpec(StrictModel):
    """The environment every trial runs in."""

    name: str = Field(description="an env name from agent.envs.ENV_NAMES")
    image_size: PosInt | None = Field(None, description="pixels per side; null: the env default")
    options: dict[str, Any] = Field(
        default_factory=dict, description="extra keyword arguments of the env's constructor"
    )

    @field_validator("name")
    @classmethod
    def _known_env(cls, name: str) -> str:
        from agent.envs import ENV_NAMES

        if name not in ENV_NAMES:
            raise spec_error(
                f"unknown env {name!r}; {suggest(name, list(ENV_NAMES))}"
                f"allowed: {', '.join(ENV_NAMES)}"
            )
        return name

    @model_validator(mode="after")
    def _fits_env_class(self) -> EnvSpec:
        """Check image_size and options against the env class (imported only when needed)."""
        if self.image_size is None and not self.options:
            return self
        from agent.envs import env_class as load_env_class

        try:
            env_class = load_env_class(self.name)
        except Exception as exc:  # an env module that is missing or broken
            raise spec_error(f"env {self.name!r} cannot be loaded: {exc}", at="name") from None
        if self.image_size is not None:
            low, high = env_class.min_image_size, 256
            if not low <= self.image_size <= high:
                raise spec_error(
                    f"must be in [{low}, {high}] for {self.name}, got {self.image_size}",
                    at="image_size",
                )
        reserved = {"self", "image_size", "obs_mode", "render_mode"}
        accepted = {
            p.name: p.default
            for p in inspect.signature(env_class.__init__).parameters.values()
            if p.name not in reserved and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)
        }
        for key, value in self.options.items():
            if key not in accepted:
                hint = " (set by the sweeper)" if key in reserved else ""
                raise spec_error(
                    f"unknown option of env {self.name!r}{hint}; "
                    f"{suggest(key, list(accepted))}allowed: {', '.join(accepted) or 'none'}",
                    at=f"options.{key}",
                )
            _check_env_option(value, accepted[key], at=f"options.{key}")
        return self


class SACSpace(search_space(SACConfig)):
    """The SAC search space, derived from ``agent.config.SACConfig``; defaults: A.1."""

    @model_validator(mode="after")
    def _batch_fits_buffer(self) -> SACSpace:
        if max(self.batch_size) > min(self.buffer_capacity):
            raise spec_error(
                f"every batch_size must be <= every buffer_capacity, got batch_size "
                f"{max(self.batch_size)} > buffer_capacity {min(self.buffer_capacity)}",
                at="batch_size",
            )
        return self


class Budget(StrictModel):
    """What one trial runs: env steps and the evaluation grid 0, eval_every, ..., env_steps."""

    env_steps: Annotated[int, Strict(), Field(ge=1, le=MAX_ENV_STEPS)] = Field(
        description=f"env steps per trial, an integer in [1, {MAX_ENV_STEPS:.0e}]"
    )
    seed_steps: NonNegInt = Field(1000, description="random-action steps before learning")
    eval_every: PosInt = Field(1000, description="env steps between evaluations")
    eval_episodes: PosInt = Field(10, description="episodes per evaluation")

    @model_validator(mode="after")
    def _grid(self) -> Budget:
        points = self.env_steps // self.eval_every
        if points > MAX_GRID_POINTS:
            raise spec_error(
                f"gives {points} evaluations per trial (env_steps / eval_every), more than "
                f"the {MAX_GRID_POINTS} a trial's curve may hold: evaluate less often",
                at="eval_every",
            )
        if self.env_steps % self.eval_every:
            raise spec_error(
                f"must divide env_steps ({self.env_steps}) so the grid ends at env_steps, "
                f"got {self.eval_every}",
                at="eval_every",
            )
        if self.seed_steps >= self.env_steps:
            raise spec_error(
                f"must be < env_steps ({self.env_steps}), got {self.seed_steps}", at="seed_steps"
            )
        return self


class Execution(StrictModel):
    """Where and how trials run."""

    address: str | None = Field(None, description="a Ray address; null: a local Ray instance")
    max_concurrent: PosInt = Field(2, description="trials at once, an integer >= 1")
    cpus_per_trial: PosFloat = 1.0
    gpus_per_trial: NonNegFloat = 0.0
    threads_per_trial: PosInt = 1
    retries: NonNegInt = Field(2, description="re-runs of a trial whose worker died")
    checkpoint_every: PosInt = Field(5000, description="env steps between checkpoints")
    stall_timeout: PosFloat = Field(
        600.0,
        description="seconds a busy worker may go without answering (a stopped process or "
        "node) before its trial is retried from its checkpoint as a dead worker's",
    )
    keep_checkpoints: bool = Field(
        False, description="keep a finished trial's checkpoint (false: removed once recorded)"
    )
    storage_grace: NonNegFloat = Field(
        60.0,
        description="seconds the driver retries a database write while the database is "
        "unreachable, before it stops (the trials in flight resume at the next launch)",
    )

    @field_validator("address")
    @classmethod
    def _address(cls, address: str | None) -> str | None:
        if address is not None and not address.strip():
            raise spec_error("must be a Ray address such as 'auto' or 'ray://host:10001', or null")
        return address


class ConfirmSpec(StrictModel):
    """The confirmation stage (``sweeper confirm``): against the winner's curse."""

    top_k: PosInt = Field(description="configurations per method re-run, best search AUC first")
    seeds: PosInt = Field(description="fresh seeds (not the search's) each one runs on")


#: the default: keep a third at rungs at a ninth and a third of the budget (halving with
#: eta = 3, Li et al. 2018's Hyperband bracket with three rungs)
DEFAULT_KEEP = 1 / 3
DEFAULT_RUNG_FRACTIONS = (1 / 9, 1 / 3)


def rungs_at(
    fractions: Sequence[float], env_steps: int, grid: int, seed_steps: int = 0
) -> tuple[int, ...]:
    """Rungs at ``fractions`` of ``env_steps``, each rounded down to a multiple of ``grid``
    (where a trial can pause) and at least the first multiple past ``seed_steps`` (before it
    the agents have not learned: a decision there is one among random policies); those
    that reach the budget are dropped, and repeats."""
    first = (seed_steps // grid + 1) * grid
    steps = [max(int(env_steps * fraction) // grid * grid, first) for fraction in fractions]
    return tuple(dict.fromkeys(step for step in steps if step < env_steps))


def default_rungs(env_steps: int, grid: int, seed_steps: int = 0) -> tuple[int, ...]:
    """The default rungs of a budget: ``rungs_at(DEFAULT_RUNG_FRACTIONS, ...)``."""
    return rungs_at(DEFAULT_RUNG_FRACTIONS, env_steps, grid, seed_steps)


class Halving(StrictModel):
    """Paired successive halving (``sweeper.plan._halving``): every method runs all its
    configurations to the first rung; at each rung ``keep`` of them (rounded up) go on,
    chosen by ``rule``, the same number for every method."""

    rungs: tuple[PosInt, ...] | None = Field(
        None,
        description="env steps where trials pause, increasing, on the evaluation grid and "
        "episode ends, past budget.seed_steps and below budget.env_steps; null: 1/9 and 1/3 "
        "of env_steps, none inside the seed phase",
    )
    keep: float = Field(DEFAULT_KEEP, gt=0, lt=1, description="the fraction that goes on")
    rule: Literal["per_method", "mean_rank"] = Field(
        "per_method",
        description="per_method: each method keeps its own best configurations; mean_rank: "
        "all keep those of the best mean rank over the methods (paired at every rung)",
    )


class StudySpec(StrictModel):
    """A whole study: what runs (env, methods, search space, budget) and where."""

    study: str = Field(description="the study name: letters, digits, '_', '.', '-'")
    seed: SeedInt = Field(0, description="samples the plan")
    env: EnvSpec = Field(description="a mapping with name (required), image_size, options")
    methods: dict[str, Any] = Field(
        description="a mapping from method names (encoder names, the controls 'true_reward' "
        "and 'state', or a variant's name with its 'encoder') to their options"
    )
    trials_per_method: PosInt = Field(description="K >= 1 SAC configurations shared by all methods")
    seeds: SeedChoices = (0,)
    sac: SACSpace = SACSpace()
    reward_scale: RewardScale = Field(
        "auto",
        description="'auto' (each trial's reward divided by its mean random-policy distance to "
        "the goal, so every method's reward is about 1) or a positive factor",
    )
    budget: Budget = Field(description="a mapping with env_steps (required), seed_steps, ...")
    precision: Literal[PRECISIONS] = Field(
        "fp32",
        description="the SAC update's and acting's precision: fp32, or bf16 autocast (weights, "
        "optimiser state, targets and rewards stay fp32); fast on CPUs with AMX or "
        "AVX512-BF16 and on recent GPUs, slow elsewhere",
    )
    random_episodes: NonNegInt = Field(
        100,
        description="episodes of a uniformly random agent the driver runs once per study, "
        "before its first trial, on the spec's env: its success rate is the 0 of the "
        "normalised scores (0: not measured, the study is not normalised)",
    )
    confirm: ConfirmSpec | None = Field(
        None, description="top_k and seeds of `sweeper confirm` (its flags override them)"
    )
    storage: str | None = Field(None, description="an SQLAlchemy URL; null: SQLite under runs/")
    checkpoints: str | None = Field(None, description="checkpoint directory; null: under runs/")
    videos: Annotated[str | tuple[NonNegInt, ...], PlainValidator(_video_steps)] = Field(
        "last",
        description="evaluation steps whose first episode each trial films (observation "
        "beside goal): 'last' (the final evaluation), 'none', or a list of env steps on the "
        "evaluation grid",
    )
    artifacts: str | None = Field(
        None,
        description="where episode videos are stored (an Optuna artifact store): a directory "
        "or an fsspec URI such as s3://bucket/prefix; null: artifacts/ beside the SQLite "
        "database, or runs/<study>/artifacts",
    )
    execution: Execution = Execution()
    halving: Halving | None = Field(
        None, description="paired successive halving: rungs, keep, rule; null: none"
    )

    @field_validator("study")
    @classmethod
    def _study_name(cls, study: str) -> str:
        if len(study) > MAX_STUDY_NAME:
            raise spec_error(
                f"must be at most {MAX_STUDY_NAME} characters (it names files and folders), "
                f"got {len(study)}"
            )
        if not _NAME_RE.match(study) or study.startswith("."):
            raise spec_error(
                "must be letters, digits, '_', '.', '-' (not starting with '.'), "
                f"got {excerpt(study)}"
            )
        return study

    @field_validator("methods")
    @classmethod
    def _methods(cls, methods: dict[str, Any]) -> dict[str, Method]:
        if not methods:
            raise spec_error(
                f"at least one method is required; allowed: {', '.join(method_names())}"
            )
        return {str(name): parse_method(str(name), options) for name, options in methods.items()}

    @field_serializer("methods")
    def _methods_as_written(self, methods: dict[str, Method]) -> dict[str, dict[str, Any]]:
        """Each method as a spec writes it (a variant with its ``encoder``), so a dumped
        spec parses back to the same spec."""
        return {
            name: ({} if m.encoder == name else {"encoder": m.encoder})
            | m.space
            | ({"sac": dict(m.sac)} if m.sac else {})
            for name, m in methods.items()
        }

    @field_validator("storage")
    @classmethod
    def _storage_url(cls, storage: str | None) -> str | None:
        if storage is not None and not _URL_RE.match(storage):
            raise spec_error(
                "must be an SQLAlchemy URL such as sqlite:///runs/study.db or "
                f"postgresql+psycopg://user@host/db, or null; got {excerpt(storage)}"
            )
        return storage

    @model_validator(mode="after")
    def _method_batch_fits_buffer(self) -> StudySpec:
        for name, method in self.methods.items():
            if not method.sac:
                continue
            batch = method.sac.get("batch_size", max(self.sac.batch_size))
            capacity = method.sac.get("buffer_capacity", min(self.sac.buffer_capacity))
            if batch > capacity:
                raise spec_error(
                    f"batch_size {batch} > buffer_capacity {capacity} for this method",
                    at=f"methods.{name}.sac.batch_size",
                )
        return self

    @model_validator(mode="after")
    def _plan_size(self) -> StudySpec:
        keys = len(self.methods) * self.trials_per_method_total
        if keys > MAX_PLAN_KEYS:
            raise spec_error(
                f"{plural(len(self.methods), 'method')} x "
                f"{plural(self.trials_per_method, 'configuration')} x "
                f"{plural(len(self.seeds), 'seed')} = {keys} trials, more than the "
                f"{MAX_PLAN_KEYS} a plan may hold: split the study",
                at="trials_per_method",
            )
        return self

    @model_validator(mode="after")
    def _rungs_on_grid(self) -> StudySpec:
        if self.halving is None:
            return self
        budget, rungs = self.budget, self.rungs
        if not rungs:
            raise spec_error(
                f"budget.env_steps={budget.env_steps} is too short for the default rungs "
                "(1/9 and 1/3 of it on the evaluation grid): give halving.rungs",
                at="halving.rungs",
            )
        grid = math.lcm(budget.eval_every, EPISODE_STEPS)
        for step in rungs:
            if step % grid or not budget.seed_steps < step < budget.env_steps:
                raise spec_error(
                    f"{step} is not a rung: rungs are multiples of budget.eval_every="
                    f"{budget.eval_every} and of the episode length {EPISODE_STEPS}, past "
                    f"budget.seed_steps={budget.seed_steps} and below budget.env_steps="
                    f"{budget.env_steps}",
                    at="halving.rungs",
                )
        if list(rungs) != sorted(set(rungs)):
            raise spec_error(
                f"must increase strictly, got {excerpt(list(rungs))}", at="halving.rungs"
            )
        return self

    @property
    def rungs(self) -> tuple[int, ...]:
        """The halving rungs (the given ones, else ``default_rungs``); empty
        without halving."""
        if self.halving is None:
            return ()
        if self.halving.rungs is not None:
            return self.halving.rungs
        budget = self.budget
        grid = math.lcm(budget.eval_every, EPISODE_STEPS)
        return default_rungs(budget.env_steps, grid, budget.seed_steps)

    @model_validator(mode="after")
    def _videos_on_grid(self) -> StudySpec:
        budget = self.budget
        for step in self.video_steps:
            if step % budget.eval_every or step > budget.env_steps:
                raise spec_error(
                    f"{step} is not an evaluation step (a multiple of budget.eval_every="
                    f"{budget.eval_every} up to budget.env_steps={budget.env_steps})",
                    at="videos",
                )
        return self

    @property
    def video_steps(self) -> tuple[int, ...]:
        """The env steps at which each trial films an evaluation episode."""
        if self.videos == "last":
            return (self.budget.env_steps,)
        return () if self.videos == "none" else self.videos

    def missing_files(self) -> tuple[MissingFile, ...]:
        """The files the trials need that this launch cannot give them: a file option
        (``hparam(file=True)``, e.g. vgg's ``weights_path``) with no value and no environment
        variable set, or, on a local run (no ``execution.address``: on a cluster the file
        lives on the workers), a path that is not a file here. Only a launch needs them
        (``check_files``); the spec reads without them."""
        missing = []
        for method_name, method in self.methods.items():
            for name, field in hyperparameters(method_options(method.encoder)).items():
                if not field.info.file:
                    continue
                at = f"methods.{method_name}.{name}"
                if name not in method.space:
                    message = f"required field is missing; {describe(field.info)}"
                    missing.append(MissingFile(method_name, at, message, unset=True))
                    continue
                absent = [p for p in method.space[name] if not Path(p).expanduser().is_file()]
                if absent and self.execution.address is None:
                    message = f"file not found: {absent[0]!r} ({field.info.help})"
                    missing.append(MissingFile(method_name, at, message, unset=False))
        return tuple(missing)

    @property
    def run_dir(self) -> Path:
        """``runs/<study>`` (relative to the working directory)."""
        return Path("runs") / self.study

    @property
    def storage_url(self) -> str:
        """The study's storage: the spec's URL, or SQLite at ``runs/<study>/study.db``."""
        return self.storage or f"sqlite:///{self.run_dir / 'study.db'}"

    @property
    def checkpoint_dir(self) -> str:
        """The checkpoint root: the spec's ``checkpoints`` or ``runs/<study>/checkpoints``."""
        return self.checkpoints or str(self.run_dir / "checkpoints")

    @property
    def trials_per_method_total(self) -> int:
        """Counted trials per method: K configurations x the seeds."""
        return self.trials_per_method * len(self.seeds)

    def with_overrides(
        self,
        storage: str | None = None,
        address: str | None = None,
        max_concurrent: int | None = None,
        threads_per_trial: int | None = None,
    ) -> StudySpec:
        """A copy with CLI overrides (None keeps the spec's value), validated again; the spec
        itself when there are none.
        ``threads_per_trial`` also reserves that many CPUs a trial (``cpus_per_trial``, if
        fewer): each thread needs a core, and Ray then never puts two trials on one."""
        if (storage, address, max_concurrent, threads_per_trial) == (None, None, None, None):
            return self
        data = self.model_dump(mode="json")
        execution = data["execution"]
        if storage is not None:
            data["storage"] = storage
        if address is not None:
            execution["address"] = address
        if max_concurrent is not None:
            execution["max_concurrent"] = max_concurrent
        if threads_per_trial is not None:
            execution["threads_per_trial"] = threads_per_trial
            execution["cpus_per_trial"] = max(execution["cpus_per_trial"], threads_per_trial)
        return parse_spec(data, source="override")


class MissingFile(NamedTuple):
    """A file a method's trials need and this launch lacks (``StudySpec.missing_files``)."""

    method: str
    at: str  # the dotted field, "methods.vgg.weights_path"
    message: str  # "required field is missing; ..." or "file not found: ..."
    unset: bool  # no value at all (else a path that is not a file here)


def check_files(
    spec: StudySpec, source: str, skip_missing: bool = False, can_skip: bool = True
) -> frozenset[str]:
    """Where trials run (``sweeper launch``, ``sweeper confirm``): raise ``SpecError``, one
    line naming the field (and ``--skip-missing`` where the command ``can_skip``), when a
    method lacks a file its trials need; with ``skip_missing``, return those methods
    instead, to be left out of this launch. A file option with no value cannot be skipped:
    its path is part of the plan (and its hash), so it must be named now for the skipped
    trials to run later in the same study."""
    missing = spec.missing_files()
    if not skip_missing:
        if missing:
            first = missing[0]
            hint = f"; or --skip-missing to launch without {first.method}" if can_skip else ""
            raise SpecError(f"{source}: {first.at}: {first.message}{hint}")
        return frozenset()
    for item in missing:
        if item.unset:
            raise SpecError(
                f"{source}: {item.at}: required field is missing; --skip-missing needs the "
                "path the file will have (it is part of the plan, so the skipped trials can "
                "run later in this study): give it in the spec or set its variable, "
                f"{item.message.split('; ', 1)[1]}"
            )
    return frozenset(item.method for item in missing)


# ---- loading -----------------------------------------------------------------------------------


def parse_spec(data: Any, source: str = "spec") -> StudySpec:
    """Validate an already-parsed spec (a dict); raise ``SpecError`` naming every problem."""
    if not isinstance(data, dict):
        raise SpecError(
            f"{source}: a spec must be a mapping of fields (study, env, methods, "
            f"trials_per_method, budget, ...), got {type(data).__name__}"
        )
    try:
        return StudySpec.model_validate(data)
    except ValidationError as exc:
        errors = format_errors(exc, StudySpec)
        detail = "; ".join(f"{path}: {message}" for path, message in errors[:MAX_ERRORS])
        if len(errors) > MAX_ERRORS:  # a list of thousands of bad values: a line, not pages
            detail += f"; and {len(errors) - MAX_ERRORS} more errors"
        raise SpecError(f"{source}: {detail}", errors) from None


def load_spec(path: str | os.PathLike[str]) -> StudySpec:
    """Read and validate a YAML study spec; raise ``SpecError`` on any problem."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_SPEC_BYTES:
            raise SpecError(
                f"{path}: a spec file must be at most {MAX_SPEC_BYTES >> 20} MiB, got "
                f"{path.stat().st_size / 2**20:.1f} MiB"
            )
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)
        raise SpecError(f"{path}: cannot read the spec file: {reason}") from None
    try:
        data = load_yaml(text)
    except SpecError as exc:
        raise SpecError(f"{path}: {exc}") from None
    return parse_spec(data, source=str(path))


def positive_int(text: str) -> int:
    """An argparse type for the counts a launch takes (``--max-concurrent``; ``sweeper
    confirm``'s ``--top-k`` and ``--seeds``): an integer >= 1."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be an integer >= 1, got {value}")
    return value
