"""VGG: ImageNet VGG16 convolutional features, from a local torchvision weights file.

Nothing is downloaded at run time. Get torchvision's ImageNet VGG16 state dict
(``vgg16-397923af.pth``, torchvision's ``VGG16_Weights.IMAGENET1K_V1``) on a machine with
internet access and give its path as the ``weights_path`` option, or set the environment
variable ``GCRL_VGG16_WEIGHTS`` (used when ``weights_path`` is not given). Only the
``features.*`` tensors are used; a full model state dict (with ``classifier.*``) is fine.
"""

from __future__ import annotations

from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from encoders.options import VGG_WEIGHTS_ENV_VAR, VGGOptions
from encoders.torch_base import TorchEncoder

#: torchvision's VGG16 "D" configuration: conv widths, "M" = 2x2 max pool
VGG16_CONFIG = (
    64,
    64,
    "M",
    128,
    128,
    "M",
    256,
    256,
    256,
    "M",
    512,
    512,
    512,
    "M",
    512,
    512,
    512,
    "M",
)
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
WHERE_TO_GET = (
    "download torchvision's ImageNet VGG16 weights "
    "(https://download.pytorch.org/models/vgg16-397923af.pth) on a machine with internet "
    f"access, copy the file here and pass its path as the vgg option weights_path "
    f"(or set {VGG_WEIGHTS_ENV_VAR})"
)


def vgg16_features() -> nn.Sequential:
    """VGG16's conv part, layer for layer as torchvision's ``vgg16().features`` (so the
    state-dict keys ``N.weight``/``N.bias`` match ``features.N.*``)."""
    layers: list[nn.Module] = []
    in_channels = 3
    for v in VGG16_CONFIG:
        if v == "M":
            layers.append(nn.MaxPool2d(kernel_size=2, stride=2))
        else:
            layers += [nn.Conv2d(in_channels, v, kernel_size=3, padding=1), nn.ReLU(inplace=True)]
            in_channels = v
    return nn.Sequential(*layers)


def load_features_state(path: Path, features: nn.Sequential) -> None:
    """Load the ``features.*`` tensors of a torchvision VGG16 state dict into ``features``;
    a ValueError says what is missing or mismatched and where to get the right file."""
    if not path.is_file():
        raise ValueError(f"vgg weights_path {str(path)!r} does not exist: {WHERE_TO_GET}")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # torch raises many types for a bad file
        raise ValueError(
            f"vgg weights_path {str(path)!r} is not a torch state dict ({err})"
        ) from err
    if not isinstance(state, dict):
        raise ValueError(
            f"vgg weights_path {str(path)!r} holds a {type(state).__name__}, not a state dict"
        )
    wanted = features.state_dict()
    problems = []
    for key, tensor in wanted.items():
        got = state.get(f"features.{key}")
        if got is None:
            problems.append(f"missing features.{key}")
        elif tuple(got.shape) != tuple(tensor.shape):
            problems.append(
                f"features.{key} has shape {list(got.shape)}, VGG16 needs {list(tensor.shape)}"
            )
    if problems:
        raise ValueError(
            f"vgg weights_path {str(path)!r} is not a torchvision VGG16 state dict: "
            f"{'; '.join(problems[:3])}{' ...' if len(problems) > 3 else ''}. {WHERE_TO_GET}"
        )
    features.load_state_dict({key: state[f"features.{key}"] for key in wanted})


class VGGEncoder(TorchEncoder):
    """``phi(o)`` = VGG16 conv features of the image, flattened.

    The image is resized (bilinear) to ``input_size`` x ``input_size`` (default 224, the
    scale the ImageNet weights were trained at), normalised with the ImageNet mean and
    std, passed through the 13 convs and 5 max pools, and the final
    ``512 x input_size/32 x input_size/32`` map is flattened (25088 values at 224).
    At 224 this costs ~15 GFLOP per image: use a GPU, or a smaller ``input_size``.
    """

    name = "vgg"
    chunk = 16

    def __init__(
        self,
        image_shape: tuple[int, int, int],
        seed: int,
        device: str,
        options: VGGOptions,
        *,
        pretrained: bool = True,
    ) -> None:
        """``pretrained=False`` keeps random weights: the same operations at the same cost,
        for timing a trial without the weights file (``agent.calibrate``), never for one."""
        super().__init__(image_shape, seed, device, options)
        self.input_size, self.weights_path = options.input_size, options.weights_path
        self.net = vgg16_features()
        if pretrained:
            load_features_state(Path(self.weights_path).expanduser(), self.net)
        self.net.to(self.torch_device)
        shape = (1, 3, 1, 1)
        self.mean = torch.tensor(IMAGENET_MEAN, device=self.torch_device).view(shape)
        self.std = torch.tensor(IMAGENET_STD, device=self.torch_device).view(shape)

    @property
    def dim(self) -> int:
        side = self.input_size
        for _ in range(VGG16_CONFIG.count("M")):
            side //= 2
        return 512 * side * side

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-2:] != (self.input_size, self.input_size):
            size = (self.input_size, self.input_size)
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=False)
        return self.net((x - self.mean) / self.std).flatten(1)
