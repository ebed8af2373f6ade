"""ManiSkill3 support: headless physics, planner demos, conversion, segmentation, training and evaluation.

The tests that need ManiSkill3 are skipped when it is not installed (`pip install -e '.[maniskill]'`); the
seed-range tests run everywhere. Everything runs on the CPU simulator with no render device.
"""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from cotpc.cli.main import main as cotpc_main
from cotpc.envs.maniskill.env import SEEDS, SeedRanges, is_maniskill_env

SKIP_REASON = "ManiSkill3 is not installed (pip install -e '.[maniskill]'; needs numpy<2)"


def needs_maniskill():
    pytest.importorskip("mani_skill", reason=SKIP_REASON)


# ------------------------------------------------------------------ no ManiSkill needed


def test_seed_ranges_are_disjoint_and_checked():
    lo_train, hi_train = SEEDS.range("train")
    lo_test, _ = SEEDS.range("test")
    assert hi_train <= lo_test
    assert list(SEEDS.seeds("test", 3, offset=5)) == [lo_test + 5, lo_test + 6, lo_test + 7]
    SEEDS.check(lo_train, "train")
    with pytest.raises(ValueError, match="belongs to the train split"):
        SEEDS.check(lo_train, "test")
    with pytest.raises(ValueError, match="do not fit"):
        SEEDS.seeds("train", 10, offset=hi_train - 5)
    with pytest.raises(ValueError, match="overlap"):
        SeedRanges({"a": (0, 10), "b": (5, 20)})


def test_task_ids():
    assert is_maniskill_env("StackCube-v1") and is_maniskill_env("PegInsertionSide-v1")
    assert not is_maniskill_env("cotpc/MovingMaze-v0") and not is_maniskill_env(None)


def test_privileged_key_steps_follow_the_official_codes_rules():
    """The official code's key states from per-step flags (flags[t] describe obs[t + 1]): the first state where a
    flag holds; Stack Cube's second, the state before cube A first rests on cube B released; a flag that never
    holds gives none."""
    from cotpc.envs.maniskill.env import key_steps_from_flags

    grasped = np.zeros(12, dtype=bool)
    grasped[3:8] = True
    on_b = np.zeros(12, dtype=bool)
    on_b[6:] = True
    assert key_steps_from_flags("StackCube-v1", np.stack([grasped, on_b], 1)).tolist() == [4, 8]
    pre = np.zeros(12, dtype=bool)
    pre[5:7] = True
    assert key_steps_from_flags("PegInsertionSide-v1", np.stack([grasped, pre], 1)).tolist() == [4, 6]
    assert key_steps_from_flags("PegInsertionSide-v1", np.stack([grasped, ~grasped & False], 1)).tolist() == [4]
    with pytest.raises(ValueError, match="expected flags of shape"):
        key_steps_from_flags("StackCube-v1", grasped[:, None])


