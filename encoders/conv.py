"""CONV: a randomly initialised DrQ conv stack plus one Linear layer, never trained.

``drq_conv_stack``, ``conv_output_size`` and ``drq_weight_init`` are the DrQ image
encoder's conv layers and its initialisation, shared with the agent (``agent`` may import
``encoders``, never the reverse).
"""

from __future__ import annotations

import torch
from torch import nn

from encoders.options import ConvOptions
from encoders.torch_base import TorchEncoder, seeded

#: DrQ: four 3x3 convs, strides 2, 1, 1, 1, no padding, ReLU after each
DRQ_STRIDES = (2, 1, 1, 1)


def conv_output_size(image_size: int) -> int:
    """Side of the DrQ conv stack's output map for a square input (84 -> 35, 48 -> 17)."""
    size = image_size
    for stride in DRQ_STRIDES:
        size = (size - 3) // stride + 1
    if size < 1:
        raise ValueError(f"image size {image_size} is too small for the DrQ conv stack")
    return size


def drq_conv_stack(in_channels: int = 3, num_filters: int = 32) -> nn.Sequential:
    """The DrQ conv layers (input: float images in [0, 1]; output: [N, num_filters, s, s]
    with ``s = conv_output_size(H)``). PyTorch's default initialisation: apply
    ``drq_weight_init`` for DrQ's. The ReLUs are in place: the conv maps are large and the
    CPU is memory-bound on them."""
    layers: list[nn.Module] = []
    for i, stride in enumerate(DRQ_STRIDES):
        layers += [nn.Conv2d(in_channels if i == 0 else num_filters, num_filters, 3, stride)]
        layers += [nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


def drq_weight_init(module: nn.Module) -> None:
    """DrQ's initialisation of its networks (``module.apply(drq_weight_init)``), as
    denisyarats/drq and facebookresearch/drqv2 ``utils.weight_init``: orthogonal weights
    with gain sqrt(2) (ReLU's) on convs and 1 on linears, zero biases."""
    if isinstance(module, nn.Linear | nn.Conv2d):
        gain = nn.init.calculate_gain("relu") if isinstance(module, nn.Conv2d) else 1.0
        nn.init.orthogonal_(module.weight, gain)
        nn.init.zeros_(module.bias)


class ConvEncoder(TorchEncoder):
    """``phi(o) = Linear(flatten(drq_conv_stack(o / 255)))`` to ``latent_dim``, random weights
    from ``seed``: 32 filters, 84x84 -> 32x35x35 -> latent_dim, 48x48 -> 32x17x17 -> latent_dim.

    ``init="drq"`` (the default) initialises it as DrQ's agents initialise their encoder, as
    the thesis' CONV is the agents' architecture; ``"pytorch"`` keeps PyTorch's default
    (uniform weights and biases in +-1/sqrt(fan_in)), whose biases outweigh the image signal
    by the last conv layer. The weights are drawn on the CPU, so they are the same on every
    device.
    """

    name = "conv"
    num_filters = 32

    def __init__(
        self,
        image_shape: tuple[int, int, int],
        seed: int,
        device: str = "cpu",
        options: ConvOptions | None = None,
    ) -> None:
        options = options or ConvOptions()
        super().__init__(image_shape, seed, device, options)
        self.latent_dim = options.latent_dim
        h, w, c = self.image_shape
        flat = self.num_filters * conv_output_size(h) * conv_output_size(w)
        with seeded(self.seed):
            net = nn.Sequential(
                drq_conv_stack(c, self.num_filters),
                nn.Flatten(),
                nn.Linear(flat, self.latent_dim),
            )
            if options.init == "drq":
                net.apply(drq_weight_init)
        self.net = net.to(self.torch_device)

    @property
    def dim(self) -> int:
        return self.latent_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)
