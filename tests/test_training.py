"""The training loop: run directory contents, exact resume, clear errors, bf16 tracking fp32, the CLI."""

import contextlib
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file

from cotpc.data import load_trajectories, save_trajectories
from cotpc.data.dataset import MissingSubskillsError, Stats, WindowDataset, synthetic_trajectories
from cotpc.policies import CheckpointError, load_policy
from cotpc.training import TrainConfig, train
from cotpc.training.train import WeightAverage, main as train_main

TINY = dict(context=4, d_model=32, n_heads=4, n_layers=2, n_centres=8, batch_size=32, progress=False,
            val_every=10, log_every=5, warmup_iters=4)


def window_dataset(data, context, cot_targets=(), episodes=None, **kw):
    """(trajectories, WindowDataset) of a file's episodes (default: all), normalised with all episodes' statistics."""
    trajs = load_trajectories(data)
    stats = Stats.of(np.concatenate([e.obs[:-1] for e in trajs.episodes]),
                     np.concatenate([e.actions for e in trajs.episodes]))
    eps = list(range(len(trajs))) if episodes is None else episodes
    return trajs, WindowDataset(trajs, eps, context, stats, cot_targets, **kw)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    path = tmp_path_factory.mktemp("data") / "demos.h5"
    save_trajectories(path, synthetic_trajectories(n_episodes=10, obs_dim=6, action_dim=2, length=20, seed=0))
    return path


def test_train_writes_a_loadable_run(data, tmp_path):
    run = train(TrainConfig(data=data, out=tmp_path / "run", iters=20, ckpt_every=10, **TINY))
    for f in ("config.json", "model.safetensors", "training_state.pt", "best/model.safetensors"):
        assert (run / f).exists(), f
    info = json.loads((run / "config.json").read_text())
    assert info["step"] == 20 and info["policy"]["name"] == "cotpc" and info["obs_dim"] == 6
    assert info["val"]["last_action_err"] > 0 and info["val"]["all_bc"] > 0 and len(info["dataset"]["val_episode_ids"]) == 1
    assert list((run / "tb").iterdir())
    pol = load_policy(run)
    assert pol.select_action(np.zeros((2, 6), np.float32)).shape == (2, 2)
    with pytest.raises(FileExistsError, match="--resume"):
        train(TrainConfig(data=data, out=tmp_path / "run", iters=20, **TINY))


@pytest.mark.parametrize("policy", ["cotpc", "bc"])
def test_resume_reaches_the_same_weights(data, tmp_path, policy):
    kw = dict(TINY, bf16=True)
    if policy == "cotpc":
        kw["dropout"] = 0.1  # dropout and state noise: the RNG states must resume too
        kw["state_noise"] = 0.1
        kw["boundary_weight"] = 3.0  # weighted window ends: the sampler's draws must resume too
    full = train(TrainConfig(data=data, policy=policy, out=tmp_path / "full", iters=16, ckpt_every=8, **kw))
    part = tmp_path / "part"
    train(TrainConfig(data=data, policy=policy, out=part, iters=16, ckpt_every=8, stop_after=8, **kw))
    assert json.loads((part / "config.json").read_text())["step"] == 8
    train(TrainConfig(data=data, policy=policy, out=part, iters=16, ckpt_every=8, resume=True, **kw))
    a, b = load_file(str(full / "model.safetensors")), load_file(str(part / "model.safetensors"))
    assert a.keys() == b.keys()
    for k in a:
        assert torch.equal(a[k], b[k]), k


def test_weight_average_follows_the_warm_up_rule():
    net = torch.nn.Linear(3, 2)
    average = WeightAverage(net, max_decay=0.5)
    assert not list(average.model.parameters())  # frozen: buffers only
    average.update(net, 0)  # the first update copies
    assert torch.equal(average.model.weight, net.weight)
    before = net.weight.detach().clone()
    with torch.no_grad():
        net.weight.add_(1.0)
    average.update(net, 1)
    decay = 1 - 2 ** -0.75  # below the cap 0.5
    assert torch.allclose(average.model.weight, decay * before + (1 - decay) * net.weight)
    assert average.decay(10_000) == 0.5


