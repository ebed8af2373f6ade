"""The Moving Maze study end to end, in a form small enough for CI."""

import json

import pytest

from cotpc.cli.main import main as cotpc_main


def test_reproduce_runs_end_to_end_and_resumes(tmp_path, capsys):
    out = tmp_path / "study"
    argv = ["reproduce", "maze", "--quick", "--out", str(out), "--iters", "6", "--batch-size", "16",
            "--train-demos", "30", "--test-demos", "4", "--val-demos", "3", "--policies", "bc", "cotpc", "--ablations", "vanilla",
            "--offset-from", "state"]  # reaches the k-means-headed runs; bc has no offset head
    cotpc_main(argv)
    results = json.loads((out / "results.json").read_text())
    for name in ("bc", "cotpc", "vanilla"):
        for split, n in (("seen", 30), ("val", 3), ("unseen", 4)):
            r = results[name][split]
            assert {"mean", "std", "best", "runs"} <= set(r)
            assert len(r["runs"]) == 1 and 0.0 <= r["mean"] <= 100.0
            # The rate is a count out of the split's episodes.
            assert abs(r["mean"] * n / 100 - round(r["mean"] * n / 100)) < 1e-9
            episodes = json.loads((out / "runs" / name / "seed0" / f"eval_{split}.json").read_text())["episodes"]
            assert len(episodes) == n
    # The headline keys are the paper's rules (deadly gaps, actions in [1.5, 4]); the same checkpoints are also
    # evaluated under the forgiving readings of them.
    for key, n, deadly, min_action in (("unseen", 4, True, 1.5), ("unseen_forgiving", 4, False, 0.0),
                                       ("val_any-action", 3, True, 0.0), ("unseen_safe-gaps", 4, False, 1.5)):
        summary = json.loads((out / "runs" / "cotpc" / "seed0" / f"eval_{key}.json").read_text())["summary"]
        assert summary["episodes"] == n and summary["deadly_gaps"] == deadly
        assert summary["min_action"] == min_action
        assert results["cotpc"][key]["runs"] == [100 * summary["success_rate"]]
        assert ("raised_share" in results["cotpc"][key]) == (min_action > 0)
    assert results["meta"]["ablations"] == ["vanilla"]
    assert results["meta"]["settings"]["train"]["iters"] == 6
    # --quick trains the BeT-style heads with 128 k-means centres (chosen on validation configs)
    policy = json.loads((out / "runs" / "cotpc" / "seed0" / "config.json").read_text())["policy"]
    assert (policy["n_centres"], policy["offset_from"]) == (128, "state")
    report = (out / "report.md").read_text()
    assert "; offset head on the state token." in report
    assert "| cotpc |" in report and "| vanilla |" in report and "| cotpc (full method, seed 0) |" in report
    assert report.count("| cotpc |") == 2 and "Forgiving readings of the rules" in report
    assert (out / "success.png").exists() and (out / "learning_curves.png").exists()
    assert list((out / "videos" / "cotpc").glob("*.gif"))
    printed = capsys.readouterr().out
    assert "report:" in printed

    # A second call reuses the finished runs and their evaluations instead of doing them again; an evaluation
    # that is missing is redone and gives the same numbers.
    run = out / "runs" / "cotpc" / "seed0"
    weights = (run / "model.safetensors").stat().st_mtime_ns
    evaluated = (run / "eval_val.json").stat().st_mtime_ns
    (run / "eval_unseen.json").unlink()
    cotpc_main(argv)
    assert (run / "model.safetensors").stat().st_mtime_ns == weights
    assert (run / "eval_val.json").stat().st_mtime_ns == evaluated
    assert (run / "eval_unseen.json").exists()
    assert json.loads((out / "results.json").read_text())["cotpc"] == results["cotpc"]


def test_reproduce_parallel_jobs_and_checkpoint_curve(tmp_path):
    """--jobs trains runs in parallel processes, giving the same weights as one by one (one thread each);
    --keep-checkpoints adds validation success at every kept checkpoint to results.json and a plot."""
    from safetensors.torch import load_file

    common = ["--iters", "10", "--batch-size", "8", "--train-demos", "12", "--test-demos", "2", "--val-demos", "3",
              "--policies", "bc", "cotpc", "--ablations", "--seeds", "1", "--n-centres", "8",
              "--bf16", "False"]  # pinned: the precision race can pick differently on a busy machine
    parallel, serial = tmp_path / "parallel", tmp_path / "serial"
    cotpc_main(["reproduce", "maze", "--out", str(parallel), "--jobs", "2", "--keep-checkpoints", *common])
    # the serial run: same thread count as each parallel process got (cores // jobs, at least 1)
    import os

    threads = max(1, len(os.sched_getaffinity(0)) // 2)
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        cotpc_main(["reproduce", "maze", "--out", str(serial), *common])
    finally:
        torch.set_num_threads(before)
    for name in ("bc", "cotpc"):
        a = load_file(parallel / "runs" / name / "seed0" / "model.safetensors")
        b = load_file(serial / "runs" / name / "seed0" / "model.safetensors")
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a), name
    results = json.loads((parallel / "results.json").read_text())
    curve = results["meta"]["val_success_by_iteration"]["cotpc/seed0"]
    assert curve["iteration"] == list(range(1, 11))  # a checkpoint every tenth of the run
    assert len(curve["val"]) == len(curve["val_forgiving"]) == 10
    assert all(0 <= v <= 100 and abs(v * 3 / 100 - round(v * 3 / 100)) < 1e-9 for v in curve["val"])
    # the paper's protocol: the best test success over runs x the last kept checkpoints, each evaluation on disk
    protocol = results["cotpc"]["paper_protocol"]
    last = protocol["runs"]["seed0"]
    assert last["iteration"] == list(range(1, 11)) and protocol["best"] == max(last["unseen"])
    for it, rate in zip(last["iteration"], last["unseen"]):
        saved = json.loads((parallel / "runs" / "cotpc" / "seed0" / "checkpoints" / f"step_{it:07d}" /
                            "eval_unseen.json").read_text())["summary"]
        assert 100 * saved["success_rate"] == rate and saved["episodes"] == 2 and saved["deadly_gaps"]
    assert "The paper's protocol" in (parallel / "report.md").read_text()
    # our headline with checkpoint selection: the best validation checkpoint (the later on a tie), scored unseen
    chosen = results["cotpc"]["val_selected"]["runs"]["seed0"]
    best = max(range(10), key=lambda i: (curve["val"][i], i))
    assert chosen["iteration"] == curve["iteration"][best] and chosen["val"] == curve["val"][best]
    assert chosen["unseen"] == last["unseen"][last["iteration"].index(chosen["iteration"])]
    assert results["cotpc"]["val_selected"]["mean"] == chosen["unseen"]
    assert "Validation-selected weights" in (parallel / "report.md").read_text()
    assert (parallel / "val_success.png").exists() and "val_success.png" in (parallel / "report.md").read_text()

    # A finished run trained with other settings is an error, never reused as if it were the one asked for.
    import pytest

    other = list(common)
    other[other.index("--n-centres") + 1] = "16"
    with pytest.raises(ValueError, match="other settings"):
        cotpc_main(["reproduce", "maze", "--out", str(serial), *other])


