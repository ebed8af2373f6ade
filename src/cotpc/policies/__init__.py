"""Policies: families (a config dataclass and a model each, registered once: the transformer with DT, BeT, CoTPC
and the ablations as presets; the BC MLP; Diffusion Policy; Decision Diffuser), the presets by name, and the
inference wrapper."""

from cotpc.policies.base import (FAMILIES, PRESETS, BaseConfig, config_from_dict, config_to_dict, get_preset,
                                 make_model, register_family)

# The families: importing each module registers it and its presets (this order is the order of `--policy`).
from cotpc.policies.mlp import MLPConfig, MLPPolicy  # bc  # isort: skip
from cotpc.policies.transformer import TransformerConfig, TransformerPolicy  # dt, bet, cotpc, ablations  # isort: skip
from cotpc.policies.diffusion import DiffusionPolicy, DPConfig  # dp  # isort: skip
from cotpc.policies.decision_diffuser import DDConfig, DecisionDiffuser  # dd  # isort: skip
from cotpc.policies.policy import CheckpointError, Policy, load_model, load_policy, save_checkpoint

__all__ = [
    "FAMILIES",
    "PRESETS",
    "BaseConfig",
    "CheckpointError",
    "DDConfig",
    "DecisionDiffuser",
    "DPConfig",
    "DiffusionPolicy",
    "MLPConfig",
    "MLPPolicy",
    "Policy",
    "TransformerConfig",
    "TransformerPolicy",
    "config_from_dict",
    "config_to_dict",
    "get_preset",
    "load_model",
    "load_policy",
    "make_model",
    "register_family",
    "save_checkpoint",
]
