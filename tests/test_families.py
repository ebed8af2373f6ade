"""Policy families: a config dataclass and a model each, registered once and found by the config's type (building)
or by the name config.json stores (loading)."""

import json
from dataclasses import dataclass

import numpy as np
import pytest
import torch
import torch.nn as nn

from cotpc.policies import (
    FAMILIES, PRESETS, BaseConfig, CheckpointError, MLPConfig, TransformerConfig, config_from_dict, config_to_dict,
    get_preset, load_policy, make_model, register_family, save_checkpoint,
)
from cotpc.policies.base import Normaliser


def test_every_preset_belongs_to_a_family_and_round_trips():
    assert set(FAMILIES) >= {"transformer", "mlp", "diffusion", "decision-diffuser"}
    for name, cfg in PRESETS.items():
        saved = config_to_dict(cfg)
        assert saved["family"] == {"bc": "mlp", "dp": "diffusion", "dd": "decision-diffuser"}.get(name, "transformer")
        assert config_from_dict(json.loads(json.dumps(saved))) == cfg  # through JSON: tuples come back as lists
    assert isinstance(PRESETS["bc"], MLPConfig) and isinstance(PRESETS["cotpc"], TransformerConfig)
    # a setting the family does not have is ignored (the trainer passes the task's context to every policy)
    assert get_preset("bc", context=20, n_centres=64) == PRESETS["bc"]
    assert get_preset("bet", context=20).context == 20


def test_checkpoints_of_the_one_config_format_still_load(tmp_path):
    torch.manual_seed(0)
    for name in ("bc", "bet"):
        cfg = get_preset(name, context=3, d_model=16, n_heads=2, n_layers=1, n_centres=4, hidden=16)
        model = make_model(cfg, 5, 2, 10)
        run = save_checkpoint(tmp_path / name, model, {"max_timestep": 10})
        info = json.loads((run / "config.json").read_text())
        # before families: no "family", an "arch", and every field of the one config (the MLP's too)
        legacy = {"arch": "mlp" if name == "bc" else "transformer", "context": 3, "d_model": 16,
                  **{k: v for k, v in info["policy"].items() if k != "family"}}
        info["policy"] = legacy
        (run / "config.json").write_text(json.dumps(info))
        policy = load_policy(run)
        assert policy.cfg == cfg
        assert policy.select_action(np.zeros((2, 5), np.float32)).shape == (2, 2)


def test_a_foreign_family_is_a_clear_error(tmp_path):
    model = make_model(PRESETS["bc"], 5, 2, 10)
    run = save_checkpoint(tmp_path / "run", model, {})
    info = json.loads((run / "config.json").read_text())
    info["policy"]["family"] = "diffusion-from-the-future"
    (run / "config.json").write_text(json.dumps(info))
    with pytest.raises(CheckpointError, match="unknown policy family 'diffusion-from-the-future'"):
        load_policy(run)
    info["policy"] = {**config_to_dict(PRESETS["bc"]), "depth": 3}
    (run / "config.json").write_text(json.dumps(info))
    with pytest.raises(CheckpointError, match=r"unknown mlp policy config keys \['depth'\]"):
        load_policy(run)


@dataclass(frozen=True)
class LinearConfig(BaseConfig):
    name: str = "linear"


class LinearPolicy(nn.Module):
    """A family as a new module would add one: its config, its model, one registration."""

    def __init__(self, cfg, obs_dim, action_dim, max_timestep):
        super().__init__()
        self.cfg, self.obs_dim, self.action_dim = cfg, obs_dim, action_dim
        self.norm = Normaliser(obs_dim, action_dim)
        self.net = nn.Linear(obs_dim, action_dim)

    def predict(self, batch):
        return self.net(batch["states"][:, -1])


def test_a_new_family_is_one_registration(tmp_path):
    register_family("linear-test", LinearConfig, LinearPolicy, presets={"linear": LinearConfig()})
    try:
        assert get_preset("linear") == LinearConfig()  # found by --policy linear, like every preset
        model = make_model(LinearConfig(), 4, 3, 0)
        assert isinstance(model, LinearPolicy)
        run = save_checkpoint(tmp_path / "run", model, {})
        assert json.loads((run / "config.json").read_text())["policy"]["family"] == "linear-test"
        policy = load_policy(run)
        obs = np.ones((2, 4), np.float32)
        np.testing.assert_allclose(policy.select_action(obs), model.net(torch.from_numpy(obs)).detach().numpy(),
                                   rtol=1e-6)
        with pytest.raises(ValueError, match="already registered"):
            register_family("linear-test", LinearConfig, nn.Linear)
        with pytest.raises(ValueError, match="preset 'bet' is already registered"):
            register_family("linear-test", LinearConfig, LinearPolicy, presets={"bet": LinearConfig()})
        with pytest.raises(ValueError, match="is a MLPConfig, not a LinearConfig"):
            register_family("linear-test", LinearConfig, LinearPolicy, presets={"linear-2": MLPConfig()})
        assert "linear-2" not in PRESETS
    finally:
        FAMILIES.pop("linear-test")
        PRESETS.pop("linear")
