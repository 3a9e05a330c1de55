"""LINEAR: a fixed random Gaussian projection of the flattened image, never trained."""

from __future__ import annotations

import torch

from encoders.options import LatentOptions
from encoders.torch_base import TorchEncoder


class LinearEncoder(TorchEncoder):
    """``phi(o) = W^T o / 255`` with ``W [H*W*C, latent_dim]`` drawn i.i.d. ``N(0, 1/latent_dim)``.

    The ``1/latent_dim`` variance keeps distances the same size as pixel distances in
    expectation (Johnson-Lindenstrauss), whatever ``latent_dim``.
    """

    name = "linear"

    def __init__(
        self,
        image_shape: tuple[int, int, int],
        seed: int,
        device: str = "cpu",
        options: LatentOptions | None = None,
    ) -> None:
        options = options or LatentOptions()
        super().__init__(image_shape, seed, device, options)
        self.latent_dim = options.latent_dim
        h, w, c = self.image_shape
        # drawn on the CPU so the projection is the same on every device
        generator = torch.Generator().manual_seed(self.seed)
        weight = torch.randn(h * w * c, self.latent_dim, generator=generator)
        self.weight = (weight / self.latent_dim**0.5).to(self.torch_device)

    @property
    def dim(self) -> int:
        return self.latent_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # flatten in HWC order, the same as PIXEL
        return x.permute(0, 2, 3, 1).reshape(len(x), -1) @ self.weight
