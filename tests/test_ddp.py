"""``torchrun --nproc_per_node=2 -m cotpc.train`` trains with DDP (gloo on the CPU)."""

import json
import os
import signal
import subprocess
import sys

import numpy as np

from cotpc.data import save_trajectories
from cotpc.data.dataset import synthetic_trajectories
from cotpc.policies import load_policy


def test_torchrun_two_processes(tmp_path):
    data = tmp_path / "demos.h5"
    save_trajectories(data, synthetic_trajectories(n_episodes=8, obs_dim=6, action_dim=2, length=20))
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
           "-m", "cotpc.train", "--data", str(data), "--out", str(run), "--iters", "6", "--ckpt-every", "3",
           "--context", "4", "--d-model", "32", "--n-heads", "4", "--n-layers", "2", "--n-centres", "8",
           "--batch-size", "16", "--no-progress", "--device", "cpu"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    # own process group, so a hang kills the workers too, not only the launcher
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
                            start_new_session=True)
    try:
        stdout, stderr = proc.communicate(timeout=180)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    assert proc.returncode == 0, stdout[-3000:] + stderr[-3000:]
    assert "6/6 iters" in stdout
    info = json.loads((run / "config.json").read_text())
    assert info["step"] == 6
    pol = load_policy(run)
    assert np.isfinite(pol.select_action(np.zeros((1, 6), np.float32))).all()