def test_a_run_of_another_design_under_the_same_preset_name_is_not_reused(tmp_path):
    """Reuse compares the preset's design too: if a preset name comes to mean another design (as `cotpc` may),
    a finished run of the earlier design is an error, not a result of the new one."""
    import dataclasses

    import pytest

    from cotpc.policies import config_to_dict, get_preset
    from cotpc.studies.runs import finished
    from cotpc.training.train import TrainConfig

    wanted = TrainConfig(data=tmp_path / "train.h5", policy="cotpc", seed=0, iters=5, context=4)
    run = tmp_path / "cotpc" / "seed0"
    run.mkdir(parents=True)
    info = {"train": {"policy": "cotpc", "seed": 0, "iters": 5, "context": 4},
            "policy": config_to_dict(get_preset("cotpc", context=4)), "step": 5}
    (run / "config.json").write_text(json.dumps(info))
    assert finished(run, wanted)
    with pytest.raises(ValueError, match="context"):  # any setting that changes what a run learns
        finished(run, dataclasses.replace(wanted, context=8))
    assert finished(run, dataclasses.replace(wanted, offset_from="cot"))  # cotpc's own: the same run
    with pytest.raises(ValueError, match="offset_from"):
        finished(run, dataclasses.replace(wanted, offset_from="state"))
    other = dataclasses.replace(get_preset("cotpc"), cot_attention="causal", random_cot_mask=False)
    info["policy"] = config_to_dict(other)
    (run / "config.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="policy.cot_attention"):
        finished(run, wanted)


@pytest.mark.parametrize("args, says", [
    (["maze", "--seeds", "0"], "cotpc reproduce maze: --seeds must be >= 1, got 0"),
    (["maze", "--iters", "0"], "--iters must be a finite number >= 1, got 0"),  # not silently the 20K default
    (["maze", "--jobs", "0"], "--jobs must be >= 1"),
    (["maze", "--policies", "cotpc", "nope"], "unknown policy 'nope'"),
    (["maniskill", "--batch-size", "0"], "cotpc reproduce maniskill: --batch-size must be"),
    (["maniskill", "--obs-std-floor", "-1"], "cotpc reproduce maniskill: --obs-std-floor must be a finite number >= 0"),
    (["kitchen", "--seeds", "0"], "cotpc reproduce kitchen: --seeds must be >= 1"),
    # a policy the shared flags do not fit: up front, not when its run starts after the demos and the other runs
    (["maze", "--policies", "cotpc", "bet", "--offset-from", "cot"],
     "cotpc reproduce maze: --policy bet: reading a head from CoT tokens needs"),
    (["maniskill", "--policies", "bet", "--offset-from", "cot"], "cotpc reproduce maniskill: --policy bet: reading"),
    (["maze", "--policies", "cotpc", "--use-actions", "False", "--offset-from", "action"],
     "--policy cotpc: a head reads action tokens but use_actions is False"),
])
def test_bad_study_flags_fail_before_anything_is_generated(tmp_path, args, says):
    with pytest.raises(SystemExit, match=says):
        cotpc_main(["reproduce", *args, "--out", str(tmp_path / "study")])
    assert not (tmp_path / "study").exists()


def test_maze_study_flags_reach_every_run():
    import tyro

    from cotpc.studies.maze import MazeReproduce, study_settings

    def parse(argv):  # as `cotpc reproduce maze ARGV` parses them
        return tyro.cli(MazeReproduce, args=argv)

    quick = study_settings(parse(["--quick"]))
    assert (quick.train.iters, quick.train.batch_size, quick.train.n_centres, quick.seeds) == (1500, 64, 128, 1)
    assert quick.train.use_actions is None  # the presets' input: states and actions, as the paper
    assert quick.train.offset_from is None  # the presets' own: CoTPC's offsets from the CoT token, as the paper
    chosen = study_settings(parse(["--quick", "--use-actions", "False", "--iters", "30", "--cot-weight", "3",
                                   "--offset-from", "state"])).train
    assert (chosen.use_actions, chosen.iters, chosen.cot_weight, chosen.offset_from) == (False, 30, 3.0, "state")
    assert study_settings(parse([])).train.iters == 20_000  # the full study's schedule
