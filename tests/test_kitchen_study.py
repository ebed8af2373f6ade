"""``cotpc reproduce kitchen`` end to end at the smallest size (needs the ``kitchen`` extra)."""

import json

import pytest

pytest.importorskip("gymnasium_robotics")
pytest.importorskip("mujoco")

from cotpc.cli.main import main as cotpc_main  # noqa: E402


def test_reproduce_kitchen_end_to_end_and_reuses(tmp_path, capsys):
    out = tmp_path / "study"
    # bc only: a transformer's 280-step rollouts take minutes on a shared 2-core machine
    argv = ["reproduce", "kitchen", "--out", str(out), "--seeds", "1", "--iters", "2", "--policies", "bc",
            "--train-demos", "2", "--val-demos", "1", "--test-demos", "1", "--batch-size", "4", "--n-centres", "8",
            "--device", "cpu", "--bf16", "False"]
    cotpc_main(argv)
    results = json.loads((out / "results.json").read_text())
    for split, n in (("seen", 2), ("val", 1), ("unseen", 1)):
        r = results["bc"][split]
        assert len(r["runs"]) == 1 and 0.0 <= r["mean"] <= 100.0
        assert len(r["completed"]["runs"]) == 1 and 0.0 <= r["completed"]["mean"] <= 4.0
        saved = json.loads((out / "runs" / "bc" / "seed0" / f"eval_{split}.json").read_text())["summary"]
        assert saved["episodes"] == n and 100 * saved["success_rate"] == r["mean"]
        assert saved["mean_completed"] == r["completed"]["mean"]
    meta = results["meta"]
    assert meta["paper"]["success"]["cotpc"] == 25.6 and meta["paper"]["avg_completed"]["bet"] == 1.8
    assert meta["n_centres"] == 8 and meta["settings"]["iters"] == 2
    assert json.loads((out / "runs" / "bc" / "seed0" / "config.json").read_text())["train"]["bf16"] is False
    # discovery is scored against the demonstrator's sub-task boundaries (4 per demo)
    assert meta["subskills"]["true"] == 8 and 0.0 <= meta["subskills"]["precision"] <= 1.0
    report = (out / "report.md").read_text()
    assert "| bc |" in report and "| 6.7 | 1.7 |" in report and "precision" in report
    assert "report:" in capsys.readouterr().out

    # A second call reuses the demos, the finished run and its evaluations; a missing evaluation is redone.
    # (train.h5 itself is rewritten: discovery always re-labels it, as it is cheap.)
    run = out / "runs" / "bc" / "seed0"
    stamps = [(p, p.stat().st_mtime_ns) for p in (out / "demos" / "test.h5", run / "model.safetensors",
                                                    run / "eval_seen.json")]
    (run / "eval_val.json").unlink()
    cotpc_main(argv)
    assert [(p, p.stat().st_mtime_ns) for p, _ in stamps] == stamps
    assert (run / "eval_val.json").exists()
    assert json.loads((out / "results.json").read_text())["bc"] == results["bc"]
    printed = capsys.readouterr().out
    assert "[1/5] demos" not in printed and "[3/5] train" not in printed
