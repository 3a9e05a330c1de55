"""VAE and CVAE: beta-VAEs trained on random-policy frames; the encoding is the posterior mean.

Both minimise, per image, ``||x - decode(z)||^2 + beta * KL(q(z|x) || N(0, I))`` with
``z ~ q(z|x) = N(mu, exp(logvar))`` (a Gaussian decoder, pixels in [0, 1], summed over
pixels), by Adam on shuffled minibatches. The trial collects ``num_images`` frames with a
uniform random policy and calls ``fit``; the encoder only stores ``num_images`` so the
trial knows how many.

A fit reports its last epoch's reconstruction error and KL, and how many latent dimensions
are active (``active_dims``): a beta-VAE whose KL term wins collapses onto its prior, its
posterior mean barely moves with the image, and the reward ``-||mu(o') - mu(o_g)||`` rests
on what little it moves, however ``reward_scale: auto`` rescales it.
"""

from __future__ import annotations

import sys
import time
from abc import abstractmethod

import numpy as np
import torch
from torch import nn

from encoders.base import FitReport
from encoders.options import VAEOptions
from encoders.torch_base import TorchEncoder, images_to_tensor, seeded

#: a latent dimension is active when the variance of its posterior mean over the data exceeds
#: this (Burda, Grosse & Salakhutdinov 2016, "Importance Weighted Autoencoders", sec. 5.2)
ACTIVE_VARIANCE = 0.01


def active_dims(means: np.ndarray, threshold: float = ACTIVE_VARIANCE) -> int:
    """How many columns of the posterior means [N, D] vary over the N images by more than
    ``threshold`` (variance): the latent dimensions the encoding uses."""
    return int((np.var(np.asarray(means, np.float64), axis=0) > threshold).sum())


class _BetaVAE(TorchEncoder):
    """The training loop and options shared by VAE and CVAE; subclasses build
    ``self.encoder_net`` (image -> 2 * latent_dim: mu, logvar) and ``self.decoder_net``
    (latent -> image logits [n, C, H, W])."""

    needs_fit = True

    def __init__(
        self,
        image_shape: tuple[int, int, int],
        seed: int,
        device: str = "cpu",
        options: VAEOptions | None = None,
    ) -> None:
        options = options or VAEOptions()
        super().__init__(image_shape, seed, device, options)
        self.latent_dim, self.beta, self.lr = options.latent_dim, options.beta, options.lr
        self.epochs, self.batch_size = options.epochs, options.batch_size
        self.num_images = options.num_images
        self.fitted = False
        with seeded(self.seed):
            self.build()
        self.encoder_net.to(self.torch_device)
        self.decoder_net.to(self.torch_device)

    @abstractmethod
    def build(self) -> None:
        """Create ``self.encoder_net`` and ``self.decoder_net``."""

    @property
    def dim(self) -> int:
        return self.latent_dim

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not self.fitted:
            raise RuntimeError(f"{self.name} encoder must be fit() before encode()")
        return self.encoder_net(x)[:, : self.latent_dim]

    def loss(self, x: torch.Tensor, generator: torch.Generator) -> tuple[torch.Tensor, ...]:
        """(mean loss, mean reconstruction error, mean KL) of a batch x in [0, 1]."""
        mu, logvar = self.encoder_net(x).chunk(2, dim=1)
        eps = torch.randn(mu.shape, generator=generator, device=mu.device)
        z = mu + eps * torch.exp(0.5 * logvar)
        recon = torch.sigmoid(self.decoder_net(z))
        recon_err = (recon - x).pow(2).flatten(1).sum(1).mean()
        kl = (0.5 * (mu.pow(2) + logvar.exp() - 1.0 - logvar)).sum(1).mean()
        return recon_err + self.beta * kl, recon_err, kl

    def fit(self, images: np.ndarray, progress: bool = True) -> FitReport:
        """Train for ``epochs`` on ``images`` (uint8 [N,H,W,C]); one stderr line per epoch
        unless ``progress=False``. Deterministic given the seed on CPU. The report's extra:
        the last epoch's ``recon`` and ``kl``, and ``active_dims`` of ``latent_dim`` on
        ``images``."""
        images = self.check_images(images)
        if len(images) == 0:
            raise ValueError("fit() needs at least one image")
        params = [*self.encoder_net.parameters(), *self.decoder_net.parameters()]
        optimizer = torch.optim.Adam(params, lr=self.lr)
        order_rng = np.random.default_rng(self.seed)
        generator = torch.Generator(device=self.torch_device).manual_seed(self.seed)
        self.encoder_net.train()
        self.decoder_net.train()
        losses: list[float] = []
        start = time.perf_counter()
        for epoch in range(self.epochs):
            totals = np.zeros(3)
            order = order_rng.permutation(len(images))
            for i in range(0, len(images), self.batch_size):
                idx = np.sort(order[i : i + self.batch_size])
                x = images_to_tensor(images[idx], self.torch_device)
                loss, recon_err, kl = self.loss(x, generator)
                optimizer.zero_grad(set_to_none=True)
                loss.backward()
                optimizer.step()
                totals += len(idx) * np.array([loss.item(), recon_err.item(), kl.item()])
            mean_loss, mean_recon, mean_kl = totals / len(images)
            if not np.isfinite(mean_loss):
                raise RuntimeError(f"{self.name} training diverged at epoch {epoch + 1} (loss NaN)")
            losses.append(float(mean_loss))
            if progress:
                print(
                    f"[{self.name}] epoch {epoch + 1}/{self.epochs} loss {mean_loss:.2f} "
                    f"(recon {mean_recon:.2f}, kl {mean_kl:.2f}) "
                    f"{time.perf_counter() - start:.1f}s",
                    file=sys.stderr,
                    flush=True,
                )
        self.fitted = True
        active = active_dims(self.encode(images))
        if progress:
            print(
                f"[{self.name}] active latent dims {active} of {self.latent_dim}",
                file=sys.stderr,
                flush=True,
            )
        return FitReport(
            epochs=self.epochs,
            losses=tuple(losses),
            seconds=time.perf_counter() - start,
            extra={"recon": float(mean_recon), "kl": float(mean_kl), "active_dims": active},
        )


