"""Goal-conditioned SAC with the DrQ architecture: the whole algorithm in this file.

- A conv stack (3x3, ``num_filters`` filters, strides 2,1,1,1, ReLU, no padding) encodes
  the observation and the goal image with the same weights. Actor and critic each put
  the flat conv features through their own head (Linear to ``feature_dim``, LayerNorm,
  tanh), applied to observation and goal alike, and concatenate the two.
- Only the critic loss trains the conv stack: the actor sees detached conv features.
- Twin Q critics with a soft-updated (``critic_tau``) target copy of the heads and Q
  networks; the target reads the online conv features (as DrQ-v2), so the convs are not
  duplicated. Episodes never terminate (they are truncated), so targets always bootstrap.
- Tanh-squashed Gaussian actor, log-std bounded to [-10, 2]; learned temperature with
  target entropy ``-|A|``.
- Augmentation: replicate-pad by ``image_pad`` and random-crop back (DrQ), done by
  one gather on the uint8 images, independently for each image.
- State-oracle mode (``pixels=False``): the same SAC on state and goal vectors, no convs.
- Precision ``bf16``: the forward passes of acting and of the update run under bf16
  autocast (convolutions and matrix products in bf16); each network's output is cast
  back to fp32, so log-probabilities, targets, losses, the reward, weights and optimiser
  state stay fp32. ``fp32`` is the same code with autocast off.

Speed: images stay uint8 NHWC until the conv, whose float input is a channels-last view
(no copy); one conv pass with gradient over (obs, goal) and one without over next_obs.
"""

from __future__ import annotations

import copy
import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from agent.config import PRECISIONS, SACConfig
from encoders.conv import conv_output_size, drq_conv_stack, drq_weight_init

LOG_STD_MIN, LOG_STD_MAX = -10.0, 2.0


def mlp(in_dim: int, hidden_sizes: tuple[int, ...], out_dim: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for size in hidden_sizes:
        layers += [nn.Linear(in_dim, size), nn.ReLU()]
        in_dim = size
    layers.append(nn.Linear(in_dim, out_dim))
    return nn.Sequential(*layers)


def random_shift(images: Tensor, pad: int) -> Tensor:
    """DrQ augmentation of uint8 [N,H,W,C]: replicate-pad by ``pad``, random crop back.

    Replicate padding followed by a crop at offset (dy, dx) reads pixel
    ``(clamp(i + dy - pad), clamp(j + dx - pad))``, so it is one gather, with no padded copy.
    """
    n, h, w, c = images.shape
    device = images.device
    shift = torch.randint(0, 2 * pad + 1, (n, 2), device=device)
    rows = (torch.arange(h, device=device) - pad + shift[:, :1]).clamp_(0, h - 1)
    cols = (torch.arange(w, device=device) - pad + shift[:, 1:]).clamp_(0, w - 1)
    pixel = (rows[:, :, None] * w + cols[:, None, :]).view(n, h * w, 1).expand(-1, -1, c)
    return images.reshape(n, h * w, c).gather(1, pixel).view(n, h, w, c)


class ConvEncoder(nn.Module):
    """uint8 images [N,H,W,3] -> flat conv features [N, repr_dim]."""

    def __init__(self, image_size: int, num_filters: int) -> None:
        super().__init__()
        side = conv_output_size(image_size)  # raises if the image is too small
        self.convs = drq_conv_stack(3, num_filters)
        self.repr_dim = num_filters * side * side

    def forward(self, images: Tensor) -> Tensor:
        # NHWC -> NCHW is a channels-last view; flatten back in HWC order without a copy
        x = images.permute(0, 3, 1, 2).float().div_(255.0)
        if not self.channels_last:
            x = x.contiguous()
        return self.convs(x).permute(0, 2, 3, 1).flatten(1)

    @property
    def channels_last(self) -> bool:
        return self.convs[0].weight.is_contiguous(memory_format=torch.channels_last)

    def use_layout(self, channels_last: bool) -> None:
        """Run the convolutions channels-last (oneDNN's fast layout on Intel CPUs; the
        default) or NCHW; the same numbers up to floating-point order."""
        self.to(memory_format=torch.channels_last if channels_last else torch.contiguous_format)


def head(in_dim: int, feature_dim: int, pixels: bool) -> nn.Module:
    """Conv features -> Linear, LayerNorm, tanh (pixels); states pass through."""
    if not pixels:
        return nn.Identity()
    return nn.Sequential(nn.Linear(in_dim, feature_dim), nn.LayerNorm(feature_dim), nn.Tanh())


class Actor(nn.Module):
    def __init__(self, dims: tuple[int, int], action_dim: int, cfg: SACConfig, pixels: bool):
        super().__init__()
        self.head = head(dims[0], cfg.feature_dim, pixels)
        in_dim = 2 * cfg.feature_dim if pixels else sum(dims)
        self.policy = mlp(in_dim, cfg.hidden_sizes, 2 * action_dim)

    def forward(self, obs: Tensor, goal: Tensor) -> tuple[Tensor, Tensor]:
        h = torch.cat([self.head(obs), self.head(goal)], dim=-1)
        mu, log_std = self.policy(h).float().chunk(2, dim=-1)  # fp32 under bf16 autocast
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(log_std) + 1)
        return mu, log_std

    def sample(self, obs: Tensor, goal: Tensor) -> tuple[Tensor, Tensor]:
        """A reparameterised tanh-Gaussian action and its log-probability [B, 1]."""
        mu, log_std = self(obs, goal)
        u = mu + log_std.exp() * torch.randn_like(mu)
        action = torch.tanh(u)
        # log N(u; mu, std) - log |d tanh(u)/du|, the latter as 2 (log 2 - u - softplus(-2u))
        log_prob = -0.5 * ((u - mu) / log_std.exp()).pow(2) - log_std - 0.5 * math.log(2 * math.pi)
        log_prob = log_prob - 2 * (math.log(2) - u - F.softplus(-2 * u))
        return action, log_prob.sum(-1, keepdim=True)


