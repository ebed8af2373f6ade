"""Batched Moving Maze evaluation: scripted policies give the rates they must."""

import json

import numpy as np
import pytest

from cotpc.cli.main import main as cotpc_main
from cotpc.data import load_trajectories
from cotpc.envs.maze.env import ISLANDS, RULES, inside
from cotpc.envs.maze.rollout import (
    RandomPolicy,
    ReplayPolicy,
    evaluate,
    load_split_configs,
    rollout,
    wilson_interval,
)


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("eval_demos")
    cotpc_main(["demos", "maze", "--out", str(out), "--train", "30", "--test", "10", "--val", "5"])
    return out


def test_replaying_the_demos_succeeds_everywhere(demo_dir, tmp_path):
    data = load_trajectories(demo_dir / "train.h5")
    policy = ReplayPolicy([ep.actions for ep in data.episodes])
    result = evaluate(policy, demo_dir, "seen", video_dir=tmp_path / "videos", num_videos=2)
    assert result.success.all() and result.success_rate == 1.0
    assert (result.region_transitions == 5).all()
    np.testing.assert_array_equal(result.steps, [ep.num_steps for ep in data.episodes])
    assert len(result.meta["videos"]) == 2 and all((tmp_path / "videos").glob("*.gif"))
    result.to_json(tmp_path / "r.json")
    saved = json.loads((tmp_path / "r.json").read_text())
    assert saved["summary"]["success_rate"] == 1.0 and len(saved["episodes"]) == 30


def test_replaying_other_demos_mostly_fails(demo_dir):
    # The same actions in the wrong configs: the bridges are elsewhere when the agent arrives.
    data = load_trajectories(demo_dir / "train.h5")
    shifted = [data.episodes[(i + 1) % len(data.episodes)].actions for i in range(len(data.episodes))]
    result = evaluate(ReplayPolicy(shifted), demo_dir, "seen")
    assert result.success_rate < 0.5


def test_random_policy_rarely_succeeds(demo_dir):
    result = evaluate(RandomPolicy(seed=0), demo_dir, "unseen")
    assert result.success_rate <= 0.1
    assert result.region_transitions.mean() < 2


def test_splits_come_from_their_own_seed_ranges(demo_dir, tmp_path):
    _, seen = load_split_configs(demo_dir, "seen")
    _, val = load_split_configs(demo_dir, "val")
    _, unseen = load_split_configs(demo_dir, "unseen")
    assert len(seen) == 30 and len(val) == 5 and len(unseen) == 10
    assert all(1_000_000 <= s < 2_000_000 for s in val)
    assert not set(seen) & set(unseen) and not set(seen) & set(val) and not set(val) & set(unseen)
    with pytest.raises(ValueError, match="split must be one of"):
        load_split_configs(demo_dir, "validation")
    # A demo directory without validation demos says how to make them.
    (tmp_path / "train.h5").symlink_to(demo_dir / "train.h5")
    with pytest.raises(FileNotFoundError, match="--val"):
        load_split_configs(tmp_path, "val")


def test_a_test_file_in_place_of_the_validation_file_is_refused(demo_dir, tmp_path):
    for ext in ("h5", "json"):
        (tmp_path / f"val.{ext}").symlink_to(demo_dir / f"test.{ext}")
    with pytest.raises(ValueError, match="belongs to the test split"):
        load_split_configs(tmp_path, "val")


def test_rollout_stops_early_and_records_steps(demo_dir):
    configs, seeds = load_split_configs(demo_dir, "unseen", episodes=3)
    data = load_trajectories(demo_dir / "test.h5")
    result, frames = rollout(ReplayPolicy([ep.actions for ep in data.episodes[:3]]), configs, seeds, "unseen", record=1)
    assert result.success.all()
    assert len(frames[0]) == max(ep.num_steps for ep in data.episodes[:3]) + 1


def test_wilson_interval():
    lo, hi = wilson_interval(0, 100)
    assert lo == 0.0 and 0.02 < hi < 0.05
    lo, hi = wilson_interval(50, 100)
    assert lo == pytest.approx(0.4038, abs=1e-3) and hi == pytest.approx(0.5962, abs=1e-3)


