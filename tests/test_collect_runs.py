"""scripts/collect-runs.py: the JSON a results table is built from, and its validation-curve figure."""

import json
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "collect-runs.py"


def scored(path: Path, once: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"summary": {"success_once": once}, "episodes": [{"success": True}]}))


def test_collects_curves_checkpoint_scores_and_draws_them(tmp_path):
    run = tmp_path / "bet/seed0"
    run.mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"policy": {"batch_size": 256}, "step": 3000}))
    for step, once in ((1000, 0.2), (2000, 0.4), (3000, 0.3)):
        scored(run / f"checkpoints/step_{step:07d}/eval_val.json", once)
    scored(run / "checkpoints/step_0002000/eval_unseen.json", 0.45)   # chosen on the validation curve
    scored(run / "eval_unseen.json", 0.35)                            # the final weights
    scored(run / "checkpoints/step_0003000/eval_val_mean.json", 0.5)  # another inference rule
    out, png = tmp_path / "runs.json", tmp_path / "fig/curve.png"
    subprocess.run([sys.executable, str(SCRIPT), str(tmp_path), "--runs", "bet/seed0", "--out", str(out),
                    "--setting", "test", "--plot", str(png)], check=True, capture_output=True)
    row = json.loads(out.read_text())["runs"]["bet/seed0"]
    assert {k: v["success_once"] for k, v in row["val_curve_50_episodes"].items()} == {
        "1000": 0.2, "2000": 0.4, "3000": 0.3}
    assert row["unseen"]["success_once"] == 0.35
    assert row["unseen_by_checkpoint"] == {"2000": {"success_once": 0.45}}
    assert list(row["other_evals"]) == ["checkpoints/step_0003000/eval_val_mean.json"]
    assert "\"success\": true" not in json.dumps(row)  # per-episode records stay in the run directories
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_missing_run_is_a_clear_error(tmp_path):
    done = subprocess.run([sys.executable, str(SCRIPT), str(tmp_path), "--runs", "bet/seed9", "--out",
                           str(tmp_path / "x.json"), "--setting", "test"], capture_output=True, text=True)
    assert done.returncode != 0 and "no run directory" in done.stderr
