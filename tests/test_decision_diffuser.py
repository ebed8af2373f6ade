"""Decision Diffuser (``--policy dd``): its size, the training windows' future states padded at both ends, DD's
noise schedule, a toy system learned by the state sampler and the inverse dynamics together, checkpoints with
seeded sampling, per-environment planning after ``reset(mask)``, clear errors, and ``cotpc train --policy dd``
through the real CLI (with a bit-exact ``--resume``)."""

import json

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from cotpc.cli.main import main as cotpc_main
from cotpc.data import save_trajectories
from cotpc.data.dataset import Stats, WindowDataset, synthetic_trajectories
from cotpc.data.trajectories import Episode, TrajectorySet
from cotpc.policies import DDConfig, Policy, get_preset, load_policy, make_model, save_checkpoint

Q, P = 6, 2
# a small U-Net (the default's structure) and a short plan, so the tests stay fast on 2 cores
TINY = dict(history=4, horizon=4, down_dims=(16, 32), step_embed_dim=16, n_groups=4, inv_hidden=64)


@pytest.fixture(autouse=True)
def one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def tiny_model(seed=0, **overrides):
    torch.manual_seed(seed)
    model = make_model(DDConfig(**{**TINY, **overrides}), Q, P, 0)
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


def test_default_size_is_the_papers_about_1_6m_parameters():
    for q, p in ((10, 2), (43, 8)):  # maze, ManiSkill shapes
        model = make_model(get_preset("dd"), q, p, 0)
        n, n_inv = model.n_params, sum(x.numel() for x in model.net.inv.parameters())
        print(f"Decision Diffuser parameters, {q}-dim states, {p}-dim actions: {n:,} "
              f"(U-Net {n - n_inv:,}, inverse dynamics {n_inv:,})")
        assert 1.5e6 < n < 1.8e6, n
    cfg = get_preset("dd", context=10, n_centres=1024)  # the trainer's task settings do not apply to DD
    assert (cfg.history, cfg.horizon, cfg.train_steps, cfg.action_horizon) == (20, 4, 100, 1)
    assert cfg.window == 20 and cfg.future_states == 4 and cfg.future_actions == 0
    assert all(c.future_states == 0 for name, c in __import__("cotpc.policies").policies.PRESETS.items()
               if name != "dd")  # the other families' windows are unchanged


def test_the_noise_schedule_is_dds_cosine_schedule():
    """DD's ``cosine_beta_schedule`` (Nichol & Dhariwal, s = 0.008, betas clipped at 0.999), 100 steps."""
    model = make_model(DDConfig(**TINY), Q, P, 0)
    steps, s = 100, 0.008
    x = np.linspace(0, steps + 1, steps + 1)
    alpha_bar = np.cos(((x / (steps + 1)) + s) / (1 + s) * np.pi * 0.5) ** 2
    betas = np.clip(1 - alpha_bar[1:] / alpha_bar[:-1], 0, 0.999)
    np.testing.assert_allclose(model.train_scheduler.betas.numpy(), betas, rtol=1e-5, atol=1e-7)
    assert model.train_scheduler.config.prediction_type == "epsilon"


def test_windows_carry_future_states_padded_at_both_ends():
    trajs = synthetic_trajectories(n_episodes=3, obs_dim=Q, action_dim=P, length=20, seed=0)
    identity = Stats(torch.zeros(Q), torch.ones(Q), torch.zeros(P), torch.ones(P))
    ds = WindowDataset(trajs, [0, 1, 2], 3, identity, future_actions=2, future_states=4)
    for e in (0, 1):
        ep, start = trajs.episodes[e], sum(x.num_steps for x in trajs.episodes[:e])
        n = ep.num_steps  # s(0..n): s(n) is the final observation, which has no action
        for t in (0, 1, 5, n - 3, n - 1):  # the start (padded history), the middle, near and at the end
            b = ds.windows(torch.tensor([start + t]))
            # the history s(t-2) .. s(t) repeats s(0) before the episode; the future s(t+1) .. s(t+4) reaches the
            # final observation s(n) and repeats it
            np.testing.assert_array_equal(b["states"][0].numpy(), ep.obs[np.clip(np.arange(t - 2, t + 1), 0, None)])
            np.testing.assert_array_equal(b["future_states"][0].numpy(), ep.obs[np.minimum(np.arange(t + 1, t + 5), n)])
            np.testing.assert_array_equal(b["valid"][0].numpy(), np.arange(t - 2, t + 1) >= 0)
            np.testing.assert_array_equal(b["future_actions"][0].numpy(),  # unchanged beside it
                                          ep.actions[np.minimum(np.arange(t + 1, t + 3), n - 1)])
    assert "future_states" not in WindowDataset(trajs, [0], 3, identity).windows(torch.tensor([0]))  # as before


