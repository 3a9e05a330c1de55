"""Shared plumbing of the torch encoders: device choice, seeded construction, batched encode.

Imported only by the encoder modules that use torch, so ``import encoders`` stays light.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch

from encoders.base import RewardEncoder


def resolve_device(device: str) -> torch.device:
    """``"auto"`` -> CUDA when available else CPU; anything else must name a usable device."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(device)
    except (RuntimeError, TypeError) as err:
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda[:N]', got {device!r}") from err
    if resolved.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"device {device!r} requested but CUDA is not available")
    if resolved.type not in ("cpu", "cuda"):
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda[:N]', got {device!r}")
    return resolved


@contextmanager
def seeded(seed: int) -> Iterator[None]:
    """Run a block (e.g. building layers) under ``torch.manual_seed(seed)`` without
    disturbing the caller's global torch RNG."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield


def images_to_tensor(images: np.ndarray, device: torch.device) -> torch.Tensor:
    """uint8 [N,H,W,C] -> float32 [N,C,H,W] in [0, 1] on ``device``."""
    x = torch.from_numpy(np.ascontiguousarray(images)).to(device)
    return x.permute(0, 3, 1, 2).float().div_(255.0)


class TorchEncoder(RewardEncoder):
    """A reward encoder computed by a torch network, in batches of ``chunk`` images.

    Subclasses build their modules in ``__init__`` (inside ``seeded(seed)``) and implement
    ``forward(x)`` from float [n,C,H,W] in [0,1] to [n,D].
    """

    #: images per forward pass in ``encode`` (bounds memory, not results)
    chunk: int = 256

    def __init__(
        self, image_shape: tuple[int, int, int], seed: int, device: str = "cpu", options: Any = None
    ):
        super().__init__(image_shape, seed, device, options)
        self.torch_device = resolve_device(device)

    @abstractmethod
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """float32 [n,C,H,W] in [0,1] on the encoder's device -> [n,D]."""

    def encode(self, images: np.ndarray) -> np.ndarray:
        images = self.check_images(images)
        # no dropout or batch norm anywhere, so train/eval mode does not matter
        out = np.empty((len(images), self.dim), np.float32)
        with torch.no_grad():
            for start in range(0, len(images), self.chunk):
                x = images_to_tensor(images[start : start + self.chunk], self.torch_device)
                out[start : start + len(x)] = self.forward(x).float().cpu().numpy()
        return out
