"""Reward encoders by name.

``make_encoder("conv", image_shape=(48, 48, 3), seed=0, latent_dim=128)`` builds one;
``encoder_names()`` lists them. The registry imports an encoder's module on first use and
names each encoder's options class (``encoders.options``, no torch), so checking a spec
(``encoder_options``) imports no torch: the sweep driver never needs it.
"""

from __future__ import annotations

import difflib
import importlib
from dataclasses import dataclass
from typing import Any

from encoders.base import RewardEncoder
from encoders.options import (
    ConvOptions,
    Hyperparameters,
    LatentOptions,
    NoOptions,
    VAEOptions,
    VGGOptions,
    build_options,
)


@dataclass(frozen=True)
class _Entry:
    entry_point: str  # "module:Class"
    options: type[Hyperparameters]  # the class's options, handed to it as ``options``


_REGISTRY: dict[str, _Entry] = {
    "pixel": _Entry("encoders.pixel:PixelEncoder", NoOptions),
    "linear": _Entry("encoders.linear:LinearEncoder", LatentOptions),
    "conv": _Entry("encoders.conv:ConvEncoder", ConvOptions),
    "vae": _Entry("encoders.vae:VAEEncoder", VAEOptions),
    "cvae": _Entry("encoders.vae:CVAEEncoder", VAEOptions),
    "vgg": _Entry("encoders.vgg:VGGEncoder", VGGOptions),
}


def register(name: str, entry_point: str, options: type[Hyperparameters] = NoOptions) -> None:
    """Register an encoder class under ``name`` ("module:Class"); it is built as
    ``cls(image_shape, seed, device, options)`` with an instance of ``options`` (a
    ``Hyperparameters`` dataclass of ``hparam`` fields, default: none)."""
    _REGISTRY[name] = _Entry(entry_point, options)


def encoder_names() -> tuple[str, ...]:
    """The registered encoder names, in registration order."""
    return tuple(_REGISTRY)


def _entry(name: str) -> _Entry:
    if name not in _REGISTRY:
        close = difflib.get_close_matches(str(name), list(_REGISTRY), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(f"unknown encoder {name!r}{hint}; known encoders: {', '.join(_REGISTRY)}")
    return _REGISTRY[name]


def encoder_class(name: str) -> type[RewardEncoder]:
    """The class registered as ``name`` (its module imported); a ValueError lists the
    names if unknown."""
    module_name, class_name = _entry(name).entry_point.split(":")
    return getattr(importlib.import_module(module_name), class_name)


def encoder_options(name: str) -> type[Hyperparameters]:
    """The options dataclass of encoder ``name`` (its fields: the options, their types,
    bounds, defaults and default search choices)."""
    return _entry(name).options


def make_encoder(
    name: str,
    image_shape: tuple[int, int, int],
    seed: int = 0,
    device: str = "cpu",
    **options: Any,
) -> RewardEncoder:
    """Build encoder ``name``; an unknown, missing or bad option raises a ValueError naming
    it (and listing the valid ones)."""
    built = build_options(encoder_options(name), options, name)
    return encoder_class(name)(image_shape, seed, device, built)