def moving_point_demos(n_episodes=32, length=6) -> TrajectorySet:
    """A 1-D point that moves by its action, always +1 in half of the episodes and always -1 in the other half,
    from 0: the next state (and so the action) is deterministic once the history shows the direction."""
    episodes = []
    for i in range(n_episodes):
        d = 1.0 if i % 2 else -1.0
        obs = (d * np.arange(length + 1, dtype=np.float32))[:, None]
        episodes.append(Episode(obs=obs, actions=np.full((length, 1), d, np.float32),
                                success=np.arange(length) == length - 1, episode_id=i, reset_kwargs={"seed": i}))
    return TrajectorySet(episodes=episodes, env_info={"env_id": "Toy-v0", "env_kwargs": {}, "max_episode_steps": 8})


def test_sampler_and_inverse_dynamics_learn_a_toy_system():
    """After a short training, the sampled next state continues the history's direction and the inverse dynamics
    of (s(t), sampled s(t+1)) gives the demo's action. An unconditioned sampler would get the direction right
    half of the time."""
    trajs = moving_point_demos()
    cfg = DDConfig(**TINY)
    obs = np.concatenate([e.obs[:-1] for e in trajs.episodes])
    act = np.concatenate([e.actions for e in trajs.episodes])
    stats = Stats.of(obs, act)
    ds = WindowDataset(trajs, list(range(len(trajs))), cfg.window, stats, future_states=cfg.future_states)
    torch.manual_seed(0)
    model = make_model(cfg, 1, 1, 0)
    for name, v in vars(stats).items():
        getattr(model.norm, name).copy_(v)
    opt = torch.optim.AdamW(model.parameters(), lr=2e-3)
    g = torch.Generator().manual_seed(1)
    for _ in range(400):
        loss, _ = model(ds.sample(64, g))
        opt.zero_grad()
        loss.backward()
        opt.step()
        model.after_optimizer_step()
    model.eval()
    ends = torch.nonzero(ds.timesteps >= 1).flatten()  # the direction is visible from the second step on
    batch = ds.windows(ends)
    gen = torch.Generator().manual_seed(0)
    plan = model.sample(batch["states"], generator=gen) * stats.obs_std + stats.obs_mean
    s_t = batch["states"][:, -1] * stats.obs_std + stats.obs_mean
    true_a = batch["actions"][:, -1] * stats.act_std + stats.act_mean
    state_err = (plan[:, cfg.history] - (s_t + true_a)).abs().flatten()
    a = model.predict(batch, torch.Generator().manual_seed(0)) * stats.act_std + stats.act_mean
    action_err = (a - true_a).abs().flatten()
    right_way = float((torch.sign(a) == torch.sign(true_a)).float().mean())
    close_s, close_a = float((state_err < 0.25).float().mean()), float((action_err < 0.25).float().mean())
    print(f"DD toy: next state within 0.25 of the demo's in {close_s:.0%} of windows (median error "
          f"{state_err.median():.3f}), action within 0.25 in {close_a:.0%}, right direction in {right_way:.0%}")
    assert state_err.median() < 0.15 and close_s > 0.6
    assert action_err.median() < 0.1 and close_a > 0.75 and right_way > 0.9
    # the inverse dynamics alone, on the demo's own transitions, is exact
    inv = model.ema.inverse(batch["states"][:, -1], batch["future_states"][:, 0]) * stats.act_std + stats.act_mean
    assert (inv - true_a).abs().max() < 0.05
    # the validation diagnostics: the plan's next state is far closer than an untrained network's (the mean
    # squared error is dominated by the few wrong-way samples, so it is not below one step's size, copy_err), and at
    # the noisiest step the trained network hands the noise back
    m = model.inference_metrics(batch)
    untrained = make_model(cfg, 1, 1, 0).eval()
    for name, v in vars(stats).items():
        getattr(untrained.norm, name).copy_(v)
    u = untrained.inference_metrics(batch)
    print(f"DD toy diagnostics, trained / untrained: state_err {m['state_err']:.4f} / {u['state_err']:.4f}, "
          f"copy_err {m['copy_err']:.4f}, denoise_max_noise {m['denoise_max_noise']:.4f} / {u['denoise_max_noise']:.4f}")
    assert m["copy_err"] == u["copy_err"] > 0  # a property of the data alone
    assert m["state_err"] < 0.05 * u["state_err"] and m["state_err"] < 5 * m["copy_err"] < u["state_err"]
    assert m["denoise_max_noise"] < 0.1 < u["denoise_max_noise"]


