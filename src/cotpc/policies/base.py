"""What every policy family shares, and the registry that finds a family by its config's type or name.

A family is one config dataclass (deriving from :class:`BaseConfig`) and one model class (an ``nn.Module`` built
as ``Model(cfg, obs_dim, action_dim, max_timestep)``), registered once with :func:`register_family`, with its
named presets (``--policy NAME``), by the module that defines them: the transformer
(:mod:`cotpc.policies.transformer`, one folder: DT, BeT, CoTPC and the ablations as presets), the Markovian MLP
(:mod:`cotpc.policies.mlp`), Diffusion Policy (:mod:`cotpc.policies.diffusion`) and Decision Diffuser
(:mod:`cotpc.policies.decision_diffuser`).
:func:`make_model`, the checkpoint format (``config.json`` names the family) and :func:`cotpc.load_policy` find
it here.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn as nn


@dataclass(frozen=True)
class BaseConfig:
    """The settings every family has: a name, and the recommended optimisation (TrainConfig flags override).

    A family's config adds its own fields and tells training what it needs through the properties below."""

    name: str = "policy"
    """Preset name this configuration came from (informational)."""
    lr: float = 5e-4
    """Peak learning rate."""
    min_lr: float = 5e-5
    """Final learning rate of the cosine schedule."""
    schedule: Literal["cosine", "constant"] = "cosine"
    """Learning-rate schedule after the warm-up."""
    warmup_iters: int = 1000
    """Linear warm-up iterations (capped at a tenth of the run)."""
    batch_size: int = 256
    """Global batch size (split across DDP processes)."""
    weight_decay: float = 1e-4
    """AdamW weight decay on matrices (biases, LayerNorms, embeddings and prompt tokens are not decayed)."""

    # --- what training asks of every family (override in the family's config) ---
    @property
    def window(self) -> int:
        """Timesteps per training window."""
        return 1

    @property
    def future_actions(self) -> int:
        """Actions after the window's last one a training window must also carry (``future_actions``, (B, F, p):
        a(t+1) .. a(t+F), the episode's last action repeated past its end); 0: none. Diffusion Policy's chunks."""
        return 0

    @property
    def future_states(self) -> int:
        """States after the window's last one a training window must also carry (``future_states``, (B, F, q):
        s(t+1) .. s(t+F), the episode's final observation repeated past its end); 0: none. Decision Diffuser's
        plans."""
        return 0

    @property
    def cot_targets(self) -> tuple[str, ...]:
        """CoT targets a training window must carry (``next``, ``last``, ``random``)."""
        return ()

    @property
    def needs_subskills(self) -> bool:
        """True if training needs ``subskill_ends`` in the data file."""
        return any(t in ("next", "last") for t in self.cot_targets)

    @property
    def n_kmeans_centres(self) -> int:
        """k-means centres of the normalised training actions the model holds (0: none)."""
        return 0

    @property
    def leak_free(self) -> bool:
        """True if no training prediction of window index i can see a(>=i) or s(>i) (tested)."""
        return True

    def replace(self, **changes) -> "BaseConfig":
        cfg = dataclasses.replace(self, **changes)
        cfg.validate()
        return cfg

    def validate(self) -> None:
        """Raise ValueError on an inconsistent configuration."""


@dataclass(frozen=True)
class Family:
    name: str
    config: type[BaseConfig]
    model: type[nn.Module]


FAMILIES: dict[str, Family] = {}
PRESETS: dict[str, BaseConfig] = {}
"""Every policy by its ``--policy`` name, as its family registered it."""


def register_family(name: str, config: type[BaseConfig], model: type[nn.Module],
                    presets: dict[str, BaseConfig] | None = None) -> Family:
    """Register a policy family and its named presets (once, in the module that defines it)."""
    if name in FAMILIES and (FAMILIES[name].config, FAMILIES[name].model) != (config, model):
        raise ValueError(f"policy family {name!r} is already registered")
    for preset, cfg in (presets or {}).items():
        if type(cfg) is not config:
            raise ValueError(f"preset {preset!r} of family {name!r} is a {type(cfg).__name__}, not a {config.__name__}")
        if preset in PRESETS and PRESETS[preset] != cfg:
            raise ValueError(f"policy preset {preset!r} is already registered")
        cfg.validate()
    FAMILIES[name] = Family(name, config, model)
    PRESETS.update(presets or {})
    return FAMILIES[name]


