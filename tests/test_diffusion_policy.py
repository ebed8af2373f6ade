"""Diffusion Policy (``--policy dp``): its size, the training windows' action chunks, the noise schedule and sampler
on a 2-mode toy distribution (which an MSE head averages away), the EMA, checkpoints with seeded sampling, the
per-environment action queue, clear errors, and ``cotpc train --policy dp`` through the real CLI."""

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from cotpc.cli.main import main as cotpc_main
from cotpc.data import save_trajectories
from cotpc.data.dataset import Stats, WindowDataset, synthetic_trajectories
from cotpc.policies import DPConfig, Policy, get_preset, load_policy, make_model, save_checkpoint
from cotpc.policies.base import mlp

Q, P = 6, 2
# a small U-Net (the default's structure) so the tests stay fast on 2 cores
TINY = dict(down_dims=(16, 32), step_embed_dim=16, n_groups=4)


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_model(seed=0, **overrides):
    torch.manual_seed(seed)
    model = make_model(DPConfig(**{**TINY, **overrides}), Q, P, 0)
    with torch.no_grad():  # statistics that are not the identity, and EMA weights unlike the trained ones
        model.norm.obs_mean.normal_()
        model.norm.obs_std.uniform_(0.5, 2.0)
        model.norm.act_mean.normal_()
        model.norm.act_std.uniform_(0.5, 2.0)
        model.after_optimizer_step()  # the first update copies the weights
        for prm in model.net.parameters():
            prm.add_(0.1 * torch.randn_like(prm))
        model.after_optimizer_step()
    return model.eval()


def test_default_size_is_the_papers_about_1_2m_parameters():
    for (q, p), (lo, hi) in {(10, 2): (1.0e6, 1.3e6), (43, 8): (1.1e6, 1.4e6)}.items():  # maze, ManiSkill shapes
        n = make_model(get_preset("dp"), q, p, 0).n_params
        print(f"Diffusion Policy parameters, {q}-dim states, {p}-dim actions: {n:,}")
        assert lo < n < hi, n
    cfg = get_preset("dp", context=20, n_centres=1024)  # the trainer's task settings do not apply to DP
    assert (cfg.obs_horizon, cfg.pred_horizon, cfg.action_horizon, cfg.train_steps) == (2, 16, 8, 100)
    assert cfg.window == 2 and cfg.future_actions == 14


def test_windows_carry_the_action_chunk_padded_as_dp_pads():
    trajs = synthetic_trajectories(n_episodes=3, obs_dim=Q, action_dim=P, length=20, seed=0)
    identity = Stats(torch.zeros(Q), torch.ones(Q), torch.zeros(P), torch.ones(P))
    ds = WindowDataset(trajs, [0, 1, 2], 2, identity, future_actions=14)
    ep = trajs.episodes[0]
    n = ep.num_steps
    for t in (0, 5, n - 3, n - 1):  # episode 0: its first step, the middle, near and at its end
        b = ds.windows(torch.tensor([t]))
        np.testing.assert_array_equal(b["states"][0].numpy(), ep.obs[[max(t - 1, 0), t]])  # s(-1) repeats s(0)
        chunk = torch.cat([b["actions"], b["future_actions"]], dim=1)[0].numpy()
        # a(t-1) .. a(t+14): a(-1) repeats a(0), past the end the last action repeats
        np.testing.assert_array_equal(chunk, ep.actions[np.clip(np.arange(t - 1, t + 15), 0, n - 1)])
    assert "future_actions" not in WindowDataset(trajs, [0], 2, identity).windows(torch.tensor([0]))  # as before


