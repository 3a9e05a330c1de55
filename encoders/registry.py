"""Reward encoders by name.

``make_encoder("conv", image_shape=(48, 48, 3), seed=0, latent_dim=128)`` builds one;
``ENCODER_NAMES`` lists them. Each encoder module registers its class with ``register``;
the registry imports modules lazily so ``import encoders`` stays light.
"""

from __future__ import annotations

import difflib
import importlib
import inspect
from typing import Any

from encoders.base import RewardEncoder

#: name -> "module:Class"; the module is imported on first use
_ENTRY_POINTS: dict[str, str] = {
    "pixel": "encoders.pixel:PixelEncoder",
    "linear": "encoders.linear:LinearEncoder",
    "conv": "encoders.conv:ConvEncoder",
    "vae": "encoders.vae:VAEEncoder",
    "cvae": "encoders.vae:CVAEEncoder",
    "vgg": "encoders.vgg:VGGEncoder",
}


def register(name: str, entry_point: str) -> None:
    """Register an encoder class under ``name`` ("module:Class")."""
    _ENTRY_POINTS[name] = entry_point


def encoder_names() -> tuple[str, ...]:
    """The registered encoder names, in registration order."""
    return tuple(_ENTRY_POINTS)


def encoder_class(name: str) -> type[RewardEncoder]:
    """The class registered as ``name``; a ValueError lists the names if unknown."""
    if name not in _ENTRY_POINTS:
        close = difflib.get_close_matches(str(name), list(_ENTRY_POINTS), n=1)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise ValueError(
            f"unknown encoder {name!r}{hint}; known encoders: {', '.join(_ENTRY_POINTS)}"
        )
    module_name, class_name = _ENTRY_POINTS[name].split(":")
    return getattr(importlib.import_module(module_name), class_name)


def encoder_options(name: str) -> dict[str, Any]:
    """The keyword options encoder ``name`` accepts, with their defaults."""
    params = inspect.signature(encoder_class(name).__init__).parameters
    skip = {"self", "image_shape", "seed", "device"}
    return {p.name: p.default for p in params.values() if p.name not in skip}


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
