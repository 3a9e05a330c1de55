"""The search spaces of a spec, derived from the hyperparameter declarations, and its methods.

``search_space(config)`` turns a dataclass of ``encoders.options.hparam`` fields (an
encoder's options, ``agent.config.SACConfig``) into a pydantic model whose fields are
tuples of distinct choices (a scalar is one choice), with the declared types, bounds,
defaults and environment-variable fallbacks. ``parse_method`` validates one entry of a
spec's ``methods`` (an encoder, a true-reward control or a named variant) into a
``Method``: its encoder and its full search space. ``StrictModel`` is the base of every
spec model: frozen, unknown keys rejected with a close name, no NaN/inf.
"""

from __future__ import annotations

import functools
import re
from typing import Annotated, Any, ClassVar, get_origin

from pydantic import (
    AfterValidator,
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    ValidationError,
    create_model,
    model_validator,
)

from agent.config import TRUE_REWARD_METHODS, SACConfig
from encoders import encoder_names, encoder_options
from encoders.options import (
    Hyperparameter,
    NoOptions,
    default_space,
    hyperparameters,
    value_type,
    with_env_fallbacks,
)
from sweeper.spec._errors import excerpt, format_errors, spec_error, suggest


def as_choices(value: Any) -> Any:
    """A scalar is a one-choice list; an empty list is an empty search space."""
    if isinstance(value, list | tuple):
        if not value:
            raise spec_error("empty search space: give a value or a non-empty list of choices")
        return value
    return [value]


def as_size_choices(value: Any) -> Any:
    """``[256, 256]`` is one choice of layer sizes; ``[[256, 256], [512, 512]]`` two."""
    if isinstance(value, list | tuple) and value and all(isinstance(v, int) for v in value):
        return [value]
    return as_choices(value)


def distinct(choices: tuple[Any, ...]) -> tuple[Any, ...]:
    """The choices, unchanged, if no two are equal (a repeated one would weigh double)."""
    if len(set(choices)) != len(choices):
        raise spec_error(f"choices must be distinct, got {excerpt(list(choices))}")
    return choices


class StrictModel(BaseModel):
    """Frozen, no unknown keys (reported with a close name), no NaN/inf."""

    model_config = ConfigDict(frozen=True, extra="forbid", allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _no_unknown_keys(cls, data: Any) -> Any:
        if isinstance(data, dict):
            allowed = list(cls.model_fields)
            for key in data:
                if key not in cls.model_fields:
                    raise spec_error(
                        f"unknown field; {suggest(key, allowed)}"
                        f"allowed: {', '.join(allowed) or 'none'}",
                        at=str(key),
                    )
        return data


class SearchSpace(StrictModel):
    """A search space derived by ``search_space`` from a dataclass of hyperparameters
    (``encoders.options.hparam`` fields): each field a tuple of distinct choices."""

    #: the dataclass this space was derived from
    hyperparameters: ClassVar[type] = NoOptions

    @model_validator(mode="before")
    @classmethod
    def _env_fallbacks(cls, data: Any) -> Any:
        """An omitted field with an environment variable takes its value when set; the value
        is written into the spec, so workers on other machines need not have it set."""
        return with_env_fallbacks(cls.hyperparameters, data) if isinstance(data, dict) else data

    def space(self) -> dict[str, tuple[Any, ...]]:
        """Field name -> choices, in the dataclass's field order; a file option given no
        value (``search_space``) is left out."""
        space = {name: getattr(self, name) for name in type(self).model_fields}
        return {name: choices for name, choices in space.items() if choices != ()}


@functools.cache
def search_space(config: type) -> type[SearchSpace]:
    """The search-space model of ``config``, a dataclass of ``hparam`` fields: one field per
    hyperparameter, a value or a non-empty list of distinct choices of the field's type and
    bounds (``encoders.options.value_type``), defaulting to its declared search choices, else
    its default; a field with neither (nor a set environment variable) is required, except
    a file (``hparam(file=True)``): only the trials need it, so a spec without it still
    reads (``sweeper status``, ``plan``, ``aggregate``); ``StudySpec.missing_files`` says
    what a launch lacks."""
    defaults = default_space(config)
    fields: dict[str, Any] = {}
    for name, (annotation, _, info) in hyperparameters(config).items():
        item = value_type(annotation, info)
        convert = as_size_choices if get_origin(annotation) is tuple else as_choices
        choices = Annotated[tuple[item, ...], BeforeValidator(convert), AfterValidator(distinct)]
        default = defaults.get(name, () if info.file else ...)  # (): no value, left out
        fields[name] = (choices, Field(default, description=describe(info) or None))
    model = create_model(f"{config.__name__}Space", __base__=SearchSpace, **fields)
    model.hyperparameters = config
    return model


def describe(info: Hyperparameter) -> str:
    """What a hyperparameter is, as errors say it: its help and its environment variable."""
    return info.help + (f" (or set ${info.env})" if info.env else "")


def method_names() -> tuple[str, ...]:
    """Methods a spec may name: the encoder registry's names and the true-reward controls
    (``agent.config.TRUE_REWARD_METHODS``: the state oracle and the image control)."""
    return (*encoder_names(), *TRUE_REWARD_METHODS)


def method_options(name: str) -> type:
    """The options dataclass of method ``name`` (the true-reward controls have none)."""
    return NoOptions if name in TRUE_REWARD_METHODS else encoder_options(name)


#: a variant's name: it becomes the first part of trial keys and of "<method>.<option>"
#: params, so no "/" or "."; "confirm" starts the confirmation stage's keys
_VARIANT_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,63}$")


