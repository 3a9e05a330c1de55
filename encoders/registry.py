"""Reward encoders by name.

``make_encoder("conv", image_shape=(48, 48, 3), seed=0, latent_dim=128)`` builds one;
``encoder_names()`` lists them. The registry imports an encoder's module on first use, and
declares each built-in encoder's options, so that checking a spec (``encoder_options``)
imports no torch: the sweep driver never needs it. ``tests/test_encoders.py`` checks the
declared options against each class's signature.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from encoders.base import RewardEncoder

#: constructor arguments every encoder takes and that are not options
_COMMON_ARGUMENTS = ("self", "image_shape", "seed", "device")


@dataclass(frozen=True)
class _Entry:
    entry_point: str  # "module:Class"
    options: Mapping[str, Any] | None  # keyword options and defaults; None: read the class


_VAE_OPTIONS = {
    "latent_dim": 16,
    "beta": 1.0,
    "lr": 1e-3,
    "epochs": 20,
    "num_images": 2000,
    "batch_size": 64,
}
_REGISTRY: dict[str, _Entry] = {
    "pixel": _Entry("encoders.pixel:PixelEncoder", {}),
    "linear": _Entry("encoders.linear:LinearEncoder", {"latent_dim": 128}),
    "conv": _Entry("encoders.conv:ConvEncoder", {"latent_dim": 128}),
    "vae": _Entry("encoders.vae:VAEEncoder", _VAE_OPTIONS),
    "cvae": _Entry("encoders.vae:CVAEEncoder", _VAE_OPTIONS),
    "vgg": _Entry("encoders.vgg:VGGEncoder", {"weights_path": None, "input_size": 224}),
}


def register(name: str, entry_point: str, options: Mapping[str, Any] | None = None) -> None:
    """Register an encoder class under ``name`` ("module:Class").

    ``options`` (keyword options with their defaults) spares importing the module to
    check a spec; without it they are read from the class's ``__init__`` signature.
    """
    _REGISTRY[name] = _Entry(entry_point, None if options is None else dict(options))


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


def signature_options(cls: type[RewardEncoder]) -> dict[str, Any]:
    """The keyword options of ``cls.__init__`` with their defaults (``inspect.Parameter.empty``
    for a required one)."""
    params = inspect.signature(cls.__init__).parameters
    return {p.name: p.default for p in params.values() if p.name not in _COMMON_ARGUMENTS}


def encoder_options(name: str) -> dict[str, Any]:
    """The keyword options encoder ``name`` accepts, with their defaults."""
    entry = _entry(name)
    if entry.options is not None:
        return dict(entry.options)
    return signature_options(encoder_class(name))


def make_encoder(
    name: str,
    image_shape: tuple[int, int, int],
    seed: int = 0,
    device: str = "cpu",
    **options: Any,
) -> RewardEncoder:
    """Build encoder ``name``; an unknown option raises a ValueError listing the valid ones."""
    cls = encoder_class(name)
    allowed = encoder_options(name)
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        valid = ", ".join(allowed) or "none"
        raise ValueError(f"encoder {name!r} has no option(s) {unknown}; valid options: {valid}")
    return cls(image_shape=image_shape, seed=seed, device=device, **options)
