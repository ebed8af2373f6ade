"""Policies: the CoTPC transformer, its baselines and ablations as configurations, and the inference wrapper."""

from cotpc.policies.config import PRESETS, PolicyConfig, get_preset
from cotpc.policies.model import MLPPolicy, TransformerPolicy, make_model
from cotpc.policies.policy import CheckpointError, Policy, load_model, load_policy, save_checkpoint

__all__ = [
    "PRESETS",
    "CheckpointError",
    "MLPPolicy",
    "Policy",
    "PolicyConfig",
    "TransformerPolicy",
    "get_preset",
    "load_model",
    "load_policy",
    "make_model",
    "save_checkpoint",
]
