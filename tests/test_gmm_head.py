"""The gmm action head: its likelihood is the mixture's, and it keeps the modes an MSE head averages."""

import pytest
import torch

from cotpc.policies import get_preset, make_model

Q, P, T = 3, 2, 2
TINY = {"context": T, "d_model": 32, "n_heads": 4, "n_layers": 1, "hidden": 64}


def test_mixture_nll_is_the_mixture_log_likelihood():
    torch.manual_seed(0)
    model = make_model(get_preset("dt-gmm", n_modes=3, **TINY), Q, P, max_timestep=10)
    raw, target = torch.randn(5, 3 * (1 + 2 * P)), torch.randn(5, P)
    logits, means, stds = model.mixture(raw)
    reference = torch.distributions.MixtureSameFamily(
        torch.distributions.Categorical(logits=logits),
        torch.distributions.Independent(torch.distributions.Normal(means, stds), 1))
    assert torch.allclose(model.mixture_nll(raw, target), -reference.log_prob(target), atol=1e-5)
    # the action is the mean of the most likely mode
    k = logits.argmax(-1)
    assert torch.equal(model.mixture_mode(raw), means[torch.arange(5), k])


def _fit(name: str) -> torch.Tensor:
    """Train on one state whose action is (+2, +2) or (-2, -2) with equal chance (a one-step window: no past
    action tells which); the predicted action."""
    torch.manual_seed(0)
    T = 1
    model = make_model(get_preset(name, **{**TINY, "context": T}), Q, P, max_timestep=10)
    opt = torch.optim.Adam(model.parameters(), lr=3e-3)
    B = 64
    sign = torch.where(torch.arange(B) % 2 == 0, 1.0, -1.0)
    batch = {"states": torch.zeros(B, T, Q), "actions": 2.0 * sign[:, None, None].expand(B, T, P).clone(),
             "timesteps": torch.arange(T).expand(B, T), "valid": torch.ones(B, T, dtype=torch.bool)}
    for _ in range(300):
        opt.zero_grad()
        model.loss(batch)[0].backward()
        opt.step()
    return model.eval().predict(batch)[0]


def test_gmm_head_keeps_a_mode_where_mse_averages_them():
    gmm, mse = _fit("dt-gmm"), _fit("dt")
    assert mse.abs().max() < 0.5  # the average of the two modes: an action no demo takes
    assert torch.allclose(gmm.abs(), torch.full((P,), 2.0), atol=0.1)  # one of the demos' actions
    assert torch.sign(gmm[0]) == torch.sign(gmm[1])  # and both components from the same mode


def test_mean_action_rule_acts_with_the_expected_action():
    """``action_rule="mean"``: the probability-weighted sum of every centre plus its offset (k-means head), or the
    mixture mean (gmm); ``mode`` (the default) is unchanged."""
    torch.manual_seed(0)
    B = 4
    batch = {"states": torch.randn(B, T, Q), "actions": torch.randn(B, T, P), "timesteps": torch.arange(T).expand(B, T)}
    for name in ("bet", "cotpc", "dt-gmm"):
        cfg = get_preset(name, n_centres=6, **TINY)
        model = make_model(cfg, Q, P, max_timestep=10).eval()
        with torch.no_grad():
            for prm in model.parameters():
                prm.add_(0.1 * torch.randn_like(prm))
            if cfg.action_head == "bet":
                model.centres.normal_()
            x, _ = model._features(batch, train=False)
            centre_feats = model._select(x, cfg.centre_from, None)[:, -1]
            if cfg.action_head == "bet":
                probs = model.centre_head(centre_feats).softmax(-1)
                off = model.offset_head(model._select(x, cfg.offset_from, None)[:, -1]).view(B, -1, P)
                expected = ((model.centres + off) * probs[..., None]).sum(1)
            else:
                logits, means, _ = model.mixture(model.mixture_head(centre_feats))
                expected = (logits.softmax(-1)[..., None] * means).sum(1)
            mode = model.predict(batch)
            model.cfg = cfg.replace(action_rule="mean")
            assert torch.allclose(model.predict(batch), expected, atol=1e-5), name
            assert not torch.allclose(mode, expected, atol=1e-3), name  # the rule changes the action


def test_the_mse_head_refuses_an_action_rule():
    with pytest.raises(ValueError, match="mse head predicts one action"):
        get_preset("dt").replace(action_rule="mean")
    get_preset("dt").replace(action_rule="mode")


def test_eval_files_of_other_action_rules_never_replace_the_runs_own(tmp_path):
    from cotpc.evaluation.request import EvalRequest

    assert EvalRequest(run=tmp_path).variant_suffix() == ""
    assert EvalRequest(run=tmp_path, action_rule="mode").variant_suffix() == ""
    assert EvalRequest(run=tmp_path, action_rule="mean", sampler_steps=5).variant_suffix() == "_steps5_mean"
    assert EvalRequest(run=tmp_path, action_rule="sample").variant_suffix() == "_sample"


def test_sample_action_rule_draws_centres_by_their_probabilities_and_repeats():
    """``action_rule="sample"`` (the original BeT's): a centre drawn from the classifier's softmax plus that
    centre's offset; the draws follow the probabilities, and a freshly loaded model draws the same sequence."""
    torch.manual_seed(0)
    n = 4000
    batch = {"states": torch.randn(1, T, Q).expand(n, T, Q), "actions": torch.randn(1, T, P).expand(n, T, P),
             "timesteps": torch.arange(T).expand(n, T)}
    cfg = get_preset("bet", n_centres=4, **TINY)
    model = make_model(cfg, Q, P, max_timestep=10).eval()
    with torch.no_grad():
        for prm in model.parameters():
            prm.add_(0.3 * torch.randn_like(prm))
        model.centres.copy_(10.0 * torch.eye(4, P) + torch.arange(4.0)[:, None] * 100)  # far apart: c from the action
        x, _ = model._features({k: v[:1] for k, v in batch.items()}, train=False)
        probs = model.centre_head(model._select(x, cfg.centre_from, None)[:, -1]).softmax(-1)[0]
        off = model.offset_head(model._select(x, cfg.offset_from, None)[:, -1]).view(-1, P)
    model.cfg = cfg.replace(action_rule="sample")
    first = model.predict(batch)
    drawn = ((first[:, None, :] - (model.centres + off)[None]).abs().sum(-1) < 1e-4).float()
    assert torch.equal(drawn.sum(1), torch.ones(n))  # every action is one centre plus its own offset
    assert torch.allclose(drawn.mean(0), probs, atol=0.03)  # drawn as often as the classifier says
    again = make_model(cfg, Q, P, max_timestep=10).eval()
    again.load_state_dict(model.state_dict())
    again.cfg = model.cfg
    assert torch.equal(again.predict(batch), first)  # a new load repeats the evaluation exactly
    assert not torch.equal(model.predict(batch), first)  # and the draws move on within an episode