def test_ema_weights_are_what_acts_and_are_saved(tmp_path):
    model = tiny_model()
    states = torch.randn(3, TINY["history"], Q)
    before = model.predict({"states": states}, torch.Generator().manual_seed(0))
    with torch.no_grad():
        for prm in model.net.parameters():  # the trained weights (U-Net and inverse dynamics) do not act...
            prm.add_(1.0)
    torch.testing.assert_close(model.predict({"states": states}, torch.Generator().manual_seed(0)), before)
    assert sum(p.numel() for p in model.parameters()) == model.n_params  # ...and the EMA copy is not trained
    save_checkpoint(tmp_path / "run", model, {})
    saved = load_file(str(tmp_path / "run" / "model.safetensors"))
    assert int(saved["ema_updates"]) == 2 and any(k.startswith("ema.inv.") for k in saved)
    assert any(k.startswith("ema.unet.") for k in saved) and "norm.obs_std" in saved


def test_sampled_plans_keep_the_history():
    model = tiny_model()
    states = torch.randn(5, TINY["history"], Q)
    plan = model.sample(states, generator=torch.Generator().manual_seed(0))
    assert plan.shape == (5, TINY["history"] + TINY["horizon"], Q)
    torch.testing.assert_close(plan[:, :TINY["history"]], states)


def test_checkpoint_round_trip_gives_identical_actions_for_a_fixed_seed(tmp_path):
    model = tiny_model()
    save_checkpoint(tmp_path / "run", model, {"max_timestep": 0})
    runs = []
    for policy in (Policy(model), load_policy(tmp_path / "run")):
        torch.manual_seed(123)
        rng = np.random.default_rng(0)
        runs.append(np.stack([policy.select_action(rng.normal(size=(3, Q)).astype(np.float32)) for _ in range(8)]))
    assert runs[0].shape == (8, 3, P) and np.isfinite(runs[0]).all()
    np.testing.assert_array_equal(runs[0], runs[1])
    info = json.loads((tmp_path / "run" / "config.json").read_text())
    assert info["policy"]["family"] == "decision-diffuser" and info["policy"]["history"] == TINY["history"]