def test_demos_also_succeed_when_gaps_are_deadly(demo_dir, tmp_path):
    # The demonstrator never steps into a gap, so the rule changes nothing for it: every demo replays to success
    # under the defaults (the paper's rules), and under each forgiving reading...
    data = load_trajectories(demo_dir / "train.h5")
    result = evaluate(ReplayPolicy([ep.actions for ep in data.episodes]), demo_dir, "seen")
    assert result.success_rate == 1.0 and result.meta["fell"] == 0
    assert (result.meta["deadly_gaps"], result.meta["min_action"]) == (True, 1.5)
    for rules in RULES.values():
        result = evaluate(ReplayPolicy([ep.actions for ep in data.episodes]), demo_dir, "seen",
                          deadly_gaps=rules.deadly_gaps, min_action=rules.min_action)
        assert result.success_rate == 1.0, rules
    # ...while a random walker falls.
    result = evaluate(RandomPolicy(seed=0), demo_dir, "seen", deadly_gaps=True)
    assert result.meta["fell"] > 0
    # each fall is written with where the fatal step would have landed, which is off walkable ground
    result.to_json(tmp_path / "random_eval.json")
    falls = [e["fell_at"] for e in json.loads((tmp_path / "random_eval.json").read_text())["episodes"] if "fell_at" in e]
    assert len(falls) == result.meta["fell"]
    assert all(0 <= x <= 60 and 0 <= y <= 80 and not any(inside(np.array([[x, y]]), ISLANDS)[0]) for x, y in falls)


def test_demos_also_succeed_under_the_papers_action_range(demo_dir):
    # The demonstrator's action components already have magnitudes in [1.5, 4]: the rule changes none of them.
    data = load_trajectories(demo_dir / "train.h5")
    result = evaluate(ReplayPolicy([ep.actions for ep in data.episodes]), demo_dir, "seen", min_action=1.5)
    assert result.success_rate == 1.0 and result.meta["min_action"] == 1.5 and result.meta["raised_share"] == 0.0
    # A policy that stands still is moved at every step: all of its action components are raised.
    result = evaluate(ReplayPolicy([np.zeros((0, 2))] * len(data.episodes)), demo_dir, "seen", min_action=1.5)
    assert result.meta["raised_share"] == 1.0


def test_eval_cli_on_a_trained_run(demo_dir, tmp_path, capsys):
    run = tmp_path / "bc"
    cotpc_main(["train", "--data", str(demo_dir / "train.h5"), "--policy", "bc", "--out", str(run),
                "--iters", "5", "--no-progress"])
    cotpc_main(["eval", str(run), "--split", "unseen", "--episodes", "3", "--video", str(tmp_path / "v"),
                "--num-videos", "1"])
    saved = json.loads((run / "eval_unseen.json").read_text())
    assert saved["summary"]["episodes"] == 3 and saved["summary"]["split"] == "unseen"
    assert all(e["seed"] >= 2_000_000 for e in saved["episodes"])  # the test configs
    assert len(list((tmp_path / "v").glob("*.gif"))) == 1
    assert "success" in capsys.readouterr().out
    assert (saved["summary"]["deadly_gaps"], saved["summary"]["min_action"]) == (True, 1.5)  # the paper's rules
    cotpc_main(["eval", str(run), "--split", "seen", "--rules", "forgiving", "--episodes", "2"])
    saved = json.loads((run / "eval_seen_forgiving.json").read_text())["summary"]
    assert (saved["deadly_gaps"], saved["min_action"]) == (False, 0.0)
    cotpc_main(["eval", str(run), "--split", "seen", "--rules", "any-action", "--episodes", "2"])
    saved = json.loads((run / "eval_seen_any-action.json").read_text())["summary"]
    assert (saved["deadly_gaps"], saved["min_action"]) == (True, 0.0)
    cotpc_main(["eval", str(run), "--split", "val"])
    saved = json.loads((run / "eval_val.json").read_text())
    assert saved["summary"]["episodes"] == 5 and all(1_000_000 <= e["seed"] < 2_000_000 for e in saved["episodes"])
    with pytest.raises(SystemExit, match="--compile: .*transformer policies"):
        cotpc_main(["eval", str(run), "--split", "val", "--episodes", "1", "--compile"])
    capsys.readouterr()
    # a bad run directory or demo folder: exit status 2 and one line naming the file, no traceback
    for args, says in (([str(demo_dir)], "no config.json; not a cotpc run directory"),
                       ([str(run), "--demos", str(tmp_path / "nowhere")], "nowhere/val.h5 does not exist")):
        with pytest.raises(SystemExit) as stop:
            cotpc_main(["eval", *args, "--split", "val", "--episodes", "1"])
        assert stop.value.code == 2 and says in capsys.readouterr().err
    for flags, says in ((["--episodes", "0"], "--episodes must be >= 1, got 0"),  # not silently "all"
                        (["--episodes", "-1"], "--episodes must be >= 1"), (["--horizon", "0"], "--horizon must be")):
        with pytest.raises(SystemExit, match=says):
            cotpc_main(["eval", str(run), "--split", "val", *flags])
    weights = run / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:500])  # a copy cut short
    with pytest.raises(SystemExit) as stop:
        cotpc_main(["eval", str(run), "--split", "val", "--episodes", "1"])
    assert stop.value.code == 2 and "not a readable safetensors file" in capsys.readouterr().err