def get_preset(name: str, **overrides) -> BaseConfig:
    """The preset ``name`` with the given settings changed. Settings left None keep the preset's, and settings its
    family does not have (the context of the Markovian MLP, say) are ignored."""
    if name not in PRESETS:
        raise ValueError(f"unknown policy {name!r}; choose one of {', '.join(PRESETS)}")
    cfg = PRESETS[name]
    fields = {f.name for f in dataclasses.fields(cfg)}
    return cfg.replace(**{k: v for k, v in overrides.items() if v is not None and k in fields})


def family_of(cfg: BaseConfig) -> Family:
    for family in FAMILIES.values():
        if type(cfg) is family.config:
            return family
    raise ValueError(f"no policy family is registered for {type(cfg).__name__}")


def make_model(cfg: BaseConfig, obs_dim: int, action_dim: int, max_timestep: int) -> nn.Module:
    """Build the network of a policy configuration (found by the config's type)."""
    cfg.validate()
    return family_of(cfg).model(cfg, obs_dim, action_dim, max_timestep)


def config_to_dict(cfg: BaseConfig) -> dict:
    """The config as saved in ``config.json`` and ``training_state.pt``: its family and its fields."""
    return {"family": family_of(cfg).name, **dataclasses.asdict(cfg)}


def config_from_dict(d: dict) -> BaseConfig:
    """Inverse of :func:`config_to_dict`. Checkpoints written before families existed have no ``family`` and an
    ``arch`` field instead (``mlp`` or ``transformer``)."""
    d = dict(d)
    legacy = "family" not in d
    name = d.pop("family", None) or ("mlp" if d.get("arch") == "mlp" else "transformer")
    if name not in FAMILIES:
        raise ValueError(f"unknown policy family {name!r} (known: {', '.join(FAMILIES)}; written by a newer cotpc?)")
    config = FAMILIES[name].config
    fields = {f.name for f in dataclasses.fields(config)}
    if legacy:  # the earlier one-config format: drop the fields this family does not have
        legacy = {f.name for f in dataclasses.fields(FAMILIES["transformer"].config)} | {"arch"}
        d = {k: v for k, v in d.items() if k in fields or k not in legacy}
    unknown = set(d) - fields
    if unknown:
        raise ValueError(f"unknown {name} policy config keys {sorted(unknown)} (written by a newer cotpc?)")
    for f in dataclasses.fields(config):  # JSON has lists where the config has tuples
        if isinstance(d.get(f.name), list):
            d[f.name] = tuple(d[f.name])
    return config(**d)


class Normaliser(nn.Module):
    """Observation and action statistics (buffers, saved in the checkpoint)."""

    def __init__(self, obs_dim: int, action_dim: int):
        super().__init__()
        self.register_buffer("obs_mean", torch.zeros(obs_dim))
        self.register_buffer("obs_std", torch.ones(obs_dim))
        self.register_buffer("act_mean", torch.zeros(action_dim))
        self.register_buffer("act_std", torch.ones(action_dim))


def mlp(sizes: list[int], act: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    """Linear layers of the given sizes with ``act`` between them (none after the last)."""
    layers: list[nn.Module] = []
    for i, (a, b) in enumerate(zip(sizes[:-1], sizes[1:])):
        layers.append(nn.Linear(a, b))
        if i < len(sizes) - 2:
            layers.append(act())
    return nn.Sequential(*layers)


def params_as_buffers(module: nn.Module) -> nn.Module:
    """Turn every parameter of ``module`` into a buffer of the same name: a frozen copy that the optimiser, the
    parameter count and DDP's gradient sync do not see, and that ``state_dict`` saves."""
    for m in module.modules():
        for name, p in list(m.named_parameters(recurse=False)):
            delattr(m, name)
            m.register_buffer(name, p.detach().clone())
    return module


def ema_decay(updates: int, power: float, max_decay: float) -> float:
    """Decay of an exponential moving average's update after ``updates`` earlier ones, Diffusion Policy's EMAModel
    rule: 0 first (a copy), then ``min(max_decay, 1 - (1 + updates)^-power)``."""
    return 0.0 if updates == 0 else min(max_decay, 1 - (1 + updates) ** -power)


@torch.no_grad()
def average_into(average: nn.Module, net: nn.Module, decay: float) -> None:
    """``average`` (``net``'s parameters held as buffers, :func:`params_as_buffers`) <- decay * average + (1 -
    decay) * net."""
    buffers = dict(average.named_buffers())
    names = [n for n, _ in net.named_parameters()]
    torch._foreach_lerp_([buffers[n] for n in names], [p.detach() for p in net.parameters()], 1 - decay)