class Method(BaseModel):
    """One method of a study: the ``encoder`` it runs (an encoder registry name, or a
    true-reward control) and its full search space (``space``: option -> choices).

    A method named after its encoder is the usual case (``conv: {latent_dim: 128}``); a
    named variant gives its encoder (``conv_pytorch_init: {encoder: conv, init: pytorch}``),
    so one study can hold several variants of one encoder. ``sac`` fixes SAC fields for
    this method only (``pixel_b128: {encoder: pixel, sac: {batch_size: 128}}``): the value
    replaces that field of every configuration the study samples; the other fields keep
    their samples, so the method stays paired with the others.
    """

    model_config = ConfigDict(frozen=True)

    encoder: str
    space: dict[str, tuple[Any, ...]]
    sac: dict[str, Any] = {}


def parse_sac_overrides(name: str, given: Any) -> dict[str, Any]:
    """The SAC fields method ``name`` fixes (``methods.<name>.sac``): a mapping of SAC
    field names to one value each, validated as the study's ``sac`` fields are."""
    if not isinstance(given, dict) or not given:
        raise spec_error(
            f"must be a mapping of SAC fields to one value each, e.g. {{batch_size: 128}}, "
            f"got {excerpt(given)}",
            at=f"{name}.sac",
        )
    model = search_space(SACConfig)
    fixed = {}
    for key, value in given.items():
        key = str(key)
        if key not in model.model_fields:
            allowed = list(model.model_fields)
            raise spec_error(
                f"unknown SAC field; {suggest(key, allowed)}allowed: {', '.join(allowed)}",
                at=f"{name}.sac.{key}",
            )
        try:
            (choice, *more) = getattr(model.model_validate({key: value}), key)
        except ValidationError as exc:
            _, message = format_errors(exc, model)[0]
            raise spec_error(message, at=f"{name}.sac.{key}") from None
        if more:
            raise spec_error(
                f"a method fixes one value (the study's sac.{key} is what is sampled), "
                f"got {excerpt(value)}",
                at=f"{name}.sac.{key}",
            )
        fixed[key] = choice
    return fixed


def parse_method(name: str, options: Any) -> Method:
    """Method ``name`` of a spec: its encoder (``options["encoder"]``, else the name) and
    its search space, the encoder's declared defaults with the spec's ``options`` on top."""
    if options is None:
        options = {}
    if not isinstance(options, dict):
        raise spec_error(
            f"must be a mapping of options (or {{}} for the defaults), got {excerpt(options)}",
            at=name,
        )
    options = dict(options)
    allowed = method_names()
    encoder = options.pop("encoder", name)
    sac = parse_sac_overrides(name, options.pop("sac")) if "sac" in options else {}
    if encoder != name:
        if not isinstance(encoder, str) or encoder not in encoder_names():
            raise spec_error(
                f"a variant's encoder must be an encoder name; "
                f"{suggest(encoder, list(encoder_names()))}allowed: {', '.join(encoder_names())}"
                f"; got {excerpt(encoder)}",
                at=f"{name}.encoder",
            )
        if name in allowed:
            raise spec_error(
                f"{name!r} is a method of its own: name the variant of {encoder!r} otherwise "
                f"(e.g. {encoder}_{name})",
                at=name,
            )
        if not _VARIANT_RE.match(name) or name == "confirm":
            raise spec_error(
                "a variant's name must be a letter, then letters, digits, '_' or '-' (at most "
                f"64 characters, not 'confirm'), got {excerpt(name)}",
                at=name,
            )
    elif name not in allowed:
        raise spec_error(
            f"unknown method; {suggest(name, list(allowed))}allowed: {', '.join(allowed)}, "
            f"or a named variant of an encoder ({name}: {{encoder: conv, ...}})",
            at=name,
        )
    model = search_space(method_options(encoder))
    try:
        space = model.model_validate(options).space()
    except ValidationError as exc:
        path, message = format_errors(exc, model)[0]
        raise spec_error(message, at=f"{name}.{path}") from None
    return Method(encoder=encoder, space=space, sac=sac)
