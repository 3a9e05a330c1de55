"""The RL side: goal-conditioned envs, SAC-DrQ, replay and the trial loop.

``agent.train(config, report)`` runs one trial. ``import agent`` stays light: torch and
the envs are imported on first use of ``train``.
"""

from __future__ import annotations

from typing import Any

from agent.config import SACConfig, TrialConfig, TrialResult

__all__ = ["SACConfig", "TrialConfig", "TrialResult", "train"]


def __getattr__(name: str) -> Any:
    if name == "train":
        from agent.trial import train

        return train
    raise AttributeError(f"module 'agent' has no attribute {name!r}")