def test_two_modes_survive_the_noise_schedule_and_sampler_where_mse_averages_them():
    """A 1-D action that is +1 or -1 with equal chance, whatever the state: DDPM training and DDIM sampling keep
    both modes; an MSE regression predicts their mean, an action no demo took."""
    cfg = DPConfig(**TINY, pred_horizon=4, action_horizon=2)
    torch.manual_seed(0)
    model = make_model(cfg, 1, 1, 0)
    # the squared-cosine schedule runs from (almost) clean to (almost) pure noise in train_steps steps
    alpha_bar = model.train_scheduler.alphas_cumprod
    assert len(alpha_bar) == 100 and alpha_bar[0] > 0.999 and alpha_bar[-1] < 1e-4
    mse = mlp([1, 64, 64, 1])
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3)
    opt_mse = torch.optim.AdamW(mse.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(1)
    for _ in range(300):
        mode = torch.randint(2, (128, 1, 1), generator=g).float() * 2 - 1
        a = mode + 0.05 * torch.randn(128, cfg.pred_horizon, 1, generator=g)
        states = torch.zeros(128, 2, 1)
        loss, _ = model({"states": states, "actions": a[:, :2], "future_actions": a[:, 2:]})
        opt.zero_grad()
        loss.backward()
        opt.step()
        model.after_optimizer_step()
        mse_loss = ((mse(states[:, -1]) - a[:, 1]) ** 2).mean()
        opt_mse.zero_grad()
        mse_loss.backward()
        opt_mse.step()
    samples = model.eval().predict({"states": torch.zeros(400, 2, 1)}, torch.Generator().manual_seed(0))[:, 0]
    share_up = float((samples > 0).float().mean())
    near_a_mode = float(((samples.abs() - 1).abs() < 0.3).float().mean())
    mean_pred = float(mse(torch.zeros(1, 1)).detach())
    print(f"DP: {share_up:.0%} of samples at +1, {near_a_mode:.0%} near a mode; MSE head: {mean_pred:+.3f}")
    assert 0.25 <= share_up <= 0.75 and near_a_mode > 0.8
    assert abs(mean_pred) < 0.3  # the MSE head sits between the modes


def test_ema_weights_are_what_acts_and_are_saved(tmp_path):
    model = tiny_model()
    states = torch.randn(3, 2, Q)
    before = model.predict({"states": states}, torch.Generator().manual_seed(0))
    with torch.no_grad():
        for prm in model.net.parameters():  # the trained weights do not act...
            prm.add_(1.0)
    torch.testing.assert_close(model.predict({"states": states}, torch.Generator().manual_seed(0)), before)
    assert sum(p.numel() for p in model.parameters()) == model.n_params  # ...and the EMA copy is not trained
    save_checkpoint(tmp_path / "run", model, {})
    saved = load_file(str(tmp_path / "run" / "model.safetensors"))
    assert int(saved["ema_updates"]) == 2 and any(k.startswith("ema.") for k in saved)
    # decay: the first update copies, later ones move by (1 + k)^-0.75 of the gap
    w, e = model.net.final[1].weight, model.ema.final[1].weight
    gap = (w - e).clone()
    model.after_optimizer_step()
    torch.testing.assert_close(w - model.ema.final[1].weight, gap * (1 - 3 ** -0.75))


def test_checkpoint_round_trip_gives_identical_actions_for_a_fixed_seed(tmp_path):
    model = tiny_model()
    save_checkpoint(tmp_path / "run", model, {"max_timestep": 0})
    runs = []
    for policy in (Policy(model), load_policy(tmp_path / "run")):
        torch.manual_seed(123)
        rng = np.random.default_rng(0)
        runs.append(np.stack([policy.select_action(rng.normal(size=(3, Q)).astype(np.float32)) for _ in range(20)]))
    assert runs[0].shape == (20, 3, P) and np.isfinite(runs[0]).all()
    np.testing.assert_array_equal(runs[0], runs[1])
    assert json.loads((tmp_path / "run" / "config.json").read_text())["policy"]["family"] == "diffusion"


def test_the_action_queue_refills_per_environment_after_reset_mask():
    model = tiny_model(action_horizon=4, pred_horizon=8)
    policy = Policy(model)
    norm = model.norm
    planned, chunks = [], []  # the state histories each sampler call planned from, and the chunks it gave
    sample = model.predict_chunk

    def recording(states):
        planned.append(states.clone())
        chunks.append(sample(states))
        return chunks[-1]

    model.predict_chunk = recording
    obs = [np.full((3, Q), t, np.float32) for t in range(8)]
    state = [((torch.from_numpy(o) - norm.obs_mean) / norm.obs_std).numpy() for o in obs]  # normalised
    acts = [policy.select_action(obs[t]) for t in range(2)]
    assert [len(s) for s in planned] == [3]  # every environment planned at its first step, in one call
    np.testing.assert_allclose(planned[0].numpy(), np.stack([state[0], state[0]], axis=1))  # s(0) repeated
    for t in range(2):  # the chunk is executed in order
        np.testing.assert_allclose(acts[t], (chunks[0][:, t] * norm.act_std + norm.act_mean).numpy(), rtol=1e-5)
    policy.reset(np.array([False, True, False]))
    policy.select_action(obs[2])
    assert [len(s) for s in planned] == [3, 1]  # only the reset environment re-plans...
    np.testing.assert_allclose(planned[1][0].numpy(), [state[2][1], state[2][1]])  # ...from a fresh history
    policy.select_action(obs[3])
    assert len(planned) == 2
    policy.select_action(obs[4])  # envs 0 and 2 have executed their 4 actions; env 1 has 2 left
    assert [len(s) for s in planned] == [3, 1, 2]
    np.testing.assert_allclose(planned[2].numpy(), np.stack([state[3][[0, 2]], state[4][[0, 2]]], axis=1))
    policy.select_action(obs[5])
    policy.select_action(obs[6])
    assert [len(s) for s in planned] == [3, 1, 2, 1]  # env 1, 4 steps after its reset
    policy.reset()  # all environments: a new batch size is fine
    policy.select_action(np.zeros((2, Q), np.float32))
    assert len(planned[-1]) == 2


def test_a_wrong_dimension_observation_is_a_clear_error():
    policy = Policy(tiny_model())
    with pytest.raises(ValueError, match=f"{Q}-dim observations"):
        policy.select_action(np.zeros((2, Q + 1), np.float32))
    with pytest.raises(ValueError, match="batch"):
        policy.select_action(np.zeros(Q, np.float32))
    policy.select_action(np.zeros((2, Q), np.float32))
    with pytest.raises(ValueError, match="reset"):
        policy.select_action(np.zeros((3, Q), np.float32))
    with pytest.raises(ValueError, match="future_actions"):  # a window without the chunk, e.g. another family's
        policy.model.loss({"states": torch.zeros(2, 2, Q), "actions": torch.zeros(2, 2, P)})
    with pytest.raises(ValueError, match="pred_horizon"):
        DPConfig(obs_horizon=2, action_horizon=16).validate()


def test_cotpc_train_policy_dp_through_the_cli(tmp_path, capsys):
    data = tmp_path / "demos.h5"
    save_trajectories(data, synthetic_trajectories(n_episodes=10, obs_dim=Q, action_dim=P, length=20, seed=0))
    with pytest.raises(SystemExit):
        cotpc_main(["train", "--help"])
    assert "dp" in capsys.readouterr().out
    run = tmp_path / "run"
    cotpc_main(["train", "--data", str(data), "--policy", "dp", "--out", str(run), "--iters", "4",
                "--batch-size", "32", "--val-every", "2", "--log-every", "2", "--bf16", "False", "--threads", "1",
                "--no-progress"])
    out = capsys.readouterr().out
    assert "dp: 4/4 iters" in out and "ms/iter" in out
    info = json.loads((run / "config.json").read_text())
    assert info["policy"]["family"] == "diffusion" and info["step"] == 4
    assert info["val"]["last_action_err"] > 0 and info["val"]["last_denoise"] > 0
    assert (run / "best" / "model.safetensors").exists()
    assert int(load_file(str(run / "model.safetensors"))["ema_updates"]) == 4  # the loop's hook ran each step
    policy = load_policy(run)
    assert policy.select_action(np.zeros((2, Q), np.float32)).shape == (2, P)


def test_resume_continues_the_ema_and_the_noise_exactly(tmp_path):
    from cotpc.training import TrainConfig, train

    data = tmp_path / "demos.h5"
    save_trajectories(data, synthetic_trajectories(n_episodes=6, obs_dim=Q, action_dim=P, length=20, seed=0))
    kw = dict(data=data, policy="dp", iters=6, ckpt_every=3, batch_size=16, val_every=3, bf16=False,
              progress=False, threads=1)
    full = train(TrainConfig(out=tmp_path / "full", **kw))
    train(TrainConfig(out=tmp_path / "part", stop_after=3, **kw))
    part = train(TrainConfig(out=tmp_path / "part", resume=True, **kw))
    a, b = load_file(str(full / "model.safetensors")), load_file(str(part / "model.safetensors"))
    assert a.keys() == b.keys() and int(b["ema_updates"]) == 6
    for k in a:
        assert torch.equal(a[k], b[k]), k
