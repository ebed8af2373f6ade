"""Action chunks on the transformer family (``action_chunk`` k, ``action_horizon`` H): each window index is
trained on a(i) .. a(i+k-1), the heads' k groups of outputs are read in the right places, and ``Policy``
predicts once every H steps, executes the chunk, and feeds the executed actions back into the context."""

import json

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from cotpc.cli.main import main as cotpc_main
from cotpc.data.dataset import Stats, WindowDataset, synthetic_trajectories
from cotpc.evaluation.request import load_for_eval
from cotpc.policies import Policy, get_preset, make_model
from cotpc.policies.kmeans import kmeans

Q, P, T, K = 6, 2, 4, 8
TINY = {"context": T, "d_model": 32, "n_heads": 4, "n_layers": 2, "n_centres": K, "hidden": 64}


@pytest.fixture(scope="module")
def trajs():
    return synthetic_trajectories(n_episodes=6, obs_dim=Q, action_dim=P, length=12, seed=0)


def build(name, trajs, **kw):
    cfg = get_preset(name, **{**TINY, **kw})
    obs = np.concatenate([e.obs[:-1] for e in trajs.episodes])
    act = np.concatenate([e.actions for e in trajs.episodes])
    ds = WindowDataset(trajs, list(range(len(trajs))), cfg.window, Stats.of(obs, act), cfg.cot_targets, seed=0,
                       future_actions=cfg.future_actions)
    torch.manual_seed(0)
    model = make_model(cfg, Q, P, max_timestep=25)
    if cfg.action_head == "bet":
        model.centres.copy_(kmeans(ds.actions, K, seed=0))
    with torch.no_grad():  # trained-looking weights: every output group differs
        for prm in model.parameters():
            prm.add_(0.05 * torch.randn_like(prm))
    return model, ds