class Critic(nn.Module):
    def __init__(self, dims: tuple[int, int], action_dim: int, cfg: SACConfig, pixels: bool):
        super().__init__()
        self.head = head(dims[0], cfg.feature_dim, pixels)
        in_dim = (2 * cfg.feature_dim if pixels else sum(dims)) + action_dim
        self.q1 = mlp(in_dim, cfg.hidden_sizes, 1)
        self.q2 = mlp(in_dim, cfg.hidden_sizes, 1)

    def forward(self, obs: Tensor, goal: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        h = torch.cat([self.head(obs), self.head(goal), action], dim=-1)
        return self.q1(h).float(), self.q2(h).float()


class SAC:
    """Networks, optimisers and the update. Observations are uint8 images or float states."""

    def __init__(
        self,
        obs_shape: tuple[int, ...],
        goal_shape: tuple[int, ...],
        action_dim: int,
        cfg: SACConfig,
        device: torch.device,
        precision: str = "fp32",
        channels_last: bool = True,
    ) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {PRECISIONS}, got {precision!r}")
        self.cfg = cfg
        self.device = device
        self.precision = precision
        self.pixels = len(obs_shape) == 3
        if self.pixels:
            self.encoder: ConvEncoder | None = ConvEncoder(obs_shape[0], cfg.num_filters)
            self.encoder.apply(drq_weight_init)
            self.encoder.to(device)
            self.encoder.use_layout(channels_last)
            dims = (self.encoder.repr_dim, self.encoder.repr_dim)
        else:
            self.encoder = None
            dims = (obs_shape[0], goal_shape[0])
        self.actor = Actor(dims, action_dim, cfg, self.pixels).to(device)
        self.critic = Critic(dims, action_dim, cfg, self.pixels).to(device)
        self.actor.apply(drq_weight_init)
        self.critic.apply(drq_weight_init)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        self.log_alpha = torch.tensor(math.log(cfg.init_temperature), device=device)
        self.log_alpha.requires_grad_(True)
        self.target_entropy = -float(action_dim)

        def adam(params: list[Tensor]) -> torch.optim.Adam:
            return torch.optim.Adam(params, lr=cfg.lr, fused=device.type in ("cpu", "cuda"))

        conv_params = list(self.encoder.parameters()) if self.encoder is not None else []
        self.critic_opt = adam(conv_params + list(self.critic.parameters()))
        self.actor_opt = adam(list(self.actor.parameters()))
        self.alpha_opt = adam([self.log_alpha])
        self.num_updates = 0

    @property
    def alpha(self) -> Tensor:
        return self.log_alpha.exp()

    def autocast(self) -> torch.autocast:
        """The forward passes' precision: bf16 autocast, or off (fp32)."""
        bf16 = self.precision == "bf16"
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=bf16)

    def to_tensor(self, x: np.ndarray) -> Tensor:
        return torch.as_tensor(x, device=self.device)

    @torch.no_grad()
    def act(self, obs: np.ndarray, goal: np.ndarray, sample: bool) -> np.ndarray:
        """One action in [-1, 1]: sampled (training) or the mean (evaluation)."""
        o, g = self.to_tensor(obs)[None], self.to_tensor(goal)[None]
        with self.autocast():
            if self.encoder is not None:
                o, g = self.encoder(torch.cat([o, g])).chunk(2)
            if sample:
                action, _ = self.actor.sample(o, g)
            else:
                action = torch.tanh(self.actor(o, g)[0])
        return action[0].cpu().numpy()

    def update(self, batch: dict[str, np.ndarray]) -> dict[str, Tensor]:
        """One gradient step of critic, then (every ``actor_update_every``) actor and
        temperature, then the target soft update. Returns the detached losses."""
        cfg = self.cfg
        obs, next_obs, goal = (self.to_tensor(batch[k]) for k in ("obs", "next_obs", "goal"))
        action, reward = self.to_tensor(batch["action"]), self.to_tensor(batch["reward"])
        n = len(obs)

        # 1. augment and encode: with gradient for (obs, goal), without for next_obs
        with self.autocast():
            if self.encoder is not None:
                images = torch.cat([obs, goal, next_obs])
                if cfg.image_pad > 0:
                    images = random_shift(images, cfg.image_pad)
                with torch.no_grad():
                    next_obs = self.encoder(images[2 * n :])
                obs, goal = self.encoder(images[: 2 * n]).split(n)

            # 2. critic: TD target from the target critic at the next observation
            with torch.no_grad():
                goal_d = goal.detach()
                next_action, next_log_prob = self.actor.sample(next_obs, goal_d)
                target_q1, target_q2 = self.critic_target(next_obs, goal_d, next_action)
                target_v = torch.min(target_q1, target_q2) - self.alpha * next_log_prob
                target_q = reward + cfg.discount * target_v
            q1, q2 = self.critic(obs, goal, action)
        critic_loss = F.mse_loss(q1, target_q) + F.mse_loss(q2, target_q)
        self.critic_opt.zero_grad(set_to_none=True)
        critic_loss.backward()
        self.critic_opt.step()
        losses = {"critic_loss": critic_loss.detach()}

        # 3. actor and temperature, on detached conv features (the actor never trains convs)
        if self.num_updates % cfg.actor_update_every == 0:
            obs, goal = obs.detach(), goal.detach()
            with self.autocast():
                pi_action, log_prob = self.actor.sample(obs, goal)
                self.critic.requires_grad_(False)  # gradients to the action only
                pi_q1, pi_q2 = self.critic(obs, goal, pi_action)
                self.critic.requires_grad_(True)
            actor_loss = (self.alpha.detach() * log_prob - torch.min(pi_q1, pi_q2)).mean()
            self.actor_opt.zero_grad(set_to_none=True)
            actor_loss.backward()
            self.actor_opt.step()

            alpha_loss = (self.alpha * (-log_prob.detach() - self.target_entropy)).mean()
            self.alpha_opt.zero_grad(set_to_none=True)
            alpha_loss.backward()
            self.alpha_opt.step()
            losses["actor_loss"] = actor_loss.detach()
            losses["alpha_loss"] = alpha_loss.detach()

        # 4. soft update of the target critic
        with torch.no_grad():
            for p, p_target in zip(
                self.critic.parameters(), self.critic_target.parameters(), strict=True
            ):
                p_target.lerp_(p, cfg.critic_tau)
        self.num_updates += 1
        return losses

    # ---- checkpoints ------------------------------------------------------------------
    def state_dict(self) -> dict:
        return {
            "encoder": self.encoder.state_dict() if self.encoder is not None else {},
            "actor": self.actor.state_dict(),
            "critic": self.critic.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "log_alpha": self.log_alpha.detach().clone(),
            "critic_opt": self.critic_opt.state_dict(),
            "actor_opt": self.actor_opt.state_dict(),
            "alpha_opt": self.alpha_opt.state_dict(),
            "num_updates": self.num_updates,
        }

    def load_state_dict(self, state: dict) -> None:
        if self.encoder is not None:
            self.encoder.load_state_dict(state["encoder"])
        for name in ("actor", "critic", "critic_target", "critic_opt", "actor_opt", "alpha_opt"):
            getattr(self, name).load_state_dict(state[name])
        with torch.no_grad():
            self.log_alpha.copy_(state["log_alpha"])
        self.num_updates = int(state["num_updates"])