@pytest.mark.parametrize("action_horizon", [1, 2])
def test_each_environment_plans_from_its_own_history_after_reset_mask(action_horizon):
    model = tiny_model(action_horizon=action_horizon)
    policy = Policy(model)
    norm, H = model.norm, TINY["history"]
    planned, chunks = [], []  # the state histories each sampler call planned from, and the actions it gave
    predict_chunk = model.predict_chunk

    def recording(states):
        planned.append(states.clone())
        chunks.append(predict_chunk(states))
        return chunks[-1]

    model.predict_chunk = recording
    obs = [np.full((3, Q), t, np.float32) + np.arange(3, dtype=np.float32)[:, None] for t in range(10)]
    state = [((torch.from_numpy(o) - norm.obs_mean) / norm.obs_std).numpy() for o in obs]  # normalised
    a0 = policy.select_action(obs[0])
    assert [len(s) for s in planned] == [3]  # every environment planned at its first step, in one call
    np.testing.assert_allclose(planned[0].numpy(), np.repeat(state[0][:, None], H, axis=1))  # s(0) padded
    np.testing.assert_allclose(a0, (chunks[0][:, 0] * norm.act_std + norm.act_mean).numpy(), rtol=1e-5)
    policy.reset(np.array([False, True, False]))
    a1 = policy.select_action(obs[1])
    fresh = np.repeat(state[1][1][None], H, axis=0)  # env 1 plans from a fresh history
    if action_horizon == 1:  # DD's default: every environment plans at every step
        assert [len(s) for s in planned] == [3, 3]
        np.testing.assert_allclose(planned[1][1].numpy(), fresh)
        np.testing.assert_allclose(planned[1][0].numpy(), np.stack([state[t][0] for t in (0, 0, 0, 1)]))
    else:  # only the reset environment plans; envs 0 and 2 execute their second queued action
        assert [len(s) for s in planned] == [3, 1]
        np.testing.assert_allclose(planned[1][0].numpy(), fresh)
        np.testing.assert_allclose(a1[[0, 2]], (chunks[0][[0, 2], 1] * norm.act_std + norm.act_mean).numpy(),
                                   rtol=1e-5)
        policy.select_action(obs[2])
        assert [len(s) for s in planned] == [3, 1, 2]
        np.testing.assert_allclose(planned[2].numpy(), np.stack([state[t][[0, 2]] for t in (0, 0, 1, 2)], axis=1))
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
    with pytest.raises(ValueError, match="future_states"):  # a window without the future, e.g. another family's
        policy.model.loss({"states": torch.zeros(2, 4, Q), "actions": torch.zeros(2, 4, P)})
    with pytest.raises(ValueError, match="action_horizon"):
        DDConfig(horizon=4, action_horizon=5).validate()
    with pytest.raises(ValueError, match="divisible"):
        DDConfig(history=10, horizon=3).validate()


def test_cotpc_train_policy_dd_through_the_cli(tmp_path, capsys):
    data = tmp_path / "demos.h5"
    save_trajectories(data, synthetic_trajectories(n_episodes=10, obs_dim=Q, action_dim=P, length=20, seed=0))
    with pytest.raises(SystemExit):
        cotpc_main(["train", "--help"])
    assert "dd" in capsys.readouterr().out
    run = tmp_path / "run"
    cotpc_main(["train", "--data", str(data), "--policy", "dd", "--out", str(run), "--iters", "4",
                "--batch-size", "16", "--val-every", "2", "--log-every", "2", "--bf16", "False", "--threads", "1",
                "--no-progress"])
    out = capsys.readouterr().out
    assert "dd: 4/4 iters" in out and "ms/iter" in out
    info = json.loads((run / "config.json").read_text())
    assert info["policy"]["family"] == "decision-diffuser" and info["step"] == 4
    val = info["val"]
    assert val["last_action_err"] > 0 and val["last_state_err"] > 0 and val["last_denoise"] > 0 and val["all_inv"] > 0
    assert (run / "best" / "model.safetensors").exists()
    assert int(load_file(str(run / "model.safetensors"))["ema_updates"]) == 4  # the loop's hook ran each step
    policy = load_policy(run)
    assert policy.select_action(np.zeros((2, Q), np.float32)).shape == (2, P)


def test_resume_continues_the_ema_and_the_noise_exactly(tmp_path):
    from cotpc.training import TrainConfig, train

    data = tmp_path / "demos.h5"
    save_trajectories(data, synthetic_trajectories(n_episodes=6, obs_dim=Q, action_dim=P, length=20, seed=0))
    kw = dict(data=data, policy="dd", iters=6, ckpt_every=3, batch_size=8, val_every=3, bf16=False,
              progress=False, threads=1)
    full = train(TrainConfig(out=tmp_path / "full", **kw))
    train(TrainConfig(out=tmp_path / "part", stop_after=3, **kw))
    part = train(TrainConfig(out=tmp_path / "part", resume=True, **kw))
    a, b = load_file(str(full / "model.safetensors")), load_file(str(part / "model.safetensors"))
    assert a.keys() == b.keys() and int(b["ema_updates"]) == 6
    for k in a:
        assert torch.equal(a[k], b[k]), k