def test_averaged_weights_are_saved_validated_and_resumed_exactly(data, tmp_path):
    kw = dict(TINY, policy="bet", ema_decay=0.9, keep_checkpoints=True)
    full = train(TrainConfig(data=data, out=tmp_path / "full", iters=16, ckpt_every=8, **kw))
    state = torch.load(full / "training_state.pt", weights_only=False)
    saved = load_file(str(full / "model.safetensors"))
    for name, value in state["ema"].items():  # the checkpoint holds the average, training_state both
        assert torch.equal(saved[name], value), name
    assert any(not torch.equal(state["ema"][n], state["model"][n]) for n in state["model"] if "gpt" in n)
    assert load_policy(full / "best").select_action(np.zeros((1, 6), np.float32)).shape == (1, 2)
    part = tmp_path / "part"
    train(TrainConfig(data=data, out=part, iters=16, ckpt_every=8, stop_after=8, **kw))
    train(TrainConfig(data=data, out=part, iters=16, ckpt_every=8, resume=True, **kw))
    resumed = load_file(str(part / "model.safetensors"))
    assert all(torch.equal(saved[n], resumed[n]) for n in saved)
    with pytest.raises(CheckpointError, match="--ema-decay"):  # the average must not change on resume
        train(TrainConfig(data=data, out=part, iters=24, resume=True, **dict(kw, ema_decay=0.0)))
    with pytest.raises(ValueError, match="averages its own weights"):
        train(TrainConfig(data=data, out=tmp_path / "dp", iters=2, **dict(kw, policy="dp")))


def test_more_kmeans_centres_than_training_actions_is_a_clear_error(data, tmp_path, capsys):
    with pytest.raises(SystemExit):
        train_main(["--data", str(data), "--policy", "bet", "--out", str(tmp_path / "run"), "--iters", "1",
                    "--n-centres", "100000", "--no-progress"])
    assert "100000 k-means centres need at least as many training actions" in capsys.readouterr().err


@pytest.mark.parametrize("flags, says", [
    (["--iters", "0"], "--iters must be a finite number >= 1, got 0"),
    (["--batch-size", "0"], "--batch-size must be"),
    (["--context", "0"], "--context must be"),  # not silently the task's default
    (["--lr", "0"], "--lr must be a finite number > 0"),
    (["--lr", "nan"], "--lr must be"),
    (["--dropout", "1.5"], "--dropout must be in [0, 1)"),
    (["--val-fraction", "1.5"], "--val-fraction must be in [0, 1), got 1.5"),  # not silently clamped
    (["--stop-after", "0"], "--stop-after must be"),
    (["--ema-decay", "1"], "--ema-decay must be in [0, 1), got 1"),
    (["--d-model", "30", "--n-heads", "8"], "--policy bet: d_model=30 must be divisible by n_heads=8"),
])
def test_flags_out_of_range_are_one_line_errors(data, tmp_path, capsys, flags, says):
    with pytest.raises(SystemExit) as stop:
        train_main(["--data", str(data), "--policy", "bet", "--out", str(tmp_path / "run"), "--no-progress", *flags])
    assert stop.value.code == 2 and says in capsys.readouterr().err
    assert not (tmp_path / "run").exists()