def test_maze_commands_never_import_maniskill():
    code = ("import sys; from cotpc.cli import demos, eval; import cotpc.envs, cotpc.envs.maze.rollout; "
            "print('mani_skill' in sys.modules, 'sapien' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.split() == ["False", "False"]


# ------------------------------------------------------------------ ManiSkill3


def test_headless_workaround_only_without_a_device_and_physics_is_deterministic():
    needs_maniskill()
    from cotpc.envs.maniskill.env import ensure_headless, flat_obs, make_env

    patched = ensure_headless()
    import sapien

    # Patched exactly when no render device exists (on this CPU-only machine: patched).
    assert patched == (sapien.render.RenderMaterial.__name__ == "InertRenderMaterial")
    env = make_env("StackCube-v1", "pd_joint_delta_pos")
    actions = np.random.default_rng(0).uniform(-1, 1, size=(60, 8)).astype(np.float32)

    def roll(seed):
        obs, _ = env.reset(seed=seed, options={"reconfigure": True})
        out = [flat_obs(obs)]
        for a in actions:
            obs, *_ = env.step(a)
            out.append(flat_obs(obs))
        return np.concatenate(out)

    a, b, c = roll(7), roll(8), roll(7)
    assert a.shape == (61, 48) and np.isfinite(a).all()
    assert np.array_equal(a, c)  # same seed and actions: bit-identical
    assert not np.array_equal(a[0], b[0])  # the seed changes the initial state
    assert np.abs(a[-1] - a[0]).max() > 1e-3  # the robot moved: physics runs
    env.close()


@pytest.fixture(scope="module")
def stack_demos(tmp_path_factory):
    needs_maniskill()
    out = tmp_path_factory.mktemp("stackcube")
    cotpc_main(["demos", "maniskill", "--env", "StackCube-v1", "--out", str(out), "--num", "2", "--test", "1",
                "--val", "1", "--no-progress"])
    return out


def test_demos_follow_the_trajectory_format_with_disjoint_seeds(stack_demos):
    from cotpc.data import load_trajectories

    for split, n in (("train", 2), ("test", 1)):
        info = json.loads((stack_demos / f"{split}.json").read_text())
        assert info["env_info"]["env_id"] == "StackCube-v1"
        assert info["env_info"]["max_episode_steps"] == 200  # the paper's horizon
        assert info["env_info"]["env_kwargs"]["control_mode"] == "pd_joint_delta_pos"
        assert len(info["episodes"]) == n and info["cotpc_generation"]["complete"]
        for record in info["episodes"]:
            SEEDS.check(record["reset_kwargs"]["seed"], split)
            assert record["control_mode"] == "pd_joint_delta_pos"
        data = load_trajectories(stack_demos / f"{split}.h5")
        assert data.obs_dim == 48 and data.action_dim == 8
        for ep in data.episodes:
            assert ep.success[-1]  # only demos that succeed after conversion are kept
            assert np.abs(ep.actions).max() <= 1 + 1e-6  # normalised delta actions
            assert 50 < ep.num_steps < 200
            # the official code's privileged key states: cube A grasped, then released on cube B, in order
            flags, keys = ep.extras["key_flags"], ep.extras["key_steps"]
            assert flags.shape == (ep.num_steps, 2) and flags.dtype == bool and flags[-1, 1] and not flags[-1, 0]
            assert len(keys) == 2 and 1 <= keys[0] < keys[1] <= ep.num_steps
            assert flags[keys[0] - 1, 0] and not flags[: keys[0] - 1, 0].any()


def test_demos_replay_to_success_through_the_eval_path(stack_demos):
    from cotpc.envs.maniskill.rollout import evaluate, replay_factory

    result = evaluate(replay_factory(stack_demos / "train.h5"), stack_demos, "seen", progress=False, backend="cpu")
    s = result.summary()
    assert s["episodes"] == 2 and s["horizon"] == 200
    assert s["success_once"] == 1.0  # deterministic: the converted actions succeed again from reset(seed)
    assert s["success_once_ci95"][0] > 0.3
    from cotpc.data import load_trajectories

    firsts = [int(np.argmax(ep.success)) + 1 for ep in load_trajectories(stack_demos / "train.h5").episodes]
    assert list(result.first_success) == firsts  # the same step as in the demo
    # Progress short of success: a successful demo grasped cube A and put it on cube B, and reached full reward.
    assert s["stages_once"]["is_cubeA_grasped"] == 1.0 and s["stages_once"]["is_cubeA_on_cubeB"] == 1.0
    assert s["mean_max_normalized_reward"] == pytest.approx(1.0)


def test_peg_insertion_evaluation_reports_its_key_states_as_progress(tmp_path):
    """Peg Insertion's info has no progress flags of its own: the evaluation reads the privileged key states
    (peg grasped, pre-inserted) from the simulator, as the demos record them."""
    needs_maniskill()
    from cotpc.data import load_trajectories
    from cotpc.envs.maniskill.rollout import evaluate, replay_factory

    cotpc_main(["demos", "maniskill", "--env", "PegInsertionSide-v1", "--out", str(tmp_path), "--num", "1",
                "--test", "0", "--no-progress"])
    demo = load_trajectories(tmp_path / "train.h5").episodes[0]
    assert demo.extras["key_flags"].any(axis=0).all()  # the demo passes through both key states
    s = evaluate(replay_factory(tmp_path / "train.h5"), tmp_path, "seen", progress=False, backend="cpu").summary()
    assert s["success_once"] == 1.0
    assert s["stages_once"] == {"is_grasped": 1.0, "pre_inserted": 1.0}


def test_resume_extends_a_split_with_the_same_demos(stack_demos, tmp_path):
    import shutil

    from cotpc.data import load_trajectories

    out = tmp_path / "more"
    out.mkdir()
    for suffix in (".h5", ".json"):
        shutil.copy(stack_demos / f"train{suffix}", out / f"train{suffix}")
    cotpc_main(["demos", "maniskill", "--out", str(out), "--num", "3", "--test", "0", "--no-progress"])
    old, new = load_trajectories(stack_demos / "train.h5"), load_trajectories(out / "train.h5")
    assert len(new) == 3 and json.loads((out / "train.json").read_text())["cotpc_generation"]["attempted"] == 3
    for a, b in zip(old.episodes, new.episodes):
        assert a.reset_kwargs == b.reset_kwargs and np.array_equal(a.actions, b.actions)
        assert np.array_equal(a.extras["key_steps"], b.extras["key_steps"])  # kept through the resume
    assert all("key_steps" in ep.extras for ep in new.episodes)


def test_segment_train_and_eval(stack_demos, tmp_path):
    from cotpc.data import load_trajectories

    from cotpc.subskills.labeling import label_file

    train = stack_demos / "train.h5"
    summary, _ = label_file(train, beta=0.05)  # scored against the privileged key states the demos carry
    assert summary["true"] == 4 and 0 <= summary["precision"] <= 1 and 0 <= summary["recall"] <= 1
    cotpc_main(["segment", str(train)])  # the paper's beta 0.05 (mean cosine) for non-maze data
    for ep in load_trajectories(train).episodes:
        ends = ep.extras["subskill_ends"]
        assert ends[-1] == ep.num_steps - 1 and np.all(np.diff(ends) > 0)
    run = tmp_path / "run"
    cotpc_main(["train", "--data", str(train), "--policy", "cotpc", "--out", str(run), "--iters", "3",
                "--batch-size", "8", "--d-model", "32", "--n-layers", "1", "--n-heads", "2", "--n-centres", "8"])
    config = json.loads((run / "config.json").read_text())
    assert config["dataset"]["env_id"] == "StackCube-v1"
    out = tmp_path / "eval.json"
    cotpc_main(["eval", str(run), "--split", "unseen", "--horizon", "15", "--backend", "cpu", "--out", str(out)])
    result = json.loads(out.read_text())
    s = result["summary"]
    assert s["env_id"] == "StackCube-v1" and s["split"] == "unseen" and s["episodes"] == 1 and s["horizon"] == 15
    assert set(result["episodes"][0]) == {"seed", "success_once", "success_at_end", "first_success_step",
                                          "stages_once", "max_normalized_reward"}
    assert set(s["stages_once"]) == {"is_cubeA_grasped", "is_cubeA_on_cubeB", "is_cubeA_static"}
    assert 0 <= s["mean_max_normalized_reward"] <= 1
    SEEDS.check(result["episodes"][0]["seed"], "test")


def test_held_demos_are_the_plain_demos_then_stillness(stack_demos, tmp_path):
    from cotpc.data import load_trajectories

    cotpc_main(["demos", "maniskill", "--env", "StackCube-v1", "--out", str(tmp_path), "--num", "1", "--test", "0",
                "--hold-after-success", "15", "--no-progress"])
    held = load_trajectories(tmp_path / "train.h5").episodes[0]
    plain = load_trajectories(stack_demos / "train.h5").episodes[0]
    n = plain.num_steps
    assert held.reset_kwargs == plain.reset_kwargs and held.num_steps == n + 15
    assert np.array_equal(held.actions[:n], plain.actions) and np.array_equal(held.obs[: n + 1], plain.obs)
    assert not held.actions[n:, :-1].any() and (held.actions[n:, -1] == plain.actions[-1, -1]).all()
    assert held.success[n - 1:].all()  # the success holds through the stillness
    assert np.abs(held.obs[n + 1:, :7] - held.obs[n, :7]).max() < 0.01  # the arm's joints stay where they were
    assert held.extras["key_flags"].shape == (n + 15, 2)


def test_ee_delta_pose_conversion(tmp_path):
    needs_maniskill()
    from cotpc.data import load_trajectories

    cotpc_main(["demos", "maniskill", "--env", "PickCube-v1", "--out", str(tmp_path), "--num", "1", "--test", "0",
                "--control-mode", "pd_ee_delta_pose", "--no-progress"])
    data = load_trajectories(tmp_path / "train.h5")
    assert data.action_dim == 7 and data.episodes[0].success[-1]
    assert data.episodes[0].control_mode == "pd_ee_delta_pose"


def test_reproduce_maniskill_end_to_end_and_resumes(stack_demos, tmp_path):
    import shutil

    from cotpc.studies.maniskill import ManiSkillStudySettings, run
    from cotpc.training.train import TrainConfig

    demos = tmp_path / "StackCube-v1" / "demos"
    shutil.copytree(stack_demos, demos)  # the fixture's 2 + 1 demos: generation finds them complete
    settings = ManiSkillStudySettings(
        out=tmp_path, envs=("StackCube-v1",), policies=("cotpc",), seeds=1, num=2, test=1, val=1,
        seen_episodes=1, curve_episodes=1, curve_every=2, paper_protocol=True, horizon=12, procs=1, backend="cpu",
        train=TrainConfig(data=Path("replaced by each task's demos"), iters=2, batch_size=8, d_model=32, n_layers=1,
                          n_heads=2, n_centres=8, keep_checkpoints=True, context=4),
    )
    results = run(settings)
    run_config = json.loads((tmp_path / "StackCube-v1/runs/cotpc/seed0/config.json").read_text())
    assert run_config["policy"]["context"] == 4  # the study's --context reaches every run
    r = results["StackCube-v1"]["cotpc"]
    for split in ("seen", "unseen"):
        assert len(r[split]["runs"]) == 1 and 0 <= r[split]["mean"] <= 100
        assert len(r[split]["success_at_end"]["runs"]) == 1
        assert set(r[split]["stages_once"]) == {"is_cubeA_grasped", "is_cubeA_on_cubeB", "is_cubeA_static"}
        assert 0 <= r[split]["max_normalized_reward"] <= 1
        summary = json.loads((tmp_path / "StackCube-v1/runs/cotpc/seed0" / f"eval_{split}.json").read_text())["summary"]
        assert summary["horizon"] == 12 and summary["episodes"] == 1
        assert summary["success_once"] * 100 == r[split]["mean"]
    assert json.loads((tmp_path / "results.json").read_text())["meta"]["paper"]["StackCube-v1"]["results"]["cotpc"] == 86.0
    report = (tmp_path / "report.md").read_text()
    assert "context 4" in report
    assert "## StackCube-v1" in report and "| cotpc |" in report and "is_cubeA_grasped" in report and "privileged key states" in report and (tmp_path / "learning_curves_StackCube-v1.png").exists()
    # --keep-checkpoints: the kept checkpoints (--curve-every 2: every second, counted back from the last) scored
    # on the validation seeds (the schedule curve), and the paper's protocol on the test seeds, labelled as such.
    curve = r["val_curve"]["seed0"]
    assert curve["iteration"] == [2] and curve["samples"] == [16] and len(curve["success_once"]) == 1  # every 2nd
    assert 0 <= curve["max_normalized_reward"][0] <= 1 and "is_cubeA_grasped" in curve["stages_once"][0]
    ckpt_eval = json.loads((tmp_path / "StackCube-v1/runs/cotpc/seed0/checkpoints/step_0000002/eval_val.json").read_text())
    assert ckpt_eval["summary"]["episodes"] == 1 and ckpt_eval["summary"]["split"] == "val"
    assert 1_000_000 <= ckpt_eval["episodes"][0]["seed"] < 2_000_000  # a validation seed, never a test one
    assert r["paper_protocol"]["runs"]["seed0"]["iteration"] == [1, 2] and "test seeds" in r["paper_protocol"]["rule"]
    assert "| cotpc/seed0 | " in report and "The paper's protocol" in report
    chosen = r["val_selected"]["runs"]["seed0"]  # the only point of the curve, scored on the unseen seeds
    assert chosen["iteration"] == 2 and chosen["success_once"] == r["val_selected"]["mean"]
    assert chosen["success_once"] == 100 * json.loads((tmp_path / "StackCube-v1/runs/cotpc/seed0/checkpoints/"
                                                      "step_0000002/eval_unseen.json").read_text())["summary"]["success_once"]
    assert "Validation-selected weights" in report
    assert (tmp_path / "val_success_StackCube-v1.png").exists()
    # A second invocation reuses the demos, the trained weights and the evaluations.
    weights = tmp_path / "StackCube-v1/runs/cotpc/seed0/model.safetensors"
    evals = tmp_path / "StackCube-v1/runs/cotpc/seed0/eval_unseen.json"
    stamps = (weights.stat().st_mtime_ns, evals.stat().st_mtime_ns)
    assert run(settings)["StackCube-v1"]["cotpc"] == r
    assert (weights.stat().st_mtime_ns, evals.stat().st_mtime_ns) == stamps


def test_reproduce_flags_reach_every_run():
    import tyro

    from cotpc.studies.maniskill import ManiSkillReproduce, study_settings

    def parse(argv):  # as `cotpc reproduce maniskill ARGV` parses them
        return tyro.cli(ManiSkillReproduce, args=argv)

    train = study_settings(parse(["--context", "60", "--bf16", "False", "--batch-size", "64",
                                  "--use-actions", "False", "--ignore-obs", "16", "17", "--cot-weight", "1",
                                  "--offset-from", "state", "--obs-std-floor", "0.01"])).train
    assert (train.context, train.bf16, train.batch_size, train.use_actions) == (60, False, 64, False)
    assert (train.cot_weight, train.offset_from, train.obs_std_floor) == (1.0, "state", 0.01)
    assert train.ignore_obs == (16, 17)
    default = study_settings(parse([])).train
    assert default.ignore_obs == ()  # default: every dimension, as the paper
    assert default.cot_weight is None  # default: the paper's 0.1
    assert default.offset_from is None  # default: the presets' (CoTPC's reads the CoT token, as the paper)
    assert default.obs_std_floor == 0.0  # default: off, as the paper
    assert default.bf16 is None  # default: each run races the two precisions
    assert default.use_actions is None  # default: the preset's (action tokens, as the paper)


def test_reproduce_action_noise_makes_dart_training_demos(monkeypatch, tmp_path):
    import tyro

    from cotpc.envs.maniskill.demos import Demonstrator
    from cotpc.studies import maniskill as study

    asked = {}

    def fake_write_splits(env_id, demos, num, test, demonstrator, **kw):
        asked[env_id] = demonstrator
        raise KeyboardInterrupt  # stop before any training

    monkeypatch.setattr(study, "write_splits", fake_write_splits)
    monkeypatch.setattr(study, "import_maniskill", lambda: None)
    for argv, expected in ((["--action-noise", "0.1"], Demonstrator(0.1)), ([], Demonstrator()),
                           (["--action-noise", "0.1", "--hold-after-success", "20"],
                            Demonstrator(0.1, hold_after_success=20))):
        settings = study.study_settings(tyro.cli(study.ManiSkillReproduce, args=["--out", str(tmp_path), *argv]))
        with pytest.raises(KeyboardInterrupt):
            study.run(settings)
        assert asked["StackCube-v1"] == expected
    bad = study.study_settings(study.ManiSkillReproduce(out=tmp_path, action_noise=-1.0))
    with pytest.raises(SystemExit, match="cotpc reproduce maniskill: --action-noise must be a std >= 0"):
        study.run(bad)
    bad = study.study_settings(study.ManiSkillReproduce(out=tmp_path, hold_after_success=-1))
    with pytest.raises(SystemExit, match="cotpc reproduce maniskill: --hold-after-success must be >= 0"):
        study.run(bad)


def test_maniskill_report_for_a_task_without_stage_flags(tmp_path):
    from cotpc.studies.maniskill import PAPER, write_report

    stats = {"mean": 0.0, "std": 0.0, "best": 0.0, "runs": [0.0]}
    split = {**stats, "success_at_end": stats, "stages_once": {}, "max_normalized_reward": 0.25}
    meta = {"settings": {"seeds": 1, "control_mode": "pd_joint_delta_pos", "action_noise": 0.1,
                         "hold_after_success": 20,
                         "train": {"iters": 2, "batch_size": None, "n_centres": None, "ignore_obs": [16, 17],
                                   "cot_weight": 1.0, "offset_from": "state", "obs_std_floor": 0.01}},
            "checkpoint_selection": "final", "wall_seconds": 1.0, "demos": {"PegInsertionSide-v1": 3},
            "horizons": {"PegInsertionSide-v1": 200}, "subskills": {}, "train_seconds": {}, "paper": PAPER,
            "hardware": {"cpus": 2, "machine": "x86_64"},
            "versions": {"torch": "t", "mani_skill": "m", "sapien": "s"}}
    report = write_report({"PegInsertionSide-v1": {"bet": {"seen": split, "unseen": split}}, "meta": meta},
                          tmp_path).read_text()
    assert "| policy | max normalised reward |\n|---|---|\n| bet | 0.250 |" in report
    assert "| bet | 0.0 ± 0.0 [0.0] |" in report and "| 42.5 |" in report
    assert "state observations without dimensions 16, 17; training demos DART-style (arm noise 0.1); training demos held still 20 steps after the success; CoT weight 1.0; offset head on the state token; observation std floored at 0.01." in report
