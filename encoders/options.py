"""Hyperparameters, each declared once: a typed field of a frozen dataclass with its bounds,
default and default search choices (thesis appendix A.1).

``hparam`` declares a field; ``Hyperparameters`` is the base of a dataclass of them, which
checks every field at construction. ``agent.config.SACConfig`` and the encoders' option
classes below are such dataclasses; the sweeper derives a spec's search spaces from them
(``sweeper.spec._space.search_space``), with the same types and bounds (``value_type``). This
module imports no torch: the sweep driver checks specs with it.

Adding a hyperparameter is one ``hparam`` field here (or in ``SACConfig``) plus its use.
"""

from __future__ import annotations

import dataclasses
import functools
import os
from collections.abc import Mapping
from dataclasses import MISSING, dataclass
from types import NoneType, UnionType
from typing import Annotated, Any, ClassVar, NamedTuple, Union, get_args, get_origin, get_type_hints

from pydantic import AfterValidator, Field, Strict, TypeAdapter, ValidationError
from pydantic_core import PydanticCustomError

#: the environment variable read when a spec or ``make_encoder`` omits vgg's ``weights_path``
VGG_WEIGHTS_ENV_VAR = "GCRL_VGG16_WEIGHTS"


@dataclass(frozen=True)
class Hyperparameter:
    """What a field declares besides its type and default (see ``hparam``)."""

    search: tuple[Any, ...] | None = None
    ge: float | None = None
    gt: float | None = None
    le: float | None = None
    one_of: tuple[Any, ...] | None = None
    env: str | None = None
    file: bool = False
    help: str = ""

    @property
    def choices(self) -> tuple[Any, ...] | None:
        """The declared default search choices, if any (``search``, else ``one_of``)."""
        return self.search if self.search is not None else self.one_of


def hparam(
    default: Any = MISSING,
    *,
    search: tuple[Any, ...] | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    one_of: tuple[Any, ...] | None = None,
    env: str | None = None,
    file: bool = False,
    help: str = "",
) -> Any:
    """A hyperparameter field: ``default`` (none: required), the default ``search`` choices
    of a study (none: ``one_of``, else the default alone), bounds ``ge``/``gt``/``le`` on
    numbers (on each item of a tuple), ``one_of`` the allowed values, ``env`` an
    environment variable read when the value is not given, ``file`` for a path that must
    exist where the trial runs, and ``help`` (shown in errors)."""
    info = Hyperparameter(search, ge, gt, le, one_of, env, file, help)
    return dataclasses.field(default=default, metadata={"hparam": info})


def _one_of(allowed: tuple[Any, ...]) -> AfterValidator:
    def check(value: Any) -> Any:
        if value not in allowed:
            raise PydanticCustomError("one_of", f"Input should be one of {allowed}")
        return value

    return AfterValidator(check)


def value_type(annotation: Any, info: Hyperparameter) -> Any:
    """The pydantic type of one value of a field: its annotation made strict (an integer
    refuses ``2.0``, ``"2"`` and ``true``; a float takes integers, not NaN or infinity),
    with the declared bounds; for ``tuple[int, ...]`` a non-empty tuple of bounded items."""
    if get_origin(annotation) in (Union, UnionType):
        (inner,) = (a for a in get_args(annotation) if a is not NoneType)
        return value_type(inner, info) | None
    if get_origin(annotation) is tuple:
        item = value_type(get_args(annotation)[0], info)
        return Annotated[tuple[item, ...], Field(min_length=1)]
    marks: list[Any] = [Strict()]
    if annotation in (int, float):
        marks.append(Field(ge=info.ge, gt=info.gt, le=info.le))
    if annotation is float:
        marks.append(Field(allow_inf_nan=False))
    if info.one_of is not None:
        marks.append(_one_of(info.one_of))
    return Annotated[(annotation, *marks)]


class Declared(NamedTuple):
    """One field of a dataclass of hyperparameters."""

    annotation: Any  # resolved: ``int``, ``tuple[int, ...]``, ``float | None``, ...
    default: Any  # ``dataclasses.MISSING``: required
    info: Hyperparameter


def hyperparameters(cls: type) -> dict[str, Declared]:
    """Field name -> its declaration, in field order."""
    hints = get_type_hints(cls)
    return {
        f.name: Declared(hints[f.name], f.default, f.metadata.get("hparam", Hyperparameter()))
        for f in dataclasses.fields(cls)
    }


def default_space(cls: type) -> dict[str, tuple[Any, ...]]:
    """The default search space of ``cls``: each field's declared choices, else its default
    alone (a required field without either is left out)."""
    space = {}
    for name, field in hyperparameters(cls).items():
        if field.info.choices is not None:
            space[name] = field.info.choices
        elif field.default is not MISSING:
            space[name] = (field.default,)
    return space