def test_eval_cli_compiled_transformer_acts_as_the_eager_one(demo_dir, tmp_path):
    run = tmp_path / "bet"  # a transformer needing no subskills in the data
    cotpc_main(["train", "--data", str(demo_dir / "train.h5"), "--policy", "bet", "--out", str(run), "--iters", "3",
                "--batch-size", "8", "--bf16", "False", "--threads", "1", "--no-progress"])
    cotpc_main(["eval", str(run), "--split", "val", "--episodes", "2"])
    eager = json.loads((run / "eval_val.json").read_text())
    cotpc_main(["eval", str(run), "--split", "val", "--episodes", "2", "--compile", "--out", str(tmp_path / "c.json")])
    compiled = json.loads((tmp_path / "c.json").read_text())
    assert (eager["summary"]["compile"], compiled["summary"]["compile"]) == (False, True)
    for a, b in zip(eager["episodes"], compiled["episodes"], strict=True):  # actions agree to ~1e-7
        assert (a["seed"], a["success"]) == (b["seed"], b["success"])


def test_eval_cli_sampler_steps_for_a_diffusion_policy(demo_dir, tmp_path):
    run = tmp_path / "dp"
    cotpc_main(["train", "--data", str(demo_dir / "train.h5"), "--policy", "dp", "--out", str(run), "--iters", "2",
                "--batch-size", "16", "--bf16", "False", "--threads", "1", "--no-progress"])
    cotpc_main(["eval", str(run), "--split", "val", "--episodes", "2", "--sampler-steps", "3"])
    saved = json.loads((run / "eval_val_steps3.json").read_text())  # beside, never over, the run's own evaluation
    assert saved["summary"]["sampler_steps"] == 3 and saved["summary"]["episodes"] == 2
    assert not (run / "eval_val.json").exists()
    with pytest.raises(SystemExit, match="inference_steps"):
        cotpc_main(["eval", str(run), "--split", "val", "--episodes", "1", "--sampler-steps", "1000"])
    # the executed part of each chunk: 1 = plan at every step; the queue is sized for it
    cotpc_main(["eval", str(run), "--split", "val", "--episodes", "2", "--action-horizon", "1"])
    saved = json.loads((run / "eval_val_ah1.json").read_text())
    assert saved["summary"]["action_horizon"] == 1 and saved["summary"]["episodes"] == 2
    with pytest.raises(SystemExit, match="action_horizon"):
        cotpc_main(["eval", str(run), "--split", "val", "--episodes", "1", "--action-horizon", "16"])
    bc = tmp_path / "bc"
    cotpc_main(["train", "--data", str(demo_dir / "train.h5"), "--policy", "bc", "--out", str(bc), "--iters", "2",
                "--no-progress"])
    with pytest.raises(SystemExit, match="diffusion policies"):
        cotpc_main(["eval", str(bc), "--split", "val", "--episodes", "1", "--sampler-steps", "3"])
