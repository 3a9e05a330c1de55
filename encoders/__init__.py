"""Reward encoders: ``phi`` in the reward ``-||phi(o') - phi(o_g)||``.

Public surface: ``RewardEncoder``, ``make_encoder``, ``encoder_names``, ``latent_reward``.
"""

from encoders.base import FitReport, RewardEncoder
from encoders.registry import encoder_names, encoder_options, make_encoder, register
from encoders.reward import latent_reward

__all__ = [
    "FitReport",
    "RewardEncoder",
    "encoder_names",
    "encoder_options",
    "latent_reward",
    "make_encoder",
    "register",
]