class VAEEncoder(_BetaVAE):
    """Fully-connected beta-VAE on the flattened image.

    Encoder: ``H*W*C -> 512 -> 128 -> (mu, logvar)`` (ReLU); decoder mirrored:
    ``latent -> 128 -> 512 -> H*W*C`` (ReLU, sigmoid output).
    """

    name = "vae"
    hidden_sizes = (512, 128)

    def build(self) -> None:
        h, w, c = self.image_shape
        (h1, h2), n = self.hidden_sizes, h * w * c
        self.encoder_net = nn.Sequential(
            Permute(0, 2, 3, 1),  # flatten in HWC order, as PIXEL
            nn.Flatten(),
            nn.Linear(n, h1),
            nn.ReLU(),
            nn.Linear(h1, h2),
            nn.ReLU(),
            nn.Linear(h2, 2 * self.latent_dim),
        )
        self.decoder_net = nn.Sequential(
            nn.Linear(self.latent_dim, h2),
            nn.ReLU(),
            nn.Linear(h2, h1),
            nn.ReLU(),
            nn.Linear(h1, n),
            nn.Unflatten(1, (h, w, c)),
            Permute(0, 3, 1, 2),
        )


class Permute(nn.Module):
    """``x.permute(*dims)`` as a layer."""

    def __init__(self, *dims: int) -> None:
        super().__init__()
        self.dims = dims

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x.permute(*self.dims)


class CVAEEncoder(_BetaVAE):
    """Convolutional beta-VAE, the RIG layout (Nair et al. 2018).

    Encoder: conv 16 k5 s3, conv 32 k3 s2, conv 64 k3 s2 (ReLU), flatten, Linear heads for
    mu and logvar. 48x48: 15x15 -> 7x7 -> 3x3, flatten 576; 84x84: 27 -> 13 -> 6, flatten
    2304. Decoder mirrored: Linear latent -> flatten size, deconv 32 k3 s2, deconv 16 k3 s2
    (ReLU), deconv C k6 s3 (k5 when k6 would overshoot), sigmoid; output padding makes each
    deconv reproduce its conv's input size exactly (none needed at 48 or 84).
    """

    name = "cvae"
    channels = (16, 32, 64)
    kernels = (5, 3, 3)
    strides = (3, 2, 2)

    def build(self) -> None:
        h, w, c = self.image_shape
        sides = [(h, w)]
        for k, s in zip(self.kernels, self.strides, strict=True):
            sides.append(tuple((n - k) // s + 1 for n in sides[-1]))
        if min(sides[-1]) < 1:
            raise ValueError(f"image_shape {self.image_shape} is too small for the CVAE")
        flat = self.channels[-1] * sides[-1][0] * sides[-1][1]
        enc: list[nn.Module] = []
        for i, (k, s) in enumerate(zip(self.kernels, self.strides, strict=True)):
            enc += [nn.Conv2d(c if i == 0 else self.channels[i - 1], self.channels[i], k, s)]
            enc += [nn.ReLU()]
        self.encoder_net = nn.Sequential(*enc, nn.Flatten(), nn.Linear(flat, 2 * self.latent_dim))
        dec: list[nn.Module] = [
            nn.Linear(self.latent_dim, flat),
            nn.Unflatten(1, (self.channels[-1], *sides[-1])),
        ]
        for i in reversed(range(len(self.kernels))):
            (n_h, n_w), (m_h, m_w), s = sides[i + 1], sides[i], self.strides[i]
            k = self.kernels[i]
            if i == 0 and (n_h - 1) * s + 6 <= m_h and (n_w - 1) * s + 6 <= m_w:
                k = 6  # RIG's output layer
            pad = (m_h - (n_h - 1) * s - k, m_w - (n_w - 1) * s - k)
            out_channels = c if i == 0 else self.channels[i - 1]
            dec += [nn.ConvTranspose2d(self.channels[i], out_channels, k, s, output_padding=pad)]
            dec += [nn.ReLU()] if i > 0 else []
        self.decoder_net = nn.Sequential(*dec)
