"""The reward-encoder interface.

A reward encoder ``phi`` maps a batch of uint8 images to float32 vectors; the reward for
reaching image ``o'`` with goal image ``o_g`` is ``-||phi(o') - phi(o_g)||_2``
(``encoders.reward.latent_reward``). Learning-free encoders are ready at construction;
learned ones must be ``fit`` on images first.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True)
class FitReport:
    """What fitting a learned encoder did: per-epoch losses and the time it took."""

    epochs: int = 0
    losses: tuple[float, ...] = ()
    seconds: float = 0.0
    extra: dict[str, float] = field(default_factory=dict)


class RewardEncoder(ABC):
    """``encode(uint8 [N,H,W,C]) -> float32 [N,D]``, deterministic given its seed.

    Attributes:
        name: the registry name ("pixel", "linear", ...).
        dim: D, the size of an encoding.
        needs_fit: True for learned encoders (``fit`` must run before ``encode``); they
            also have ``num_images``, the random-policy frames to fit on (an option).
        options: the encoder's options (its ``encoders.options`` dataclass).
    """

    name: str = ""
    needs_fit: bool = False

    def __init__(
        self, image_shape: tuple[int, int, int], seed: int, device: str = "cpu", options: Any = None
    ):
        if len(image_shape) != 3 or image_shape[2] != 3 or min(image_shape) <= 0:
            raise ValueError(f"image_shape must be (H, W, 3), got {image_shape}")
        self.image_shape = tuple(int(s) for s in image_shape)
        self.seed = int(seed)
        self.device = device
        self.options = options

    @property
    @abstractmethod
    def dim(self) -> int:
        """Size D of one encoding."""

    @abstractmethod
    def encode(self, images: np.ndarray) -> np.ndarray:
        """Encode uint8 images [N,H,W,C] to float32 [N,D]."""

    def fit(self, images: np.ndarray, progress: bool = True) -> FitReport:
        """Train on uint8 images [N,H,W,C]; learning-free encoders do nothing."""
        return FitReport()

    def check_images(self, images: np.ndarray) -> np.ndarray:
        """Validate a batch against ``image_shape`` and dtype; raise ValueError if off."""
        images = np.asarray(images)
        if images.dtype != np.uint8:
            raise ValueError(f"images must be uint8, got {images.dtype}")
        if images.ndim != 4 or tuple(images.shape[1:]) != self.image_shape:
            raise ValueError(
                f"images must have shape [N, {', '.join(map(str, self.image_shape))}], "
                f"got {list(images.shape)}"
            )
        return images