def test_resume_with_other_config_or_data_is_a_clear_error(data, tmp_path):
    train(TrainConfig(data=data, out=tmp_path / "run", iters=4, **TINY))
    with pytest.raises(CheckpointError, match="another configuration"):
        train(TrainConfig(data=data, policy="bet", out=tmp_path / "run", iters=8, resume=True, **TINY))
    other = tmp_path / "other.h5"
    save_trajectories(other, synthetic_trajectories(n_episodes=10, obs_dim=7, action_dim=2, length=20, seed=1))
    with pytest.raises(CheckpointError, match="dims"):
        train(TrainConfig(data=other, out=tmp_path / "run", iters=8, resume=True, **TINY))
    state = tmp_path / "run" / "training_state.pt"
    saved = state.read_bytes()
    state.write_bytes(saved[: len(saved) // 2])  # killed while copying: a truncated file
    with pytest.raises(CheckpointError, match="training_state.pt: cannot resume: not a readable training state"):
        train(TrainConfig(data=data, out=tmp_path / "run", iters=8, resume=True, **TINY))
    torch.save({"model": {}}, state)  # a foreign torch file under the name
    with pytest.raises(CheckpointError, match="not a cotpc training state"):
        train(TrainConfig(data=data, out=tmp_path / "run", iters=8, resume=True, **TINY))
    state.write_bytes(saved)
    train(TrainConfig(data=data, out=tmp_path / "run", iters=8, resume=True, **TINY))  # restored: resumes


def test_state_noise_perturbs_only_the_input_states(data):
    _, ds = window_dataset(data, 4, ("next", "last"))
    clean = ds.sample(64, torch.Generator().manual_seed(0))
    noisy = ds.sample(64, torch.Generator().manual_seed(0), state_noise=0.5)
    for k in ("actions", "cot", "timesteps", "valid", "cot_hide"):
        assert torch.equal(clean[k], noisy[k]), k
    diff = noisy["states"] - clean["states"]
    assert 0.4 < float(diff.std()) < 0.6  # the requested scale, in normalised units
    assert torch.equal(ds.sample(64, torch.Generator().manual_seed(0), state_noise=0.0)["states"], clean["states"])


@pytest.mark.parametrize("field, bad, used", [("state_noise", -0.1, 0.2), ("boundary_weight", -1.0, 2.0),
                                               ("obs_std_floor", -0.1, 0.5)])
def test_sampling_option_is_checked_and_kept_on_resume(data, tmp_path, field, bad, used):
    flag = "--" + field.replace("_", "-")
    with pytest.raises(ValueError, match=flag):
        train(TrainConfig(data=data, out=tmp_path / "bad", iters=2, **{field: bad}, **TINY))
    train(TrainConfig(data=data, out=tmp_path / "run", iters=4, **{field: used}, **TINY))
    with pytest.raises(CheckpointError, match=flag):
        train(TrainConfig(data=data, out=tmp_path / "run", iters=8, resume=True, **TINY))


@pytest.mark.parametrize("policy", ["bet", "cotpc", "bc"])  # deterministic policies: equal actions say it all
def test_ignored_observation_dimensions_never_reach_the_policy(data, tmp_path, policy):
    run = train(TrainConfig(data=data, policy=policy, out=tmp_path / "run", iters=4, ignore_obs=(1, 4), **TINY))
    std = load_file(str(run / "model.safetensors"))["norm.obs_std"]
    assert torch.isinf(std[[1, 4]]).all() and torch.isfinite(std[[0, 2, 3, 5]]).all()
    obs = np.random.default_rng(0).normal(size=(3, 6)).astype(np.float32)
    changed = obs.copy()
    changed[:, [1, 4]] += 100.0  # whatever the hidden dimensions hold, the actions are the same
    for n in range(3):  # over a growing context
        pol_a, pol_b = load_policy(run), load_policy(run)
        for t in range(n + 1):
            a, b = pol_a.select_action(obs), pol_b.select_action(changed)
        assert np.allclose(a, b, atol=1e-6), (n, a, b)
    changed[:, 0] += 100.0  # a dimension it does see changes them
    pol_a, pol_b = load_policy(run), load_policy(run)
    assert not np.allclose(pol_a.select_action(obs), pol_b.select_action(changed))


def test_obs_std_floor_bounds_what_a_near_constant_dimension_reads(tmp_path, capsys):
    """A dimension the demos barely move (Stack Cube: cube B's height) is scaled by 1 / std; --obs-std-floor caps
    that scale, in the checkpoint's statistics, so evaluation normalises as training did."""
    trajs = synthetic_trajectories(n_episodes=12, obs_dim=6, action_dim=2, length=20, seed=0)
    rng = np.random.default_rng(0)
    for ep in trajs.episodes:
        ep.obs[:, 3] = 0.02 + 1e-5 * rng.normal(size=len(ep.obs))  # resting on the table
    data = tmp_path / "demos.h5"
    save_trajectories(data, trajs)
    stats = Stats.of(np.concatenate([e.obs for e in trajs.episodes]), np.concatenate([e.actions for e in trajs.episodes]),
                     obs_std_floor=0.01)
    assert stats.obs_std[3] == pytest.approx(0.01) and (stats.obs_std[[0, 1, 2, 4, 5]] > 0.01).all()
    plain = train(TrainConfig(data=data, policy="bc", out=tmp_path / "plain", iters=2, **TINY))
    floored = train(TrainConfig(data=data, policy="bc", out=tmp_path / "floored", iters=2, obs_std_floor=0.01,
                                **TINY))
    assert "--obs-std-floor 0.01 raised the std of observation dimensions [3]" in capsys.readouterr().out
    std_plain = load_file(str(plain / "model.safetensors"))["norm.obs_std"]
    std_floored = load_file(str(floored / "model.safetensors"))["norm.obs_std"]
    assert std_plain[3] < 1e-4 and std_floored[3] == pytest.approx(0.01)
    assert torch.equal(std_plain[[0, 1, 2, 4, 5]], std_floored[[0, 1, 2, 4, 5]])
    # what the loaded policies read for a 1 cm move of that dimension: thousands of stds, or one
    assert 0.01 / float(load_policy(plain).model.norm.obs_std[3]) > 500
    assert 0.01 / float(load_policy(floored).model.norm.obs_std[3]) == pytest.approx(1.0)


def test_offset_from_reaches_the_offset_head_and_is_checked(data, tmp_path, capsys):
    run = train(TrainConfig(data=data, policy="cotpc-causal", out=tmp_path / "run", iters=2, offset_from="state",
                            **TINY))
    assert json.loads((run / "config.json").read_text())["policy"]["offset_from"] == "state"
    assert load_policy(run).model.cfg.offset_from == "state"
    dt = train(TrainConfig(data=data, policy="dt", out=tmp_path / "dt", iters=2, offset_from="cot", **TINY))
    assert json.loads((dt / "config.json").read_text())["policy"]["action_head"] == "mse"  # no offset head: ignored
    with pytest.raises(SystemExit) as stop:  # bet has no CoT tokens for its offset head to read
        train_main(["--data", str(data), "--policy", "bet", "--out", str(tmp_path / "bad"), "--no-progress",
                    "--offset-from", "cot"])
    assert stop.value.code == 2 and "--policy bet: reading a head from CoT tokens" in capsys.readouterr().err


def test_ignored_observation_dimensions_are_checked_and_kept_on_resume(data, tmp_path):
    with pytest.raises(ValueError, match="--ignore-obs 6: .* 6-dim observations"):
        train(TrainConfig(data=data, out=tmp_path / "bad", iters=2, ignore_obs=(6,), **TINY))
    train(TrainConfig(data=data, out=tmp_path / "run", iters=4, ignore_obs=(2,), **TINY))
    with pytest.raises(CheckpointError, match="--ignore-obs"):
        train(TrainConfig(data=data, out=tmp_path / "run", iters=8, resume=True, **TINY))


def test_kept_checkpoints_hold_their_own_step(data, tmp_path):
    """--keep-checkpoints links the files just written; later checkpoints must not change the earlier ones."""
    run = train(TrainConfig(data=data, out=tmp_path / "run", iters=12, ckpt_every=4, keep_checkpoints=True, **TINY))
    kept = sorted((run / "checkpoints").iterdir())
    assert [k.name for k in kept] == ["step_0000004", "step_0000008", "step_0000012"]
    weights = [load_file(str(k / "model.safetensors")) for k in kept]
    assert [json.loads((k / "config.json").read_text())["step"] for k in kept] == [4, 8, 12]
    name = next(n for n in weights[0] if weights[0][n].is_floating_point() and "norm" not in n)
    assert not torch.equal(weights[0][name], weights[1][name]) and not torch.equal(weights[1][name], weights[2][name])
    final = load_file(str(run / "model.safetensors"))
    assert all(torch.equal(final[n], weights[2][n]) for n in final)
    assert load_policy(kept[0]).select_action(np.zeros((1, 6), np.float32)).shape == (1, 2)


def test_boundary_weights_mark_the_steps_around_each_subskill_boundary():
    from cotpc.data.dataset import boundary_weights

    ep = synthetic_trajectories(n_episodes=1, length=20, seed=0).episodes[0]
    ep.extras["subskill_ends"] = np.array([4, 11, 19])  # key states at 5 and 12; 20 is the episode's end
    w = boundary_weights(ep, 3.0, 1, "x")
    assert w.shape == (20,)
    assert np.flatnonzero(w == 3.0).tolist() == [4, 5, 6, 11, 12, 13] and set(w.tolist()) == {1.0, 3.0}
    assert np.flatnonzero(boundary_weights(ep, 2.0, 0, "x") == 2.0).tolist() == [5, 12]
    with pytest.raises(ValueError, match="boundary weight"):
        boundary_weights(ep, 0.0, 1, "x")
    del ep.extras["subskill_ends"]
    with pytest.raises(MissingSubskillsError, match="cotpc segment"):
        boundary_weights(ep, 3.0, 1, "x")


def test_boundary_weight_draws_boundary_windows_that_much_more_often(data):
    from cotpc.data.dataset import boundary_weights

    trajs, uniform = window_dataset(data, 4, ("next", "last"))
    near = np.concatenate([boundary_weights(e, 2.0, 1, "x") > 1 for e in trajs.episodes])
    assert 0.1 < near.mean() < 0.9
    _, same = window_dataset(data, 4, ("next", "last"), boundary_weight=1.0)
    a, b = (ds.sample(64, torch.Generator().manual_seed(0)) for ds in (uniform, same))
    assert all(torch.equal(a[k], b[k]) for k in a)  # weight 1 is the uniform sampler, draw for draw
    _, weighted = window_dataset(data, 4, ("next", "last"), boundary_weight=4.0, boundary_radius=1)
    gen = torch.Generator().manual_seed(0)
    ends = torch.cat([weighted.sample_ends(4096, gen) for _ in range(8)]).numpy()
    expected = 4 * near.mean() / (4 * near.mean() + (1 - near.mean()))
    assert abs(near[ends].mean() - expected) < 0.02, (near[ends].mean(), expected)
    assert ends.min() >= 0 and ends.max() < len(weighted) and len(np.unique(ends)) == len(weighted)


def test_compiled_training_tracks_eager_and_resumes_only_compiled_alike(data, tmp_path):
    """--compile default: the same step through torch.compile's fused kernels, so the losses track eager
    training's; a run started eager does not resume compiled (its numbers would change)."""
    kw = dict(TINY, bf16=False, val_every=6)
    losses = {}
    for mode in ("off", "default"):
        run = train(TrainConfig(data=data, out=tmp_path / mode, iters=6, compile=mode, **kw))
        losses[mode] = json.loads((run / "config.json").read_text())["val"]["all_loss"]
    assert losses["default"] == pytest.approx(losses["off"], rel=1e-3), losses
    with pytest.raises(CheckpointError, match="--compile"):
        train(TrainConfig(data=data, out=tmp_path / "off", iters=8, compile="default", resume=True, **kw))


def test_missing_subskills_tells_how_to_segment(tmp_path):
    trajs = synthetic_trajectories(n_episodes=4, obs_dim=6, action_dim=2, length=20)
    for ep in trajs.episodes:
        ep.extras.clear()
    save_trajectories(tmp_path / "raw.h5", trajs)
    with pytest.raises(MissingSubskillsError, match="cotpc segment"):
        train(TrainConfig(data=tmp_path / "raw.h5", out=tmp_path / "run", iters=2, **TINY))
    # policies without CoT targets train on it
    train(TrainConfig(data=tmp_path / "raw.h5", policy="bet", out=tmp_path / "bet", iters=2, **TINY))


def test_bf16_tracks_fp32(data, tmp_path):
    """bf16 autocast changes the numbers slightly but not the learning: the losses track each other."""
    vals = {}
    for bf16 in (False, True):
        run = train(TrainConfig(data=data, out=tmp_path / f"bf16_{bf16}", iters=40, val_every=20, bf16=bf16,
                                **{k: v for k, v in TINY.items() if k != "val_every"}))
        vals[bf16] = json.loads((run / "config.json").read_text())["val"]["all_loss"]
    assert abs(vals[True] - vals[False]) < 0.1 * vals[False], vals


def test_cli_help_documents_flags(capsys):
    from cotpc.cli.train import main

    with pytest.raises(SystemExit) as e:
        main(["--help"], prog="cotpc train")
    assert e.value.code == 0
    out = capsys.readouterr().out
    for flag in ("--data", "--policy", "--resume", "--bf16", "--ckpt-every", "--val-fraction"):
        assert flag in out


def test_validation_reports_the_inference_regime_and_best_selects_on_it(data, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = train(TrainConfig(data=data, out=tmp_path / "run", iters=30, **TINY))
    val = json.loads((run / "config.json").read_text())["val"]
    for k in ("last_action_err", "last_ce", "last_centre_acc", "last_offset", "last_cot", "last_bc", "all_bc", "all_cot"):
        assert k in val, k
    assert 0 <= val["last_centre_acc"] <= 1
    acc = EventAccumulator(str(run / "tb"))
    acc.Reload()
    errs = {e.step: e.value for e in acc.Scalars("val/last_action_err")}
    best = json.loads((run / "best" / "config.json").read_text())
    assert best["val"]["last_action_err"] == pytest.approx(min(errs.values()), rel=1e-5)
    assert best["step"] == min(errs, key=errs.get)


def test_inference_metrics_score_what_select_action_outputs():
    from test_policies import P, Q, build

    trajs = synthetic_trajectories(n_episodes=8, obs_dim=Q, action_dim=P, length=20, seed=0)
    for name in ("cotpc", "bc", "dt"):
        model, ds = build(name, trajs)
        batch = ds.windows(torch.arange(0, 40))
        m = model.eval().inference_metrics(batch)
        want = ((model.predict(batch) - batch["actions"][:, -1]) ** 2).mean()
        torch.testing.assert_close(m["action_err"], want)


def test_timestep_embeddings_cover_training_and_clamp_beyond(data, tmp_path):
    from cotpc.data import load_trajectories

    run = train(TrainConfig(data=data, out=tmp_path / "run", iters=4, **TINY))
    longest = max(ep.num_steps for ep in load_trajectories(data).episodes)
    assert json.loads((run / "config.json").read_text())["max_timestep"] == longest  # a row per trained step
    model = load_policy(run).model
    g = torch.Generator().manual_seed(0)
    s, a = torch.randn(2, 4, 6, generator=g), torch.randn(2, 3, 2, generator=g)
    at_last = model.gpt(s, a, torch.full((2, 4), longest - 1))[0]
    beyond = model.gpt(s, a, torch.arange(4)[None].repeat(2, 1) + 5 * longest)[0]
    torch.testing.assert_close(beyond, at_last)  # steps past the longest demo read its last (trained) row


def test_gradient_shares_of_the_loss_terms_are_logged(data, tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run = train(TrainConfig(data=data, out=tmp_path / "run", iters=10, **TINY))
    acc = EventAccumulator(str(run / "tb"))
    acc.Reload()
    shares = {k: acc.Scalars(f"grad/{k}_share")[-1].value for k in ("ce", "offset", "cot")}
    assert abs(sum(shares.values()) - 1) < 1e-5 and all(v > 0 for v in shares.values())


def test_validation_metrics_of_one_pass_equal_the_separate_computations():
    from test_policies import P, Q, build

    trajs = synthetic_trajectories(n_episodes=8, obs_dim=Q, action_dim=P, length=20, seed=0)
    for name in ("cotpc", "cotpc-causal", "swapped", "decoupled", "dt", "bc"):
        model, ds = build(name, trajs)
        batch = ds.windows(torch.arange(0, 40))
        all_pos, last = model.eval().validation_metrics(batch)
        want_last = model.inference_metrics(batch)
        assert last.keys() == want_last.keys()
        for k in last:
            torch.testing.assert_close(last[k], want_last[k], msg=f"{name} {k}")
        if name != "bc":
            model.cfg = model.cfg.replace(random_cot_mask=False)  # the training loss without its random mask
        want_all = model.loss(batch)[1]
        for k in want_all:
            torch.testing.assert_close(all_pos[k], want_all[k], msg=f"{name} {k}")


def test_training_leaves_the_callers_thread_count(tmp_path):
    from cotpc.data import save_trajectories
    from cotpc.data.dataset import synthetic_trajectories
    from cotpc.training import TrainConfig, train

    data = tmp_path / "d.h5"
    save_trajectories(data, synthetic_trajectories(n_episodes=4, obs_dim=4, action_dim=2, length=10, seed=0))
    torch.set_num_threads(2)
    train(TrainConfig(data=data, policy="bc", out=tmp_path / "run", iters=2, threads=1, progress=False))
    assert torch.get_num_threads() == 2


def test_checkpoint_interval_defaults_follow_the_run_length():
    """--ckpt-every defaults to a tenth of the run (at most 5000), a twentieth with --keep-checkpoints (the
    paper's last-20 protocol), so a short run with --keep-checkpoints keeps a curve, not only its last weights."""
    from cotpc.training.train import PROTOCOL_CHECKPOINTS, checkpoint_interval

    def interval(**kw):
        return checkpoint_interval(TrainConfig(data=Path("x.h5"), **kw))

    assert interval(iters=3000) == 300 and interval(iters=200_000) == 5000 and interval(iters=5) == 1
    assert interval(iters=3000, keep_checkpoints=True) == 3000 // PROTOCOL_CHECKPOINTS == 150
    assert interval(iters=3000, ckpt_every=7, keep_checkpoints=True) == 7
    with pytest.raises(ValueError, match="ckpt-every"):
        interval(iters=10, ckpt_every=0)


def test_validation_does_not_depend_on_the_chunk_size(data):
    """evaluate_loss averages the last-position metrics (what selects checkpoints) over every window whatever the
    chunk (the CPU default is smaller than a GPU's); the all-position terms are means of per-chunk masked means,
    so they move slightly with it."""
    from cotpc.policies import get_preset, make_model
    from cotpc.training.train import evaluate_loss

    cfg = get_preset("cotpc", context=4, d_model=32, n_heads=4, n_layers=2, n_centres=8)
    trajs, ds = window_dataset(data, cfg.window, cfg.cot_targets, episodes=[0, 1, 2], where=str(data))
    torch.manual_seed(0)
    model = make_model(cfg, trajs.obs_dim, trajs.action_dim, 20)
    default, small = (evaluate_loss(model, ds, contextlib.nullcontext),
                      evaluate_loss(model, ds, contextlib.nullcontext, chunk=7))
    assert len(ds) > 7 and default.keys() == small.keys() and "last_action_err" in default
    for k in default:
        assert default[k] == pytest.approx(small[k], rel=1e-5 if k.startswith("last_") else 1e-2, abs=1e-7), k


def test_validation_of_a_capped_family_scores_a_fixed_evenly_spaced_subset(data, tmp_path):
    """A family with ``validation_windows`` (the transformers and the diffusion policies) is scored on that many
    held-out windows, evenly spaced over the set and the same each time; the others on every window."""
    from cotpc.policies import get_preset, make_model
    from cotpc.training.train import evaluate_loss

    # the caps that keep validation a small share of a run on a large file (docs/performance.md)
    caps = {name: getattr(make_model(get_preset(name), 4, 2, 20), "validation_windows", None)
            for name in ("bc", "bet", "cotpc", "dp")}
    assert caps == {"bc": None, "bet": 1024, "cotpc": 1024, "dp": 256}

    _, ds = window_dataset(data, 4)

    class Recorder(torch.nn.Module):
        def __init__(self, limit):
            super().__init__()
            self.validation_windows, self.seen = limit, []

        def validation_metrics(self, batch):
            self.seen.append(batch["timesteps"][:, -1].clone())
            t = batch["timesteps"][:, -1].float().mean()
            return {"t": t}, {"t": t}

    full, capped = Recorder(None), Recorder(16)
    everything = evaluate_loss(full, ds, contextlib.nullcontext, chunk=7)
    subset = evaluate_loss(capped, ds, contextlib.nullcontext, chunk=7)
    assert len(torch.cat(full.seen)) == len(ds) and len(torch.cat(capped.seen)) == 16
    chosen = torch.linspace(0, len(ds) - 1, 16).round().long()
    assert torch.equal(torch.cat(capped.seen), ds.timesteps[chosen])
    assert subset["last_t"] == pytest.approx(float(ds.timesteps[chosen].float().mean()))
    assert everything["last_t"] == pytest.approx(float(ds.timesteps.float().mean()))
    overridden = Recorder(16)  # --val-windows overrides the family's cap
    evaluate_loss(overridden, ds, contextlib.nullcontext, chunk=7, limit=40)
    assert len(torch.cat(overridden.seen)) == 40
    with pytest.raises(ValueError, match="--val-windows"):
        train(TrainConfig(data=data, out=tmp_path / "bad", iters=2, val_windows=0, **TINY))


def test_states_only_transformer_trains_and_acts_without_past_actions(data, tmp_path):
    # --use-actions False: the original BeT's input (states only); the flag reaches the saved config, and the
    # loaded policy's actions do not depend on the actions it took before
    run = train(TrainConfig(data=data, policy="bet", out=tmp_path / "run", iters=10, use_actions=False, **TINY))
    assert json.loads((run / "config.json").read_text())["policy"]["use_actions"] is False
    pol = load_policy(run)
    obs = np.random.default_rng(0).normal(size=(3, 2, 6)).astype(np.float32)
    first = [pol.select_action(o) for o in obs]
    pol.reset()
    pol.select_action(obs[0])
    pol._actions[:, -1] = 123.0  # another action taken at the first step: must not matter
    for o, a in zip(obs[1:], first[1:]):
        assert np.array_equal(pol.select_action(o), a)


@pytest.mark.parametrize("episode_timestep", [True, False])
def test_without_the_episode_timestep_actions_do_not_depend_on_time(data, tmp_path, episode_timestep):
    # --episode-timestep False: the window index is the only position; the same window read at another episode
    # step gives the same action (with the embedding it does not)
    run = train(TrainConfig(data=data, policy="bet", out=tmp_path / "run", iters=10,
                            episode_timestep=episode_timestep, **TINY))
    assert json.loads((run / "config.json").read_text())["policy"]["episode_timestep"] is episode_timestep
    pol = load_policy(run)
    assert (pol.model.gpt.global_emb is not None) is episode_timestep
    obs = np.random.default_rng(0).normal(size=(6, 1, 6)).astype(np.float32)
    actions = []
    for shift in (0, 7):
        pol.reset()
        out = []
        for i, o in enumerate(obs):
            out.append(pol.select_action(o))
            if i == 0:
                pol._t += shift  # the next observations arrive as if later in the episode
        actions.append(np.concatenate(out))
    assert np.array_equal(actions[0], actions[1]) is not episode_timestep
