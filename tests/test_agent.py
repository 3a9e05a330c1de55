"""SAC-DrQ networks and update, metrics, configs: small and fast."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from agent.config import SACConfig, TrialConfig
from agent.metrics import (
    diverged_metrics,
    evaluation_grid,
    metric_key,
    normalized_auc,
    summarize_episodes,
)
from agent.sac import SAC, conv_output_size, random_shift

torch.set_num_threads(1)


def batch(size: int, n: int = 8, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    images = lambda: rng.integers(0, 256, (n, size, size, 3), dtype=np.uint8)  # noqa: E731
    return {
        "obs": images(),
        "next_obs": images(),
        "goal": images(),
        "action": rng.uniform(-1, 1, (n, 2)).astype(np.float32),
        "reward": rng.uniform(-1, 0, (n, 1)).astype(np.float32),
    }


def pixel_agent(size: int = 32, precision: str = "fp32") -> SAC:
    cfg = SACConfig(hidden_sizes=(16, 16), batch_size=8)
    return SAC((size, size, 3), (size, size, 3), 2, cfg, torch.device("cpu"), precision)


def snapshot(module: torch.nn.Module) -> list[torch.Tensor]:
    return [p.detach().clone() for p in module.parameters()]


def changed(before: list[torch.Tensor], module: torch.nn.Module) -> bool:
    return any(not torch.equal(a, b) for a, b in zip(before, module.parameters(), strict=True))


def test_conv_output_size_matches_the_network() -> None:
    assert conv_output_size(84) == 35 and conv_output_size(48) == 17
    agent = pixel_agent(48)
    assert agent.encoder.repr_dim == 32 * 17 * 17
    out = agent.encoder(torch.zeros(2, 48, 48, 3, dtype=torch.uint8))
    assert out.shape == (2, 32 * 17 * 17)


def test_act_shapes_and_range() -> None:
    agent = pixel_agent()
    obs = batch(32)["obs"][0]
    for sample in (True, False):
        action = agent.act(obs, obs, sample=sample)
        assert action.shape == (2,) and np.all(np.abs(action) <= 1)
    # the evaluation policy is deterministic
    np.testing.assert_array_equal(agent.act(obs, obs, False), agent.act(obs, obs, False))


def test_only_the_critic_loss_trains_the_convs() -> None:
    agent = pixel_agent()
    conv, actor, critic = snapshot(agent.encoder), snapshot(agent.actor), snapshot(agent.critic)
    log_alpha = agent.log_alpha.item()
    critic_grads: list[torch.Tensor] = []

    def skip_critic_step() -> None:  # record the critic's conv gradients, apply nothing
        critic_grads.extend(p.grad.clone() for p in agent.encoder.parameters())

    agent.critic_opt.step = skip_critic_step
    losses = agent.update(batch(32))
    assert set(losses) == {"critic_loss", "actor_loss", "alpha_loss"}
    # the actor and temperature updates ran, and left the conv weights and gradients alone
    assert changed(actor, agent.actor) and agent.log_alpha.item() != log_alpha
    assert not changed(conv, agent.encoder) and not changed(critic, agent.critic)
    assert all(g.abs().sum() > 0 for g in critic_grads)
    for g, p in zip(critic_grads, agent.encoder.parameters(), strict=True):
        assert torch.equal(g, p.grad)

    del agent.critic_opt.step  # the real step: the critic loss moves the convs
    agent.update(batch(32, seed=1))
    assert changed(conv, agent.encoder) and changed(critic, agent.critic)


def test_target_critic_is_a_soft_copy() -> None:
    agent = pixel_agent()
    target = snapshot(agent.critic_target)
    agent.update(batch(32))
    tau = agent.cfg.critic_tau
    for t0, t1, p in zip(
        target, agent.critic_target.parameters(), agent.critic.parameters(), strict=True
    ):
        torch.testing.assert_close(t1, (1 - tau) * t0 + tau * p)


def test_actor_update_every() -> None:
    cfg = SACConfig(hidden_sizes=(16,), actor_update_every=2)
    agent = SAC((3,), (2,), 2, cfg, torch.device("cpu"))  # state oracle: vectors, no convs
    assert agent.encoder is None
    b = {
        "obs": np.ones((4, 3), np.float32),
        "next_obs": np.ones((4, 3), np.float32),
        "goal": np.zeros((4, 2), np.float32),
        "action": np.zeros((4, 2), np.float32),
        "reward": np.zeros((4, 1), np.float32),
    }
    assert "actor_loss" in agent.update(b)
    assert "actor_loss" not in agent.update(b)
    assert "actor_loss" in agent.update(b)


def test_random_shift_is_a_crop_of_the_replicate_padded_image() -> None:
    images = torch.randint(0, 256, (6, 10, 10, 3), dtype=torch.uint8)
    torch.testing.assert_close(random_shift(images, 0), images)
    torch.manual_seed(0)
    out = random_shift(images, 2).numpy()
    padded = np.pad(images.numpy(), ((0, 0), (2, 2), (2, 2), (0, 0)), mode="edge")
    offsets = set()
    for i in range(6):
        crops = [
            (dy, dx)
            for dy in range(5)
            for dx in range(5)
            if np.array_equal(padded[i, dy : dy + 10, dx : dx + 10], out[i])
        ]
        assert crops, f"image {i} is not a crop of its padded copy"
        offsets.add(crops[0])
    assert len(offsets) > 1  # independent shifts per image


def test_normalized_auc_by_hand() -> None:
    assert normalized_auc([0, 10], [0.0, 1.0]) == 0.5
    # (0.5*1*(0+1) + 0.5*2*(1+1)) / 3 = 2.5 / 3
    assert math.isclose(normalized_auc([0, 1, 3], [0.0, 1.0, 1.0]), 2.5 / 3)
    assert normalized_auc([0, 5, 10], [0.3, 0.3, 0.3]) == pytest.approx(0.3)
    with pytest.raises(ValueError, match="increasing"):
        normalized_auc([0, 0], [1, 1])


def test_evaluation_grid_and_metric_names() -> None:
    assert evaluation_grid(300, 100) == (0, 100, 200, 300)
    assert evaluation_grid(250, 100) == (0, 100, 200, 250)
    assert metric_key("is_success") == "success_rate"
    assert metric_key("angle_success") == "angle_success_rate"
    assert metric_key("hand_distance") == "final_hand_distance"
    finals = [{"is_success": 1.0, "distance": 0.5}, {"is_success": 0.0, "distance": 1.5}]
    assert summarize_episodes(finals, ("is_success", "distance")) == {
        "success_rate": 0.5,
        "final_distance": 1.0,
    }
    filled = diverged_metrics(("success_rate", "final_distance"))
    assert filled["success_rate"] == 0.0 and math.isnan(filled["final_distance"])


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"lr": 0.0}, "sac.lr"),
        ({"hidden_sizes": ()}, "sac.hidden_sizes"),
        ({"discount": 1.5}, "sac.discount"),
        ({"batch_size": 2.5}, "sac.batch_size"),
        ({"updates_per_step": 0}, "sac.updates_per_step"),  # a trial must learn
        ({"hidden_sizes": (64, 0)}, r"sac.hidden_sizes\[1\]"),
    ],
)
def test_bad_sac_config_names_the_field(kwargs: dict, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        SACConfig(**kwargs)


def test_bad_trial_config_names_the_field() -> None:
    with pytest.raises(ValueError, match="total_steps"):
        TrialConfig(total_steps=0)
    with pytest.raises(ValueError, match="device"):
        TrialConfig(device="tpu")
    assert SACConfig(hidden_sizes=[8, 8]).hidden_sizes == (8, 8)


def test_an_update_in_either_conv_layout_gives_the_same_losses() -> None:
    """Channels-last (the default) and NCHW differ only in floating-point order: over
    three updates from the same weights, batch and random shifts, every loss agrees to
    1e-5 relative, and the layout really changed."""
    losses = {}
    for channels_last in (True, False):
        torch.manual_seed(0)
        agent = pixel_agent()
        agent.encoder.use_layout(channels_last)
        assert agent.encoder.channels_last is channels_last
        torch.manual_seed(1)
        losses[channels_last] = [
            {k: float(v) for k, v in agent.update(batch(32, seed=i)).items()} for i in range(3)
        ]
    assert losses[True][0].keys() >= {"critic_loss"}
    for fast, plain in zip(losses[True], losses[False], strict=True):
        for name in fast:
            assert fast[name] == pytest.approx(plain[name], rel=1e-5, abs=1e-7), name


def test_bf16_runs_the_forward_passes_in_bf16_and_keeps_the_rest_fp32() -> None:
    """Under precision bf16 the convolutions and the Q networks compute in bf16, while
    weights, gradients, optimiser state, losses and actions stay fp32; from the same
    weights and batches the losses are fp32's within bf16's resolution, and fp32 is the
    same code with autocast off. Compared at the first update, from the same weights (Adam
    turns the small differences of the gradients into steps of the learning rate's size,
    so later updates start from different weights)."""
    losses, conv_dtypes = {}, {}
    for precision in ("fp32", "bf16"):
        torch.manual_seed(0)
        agent = pixel_agent(precision=precision)
        seen: list[torch.dtype] = []
        agent.encoder.convs[0].register_forward_hook(
            lambda m, i, out, seen=seen: seen.append(out.dtype)
        )
        torch.manual_seed(1)
        losses[precision] = [
            {k: float(v) for k, v in agent.update(batch(32, seed=i)).items()} for i in range(3)
        ]
        conv_dtypes[precision] = set(seen)
        action = agent.act(batch(32)["obs"][0], batch(32)["goal"][0], sample=True)
        assert action.dtype == np.float32
        for net in (agent.encoder, agent.actor, agent.critic, agent.critic_target):
            assert {p.dtype for p in net.parameters()} == {torch.float32}
            assert {p.grad.dtype for p in net.parameters() if p.grad is not None} <= {torch.float32}
        state = agent.critic_opt.state_dict()["state"]
        assert {t.dtype for s in state.values() for t in s.values() if t.dim()} == {torch.float32}
    assert conv_dtypes == {"fp32": {torch.float32}, "bf16": {torch.bfloat16}}
    full, half = losses["fp32"][0], losses["bf16"][0]
    assert full.keys() == half.keys() == {"critic_loss", "actor_loss", "alpha_loss"}
    for name in full:
        assert half[name] != full[name] and half[name] == pytest.approx(full[name], rel=0.02)
    assert all(math.isfinite(v) for update in losses["bf16"] for v in update.values())
    with pytest.raises(ValueError, match="precision"):
        pixel_agent(precision="fp16")
    with pytest.raises(ValueError, match="precision"):
        TrialConfig(precision="fp16")