def with_env_fallbacks(cls: type, given: Mapping[str, Any]) -> dict[str, Any]:
    """``given`` and, for each field of ``cls`` it omits whose environment variable is set,
    the variable's value."""
    values = dict(given)
    for name, field in hyperparameters(cls).items():
        if name not in values and field.info.env and os.environ.get(field.info.env):
            values[name] = os.environ[field.info.env]
    return values


@functools.cache
def _adapters(cls: type) -> dict[str, TypeAdapter]:
    return {
        name: TypeAdapter(value_type(field.annotation, field.info))
        for name, field in hyperparameters(cls).items()
    }


@dataclass(frozen=True)
class Hyperparameters:
    """Base of a frozen dataclass of ``hparam`` fields: each field is checked against its
    type and bounds at construction (a ValueError names the field, after the class's
    ``prefix``, and the value) and stored as validated (lists become tuples, integers in
    float fields floats)."""

    #: what an error puts before the field's name (``"sac."``)
    prefix: ClassVar[str] = ""

    def __post_init__(self) -> None:
        for name, adapter in _adapters(type(self)).items():
            try:
                value = adapter.validate_python(getattr(self, name))
            except ValidationError as exc:
                err = exc.errors(include_url=False)[0]
                where = "".join(f"[{part}]" for part in err["loc"] if isinstance(part, int))
                must = err["msg"].replace("Input should be", "must be", 1)
                must = must if must.startswith("must be") else f"is invalid: {must}"
                raise ValueError(
                    f"{self.prefix}{name}{where} {must}, got {err['input']!r}"
                ) from None
            object.__setattr__(self, name, value)


def build_options(cls: type[Hyperparameters], given: Mapping[str, Any], name: str) -> Any:
    """``cls(**given)`` for encoder ``name``: an omitted field with an environment variable
    takes its value when set; a ValueError names an unknown, missing or bad option."""
    fields = hyperparameters(cls)
    unknown = sorted(set(given) - set(fields))
    if unknown:
        valid = ", ".join(fields) or "none"
        raise ValueError(f"encoder {name!r} has no option(s) {unknown}; valid options: {valid}")
    values = with_env_fallbacks(cls, given)
    for key, field in fields.items():
        if key not in values and field.default is MISSING:
            hint = f" or set ${field.info.env}" if field.info.env else ""
            raise ValueError(
                f"encoder {name!r} needs option {key} ({field.info.help}): give it{hint}"
            )
    try:
        return cls(**values)
    except ValueError as exc:
        raise ValueError(f"encoder {name!r} option {exc}") from None


# ---- the encoders' options ----------------------------------------------------------------


@dataclass(frozen=True)
class NoOptions(Hyperparameters):
    """An encoder without options (pixel)."""


@dataclass(frozen=True)
class LatentOptions(Hyperparameters):
    """The random projections (linear, conv)."""

    latent_dim: int = hparam(128, ge=1, search=(128, 256), help="size of the encoding")  # A.1


#: how CONV's random weights are drawn (``encoders.conv``)
CONV_INITS = ("drq", "pytorch")


@dataclass(frozen=True)
class ConvOptions(LatentOptions):
    """The random conv net (conv). LINEAR has no such choice: its one construction is the
    Gaussian projection of ``encoders.linear``."""

    # the thesis' CONV is "the same architecture used by all RL agents" (DrQ's), so it is
    # initialised as DrQ's agents initialise their encoder; PyTorch's default is kept for
    # comparison (its biases dominate the image signal after four ReLU layers)
    init: str = hparam(
        "drq",
        one_of=CONV_INITS,
        search=("drq",),
        help="weights: 'drq' (orthogonal, gain sqrt(2) on convs and 1 on the linear, zero "
        "biases: DrQ's weight_init) or 'pytorch' (PyTorch's default)",
    )


@dataclass(frozen=True)
class VAEOptions(Hyperparameters):
    """The beta-VAEs (vae, cvae)."""

    latent_dim: int = hparam(16, one_of=(8, 16), help="size of the encoding")  # A.1
    # from the plain VAE to the strong bottleneck RIG-style reward encoders use
    beta: float = hparam(1.0, gt=0, search=(1.0, 5.0, 20.0), help="weight of the KL term")
    lr: float = hparam(1e-3, gt=0, search=(1e-3, 3e-4), help="Adam's learning rate")
    # a short and a long pre-training; the trial pays for both before SAC starts
    epochs: int = hparam(20, ge=1, search=(10, 30), help="passes over the images")
    num_images: int = hparam(
        2000, ge=1, search=(1000, 5000), help="random-policy frames the VAE is fit on"
    )
    batch_size: int = hparam(64, ge=1, help="images per Adam step")


@dataclass(frozen=True)
class VGGOptions(Hyperparameters):
    """ImageNet VGG16 features (vgg); the weights file is local, never downloaded."""

    weights_path: str = hparam(
        env=VGG_WEIGHTS_ENV_VAR,
        file=True,
        help="VGG16 ImageNet weights in torchvision format, vgg16-397923af.pth",
    )
    input_size: int = hparam(224, ge=32, help="pixels per side the image is resized to")