def test_chunk_targets_are_the_next_k_actions_repeating_the_last(trajs):
    model, ds = build("bet", trajs, action_chunk=3)
    ends = torch.tensor([0, 5, 11, 12 + 10])  # 11 and 22: the last and next-to-last steps of an episode
    target = model._chunk_targets(ds.windows(ends))  # (B, T, 3, p)
    assert target.shape == (4, T, 3, P)
    for b, end in enumerate(ends.tolist()):
        ep_start, ep_last = 12 * (end // 12), 12 * (end // 12) + 11
        for i in range(T):
            t = end - (T - 1) + i
            if t < ep_start:
                continue  # left padding
            for j in range(3):
                torch.testing.assert_close(target[b, i, j], ds.actions[min(t + j, ep_last)])


@pytest.mark.parametrize("name", ["bet", "dt", "dt-gmm"])
def test_chunk_loss_is_the_mean_of_each_steps_loss(name, trajs):
    """The chunk's loss, from the model's gathered offsets, equals each step's loss from its own group of the
    dense head outputs, averaged: step j reads group j, for the centre, offset, decoder and mixture heads."""
    k = 3
    model, ds = build(name, trajs, action_chunk=k)
    batch = ds.sample(16, torch.Generator().manual_seed(0))
    with torch.no_grad():
        _, metrics = model.loss(batch)
        x, _ = model._features(batch, train=True)
        feats = model._select(x, model.cfg.centre_from, batch["valid"])
        target = model._chunk_targets(batch)
        w = batch["valid"].float()
        per_step = []
        for j in range(k):
            tj = target[:, :, j]
            if name == "dt":
                pred = model.action_decoder(feats).view(16, T, k, P)[:, :, j]
                per_step.append(((pred - tj) ** 2).mean(-1))
            elif name == "dt-gmm":
                raw = model.mixture_head(feats).view(16, T, k, -1)[:, :, j]
                per_step.append(model.mixture_nll(raw, tj))
            else:
                logits = model.centre_head(feats).view(16, T, k, K)[:, :, j]
                offsets = model.offset_head(feats).view(16, T, k, K, P)[:, :, j]
                c = torch.cdist(tj, model.centres[None].expand(16, -1, -1)).argmin(-1)
                ce = F.cross_entropy(logits.flatten(0, 1), c.flatten(), reduction="none").view(16, T)
                off = offsets.gather(2, c[..., None, None].expand(16, T, 1, P))[:, :, 0]
                off_mse = ((off - (tj - model.centres[c])) ** 2).mean(-1)
                per_step.append(ce + model.cfg.offset_weight * off_mse)
        want = ((torch.stack(per_step).mean(0) * w).sum() / w.sum())
    torch.testing.assert_close(metrics["bc"], want, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("name", ["bet", "cotpc-causal", "dt", "dt-gmm"])
def test_inference_chunk_equals_the_training_forward(name, trajs):
    """predict_window_chunk (the fast inference path) gives, at the last window index, the chunk the training
    forward's heads give there; predict() is its first action."""
    k = 3
    model, ds = build(name, trajs, action_chunk=k)
    model.eval()
    batch = ds.windows(torch.tensor([0, 1, 7, 15]))  # the first two start before their episode
    with torch.no_grad():
        x, _ = model._features(batch, train=False)
        cfg, valid = model.cfg, batch["valid"]
        feats = model._select(x, cfg.centre_from, valid)[:, -1]
        if name == "dt":
            want = model.action_decoder(feats).view(-1, k, P)
        elif name == "dt-gmm":
            want = model.mixture_mode(model.mixture_head(feats).view(len(feats), k, -1))
        else:
            logits = model.centre_head(feats).view(-1, k, K)
            offsets = model.offset_head(model._select(x, cfg.offset_from, valid)[:, -1]).view(-1, k, K, P)
            c = logits.argmax(-1)
            want = model.centres[c] + offsets.gather(2, c[..., None, None].expand(-1, k, 1, P))[:, :, 0]
        n_prev = valid.sum(1) - 1
        got = model.predict_window_chunk(batch["states"], batch["actions"][:, :-1], batch["timesteps"], n_prev)
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(model.predict(batch), want[:, 0], rtol=1e-5, atol=1e-5)


def test_policy_predicts_every_h_steps_and_feeds_executed_actions_back(trajs):
    model, _ = build("bet", trajs, action_chunk=4, action_horizon=3)
    calls = []
    inner = model.predict_window_chunk

    def spy(states, actions, timesteps, n_prev=None):
        out = inner(states, actions, timesteps, n_prev)
        calls.append((states.clone(), None if actions is None else actions.clone(), timesteps.clone(), out))
        return out

    model.predict_window_chunk = spy
    policy = Policy(model)
    obs = np.random.default_rng(0).normal(size=(8, 2, Q)).astype(np.float32)
    executed = [policy.select_action(o) for o in obs]
    assert len(calls) == 3  # steps 1, 4 and 7
    norm = model.norm
    act = lambda a: a.numpy() * norm.act_std.numpy() + norm.act_mean.numpy()  # noqa: E731
    first = act(calls[0][3])
    for t in range(3):  # the first chunk's first H actions, in order
        np.testing.assert_allclose(executed[t], first[:, t], rtol=1e-5, atol=1e-6)
    # the second prediction's context holds the three executed actions (normalised) and the step-4 window
    states, prev, timesteps, _ = calls[1]
    np.testing.assert_allclose(prev[:, -3:].numpy(), calls[0][3][:, :3].numpy(), rtol=1e-6, atol=1e-6)
    assert timesteps[:, -1].tolist() == [3, 3]
    s4 = (obs[3] - norm.obs_mean.numpy()) / norm.obs_std.numpy()
    np.testing.assert_allclose(states[:, -1].numpy(), s4, rtol=1e-5, atol=1e-6)
    # resetting one environment mid-chunk: it predicts at its next step, the other keeps executing its queue
    policy.reset([0])
    calls.clear()
    policy.select_action(obs[0])
    assert len(calls) == 1 and calls[0][0].shape[0] == 1 and calls[0][2][0, -1] == 0


def test_horizon_must_fit_the_chunk_and_the_chunk_fits_eval_override(trajs, tmp_path):
    with pytest.raises(ValueError, match=r"action_horizon=5 must be in \[1, action_chunk=4\]"):
        get_preset("bet", action_chunk=4, action_horizon=5)
    with pytest.raises(ValueError, match="action_chunk must be >= 1"):
        get_preset("bet", action_chunk=0)
    model, _ = build("dt", trajs)  # action_chunk 1: the paper's model, one action per index
    assert model.action_decoder[-1].out_features == P and model.cfg.future_actions == 0


def test_train_and_eval_cli_with_chunks(tmp_path, capsys):
    demos = tmp_path / "demos"
    cotpc_main(["demos", "maze", "--out", str(demos), "--train", "12", "--test", "4", "--val", "3"])
    run = tmp_path / "bet"
    cotpc_main(["train", "--data", str(demos / "train.h5"), "--policy", "bet", "--out", str(run), "--iters", "3",
                "--batch-size", "8", "--bf16", "False", "--threads", "1", "--no-progress", "--action-chunk", "4",
                "--action-horizon", "4", "--val-every", "3", "--n-centres", "32"])
    policy = json.loads((run / "config.json").read_text())["policy"]
    assert (policy["action_chunk"], policy["action_horizon"]) == (4, 4)
    cotpc_main(["eval", str(run), "--split", "val", "--episodes", "2"])
    assert json.loads((run / "eval_val.json").read_text())["summary"]["episodes"] == 2
    cotpc_main(["eval", str(run), "--split", "val", "--episodes", "2", "--action-horizon", "1"])
    assert json.loads((run / "eval_val_ah1.json").read_text())["summary"]["action_horizon"] == 1
    with pytest.raises(SystemExit, match="action_chunk=4"):
        load_for_eval(run, overrides={"action_horizon": 5})
    capsys.readouterr()
    with pytest.raises(SystemExit):
        cotpc_main(["train", "--data", str(demos / "train.h5"), "--policy", "bet", "--out", str(tmp_path / "x"),
                    "--iters", "1", "--action-chunk", "0"])
    assert "--action-chunk must be a finite number >= 1, got 0" in capsys.readouterr().err
