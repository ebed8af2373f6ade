"""`cotpc segment` (file round trip, replacement, figures, sweep) and `cotpc bench segment`."""

import json

import h5py
import numpy as np
import pytest

from cotpc.cli.main import main as cotpc_main
from cotpc.cli.segment import main as segment_main
from cotpc.data import Episode, TrajectorySet, load_trajectories, save_trajectories
from cotpc.subskills import discover


def make_file(path, env_id="Test-v0", n_episodes=3, with_keys=False):
    rng = np.random.default_rng(0)
    episodes = []
    for i in range(n_episodes):
        n = 20 + 5 * i
        dirs = np.array([[3.0, 0.5], [0.2, -3.0], [-3.0, 0.1]])
        actions = dirs[np.repeat([0, 1, 2], [7, 6, n - 13])] + 0.2 * rng.normal(size=(n, 2))
        obs = np.concatenate([[[55.0, 75.0]], 55.0 + np.cumsum(actions, axis=0) * [1, 0.5]])
        obs = np.concatenate([obs, np.tile([55.0, 72.0, 20.0, 55.0, 40.0, 25.0, 5.0, 10.0], (n + 1, 1))], axis=1)
        extras = {"key_steps": np.array([7, 13])} if with_keys else {}
        episodes.append(Episode(obs=obs.astype(np.float32), actions=actions.astype(np.float32),
                                success=np.arange(n) == n - 1, episode_id=i, reset_kwargs={"seed": i},
                                extras=extras))
    ts = TrajectorySet(episodes, env_info={"env_id": env_id, "env_kwargs": {}, "max_episode_steps": 60})
    h5, _ = save_trajectories(path, ts)
    return h5, ts


def read_labels(h5):
    with h5py.File(h5, "r") as f:
        return {k: (f[k]["subskill_ends"][()], dict(f[k]["subskill_ends"].attrs)) for k in f}


def test_round_trip_and_replace(tmp_path, capsys):
    h5, ts = make_file(tmp_path / "demos")
    segment_main([str(h5), "--beta", "0.05"], prog="cotpc segment")
    out = capsys.readouterr().out
    assert "subskills per demo: mean" in out and "segment length" in out
    labels = read_labels(h5)
    assert set(labels) == {"traj_0", "traj_1", "traj_2"}
    for ep in ts.episodes:
        ends, attrs = labels[f"traj_{ep.episode_id}"]
        assert ends.dtype == np.int64
        np.testing.assert_array_equal(ends, discover(ep.actions, 0.05))
        assert attrs["beta"] == 0.05 and attrs["min_size"] == 1
        assert attrs["method"] == "exact-dp" and attrs["cost"] == "mean-cosine"
    assert labels["traj_0"][0].tolist() == [6, 12, 19]  # the three constant-direction stretches

    # re-running with other parameters replaces the labels (and the file still loads)
    segment_main([str(h5), "--beta", "5", "--min-size", "2", "--cost", "sum-cosine"], prog="cotpc segment")
    labels = read_labels(h5)
    for ep in ts.episodes:
        ends, attrs = labels[f"traj_{ep.episode_id}"]
        np.testing.assert_array_equal(ends, discover(ep.actions, 5.0, 2, "sum-cosine"))
        assert attrs["beta"] == 5.0 and attrs["min_size"] == 2 and attrs["cost"] == "sum-cosine"
    loaded = load_trajectories(h5)
    assert all("subskill_ends" in ep.extras for ep in loaded.episodes)


def test_errors_are_messages(tmp_path):
    h5, _ = make_file(tmp_path / "demos")
    with pytest.raises(SystemExit, match="traj_0 has 20 actions, fewer than min_size=30"):
        segment_main([str(h5), "--min-size", "30"], prog="cotpc segment")
    with pytest.raises(SystemExit, match="no such trajectory file"):
        segment_main([str(tmp_path / "missing.h5")], prog="cotpc segment")
    with pytest.raises(SystemExit, match=r"is a directory; pass one trajectory file in it \(demos.h5\)"):
        segment_main([str(tmp_path)], prog="cotpc segment")
    with h5py.File(h5, "r") as f:
        assert not any("subskill_ends" in f[k] for k in f)  # nothing written on failure


@pytest.mark.parametrize("damage, says", [
    (lambda a: a.__setitem__((4, 1), np.nan), r"traj_1: actions holds NaN/inf \(first at index \(4, 1\)\)"),
    (lambda a: a.__setitem__(slice(None), 0.0), r"traj_1: every action of this episode is zero \(25 steps\)"),
])
def test_nan_or_all_zero_actions_are_named_by_every_reader(tmp_path, damage, says):
    h5, _ = make_file(tmp_path / "demos")
    with h5py.File(h5, "r+") as f:
        a = f["traj_1"]["actions"][()]
        damage(a)
        f["traj_1"]["actions"][...] = a
    with pytest.raises(SystemExit, match=says):
        segment_main([str(h5)], prog="cotpc segment")
    with pytest.raises(SystemExit):  # cotpc train: one line on stderr, exit status 2
        cotpc_main(["train", "--data", str(h5), "--policy", "bet", "--out", str(tmp_path / "run"), "--iters", "1"])
    assert not (tmp_path / "run" / "model.safetensors").exists()


def test_maze_defaults_key_steps_and_figures(tmp_path, capsys):
    from cotpc.envs import task_defaults

    h5, _ = make_file(tmp_path / "maze", env_id="cotpc/MovingMaze-v0", with_keys=True)
    segment_main([str(h5), "--plot", str(tmp_path / "fig"), "--num-plot", "2"], prog="cotpc segment")
    out = capsys.readouterr().out
    assert "precision" in out and "recall" in out
    ends, attrs = read_labels(h5)["traj_0"]
    maze = task_defaults("cotpc/MovingMaze-v0")
    assert (attrs["beta"], attrs["cost"]) == (maze.beta, maze.cost) == (1.0, "sum-cosine")
    for name in ("subskills_similarity.png", "subskills_maze_paths.png"):
        png = tmp_path / "fig" / name
        assert png.stat().st_size > 5000 and png.read_bytes()[:4] == b"\x89PNG"


def test_sweep_prints_table_and_writes_nothing(tmp_path, capsys):
    h5, _ = make_file(tmp_path / "maze", with_keys=True)
    cotpc_main(["segment", str(h5), "--sweep-beta", "0.01", "0.05", "--sweep-cost", "mean-cosine", "--json"])
    rows = json.loads(capsys.readouterr().out)["mean-cosine"]
    assert [r["beta"] for r in rows] == [0.01, 0.05]
    assert rows[1]["precision"] == 1.0 and rows[1]["recall"] == 1.0  # boundaries at 7 and 13 are found exactly
    with h5py.File(h5, "r") as f:
        assert not any("subskill_ends" in f[k] for k in f)


def test_bench_segment_small(capsys):
    pytest.importorskip("ruptures")
    cotpc_main(["bench", "segment", "--num", "6", "--length", "40", "--dim", "3", "--repeats", "1",
                "--ruptures-num", "3", "--verify", "3", "--json"])
    r = json.loads(capsys.readouterr().out)
    assert r["verify"]["num"] == 3 and r["verify"]["equal"] == 3
    for impl in ("direct", "prefix"):
        x = r["ruptures"]["cost_impl"][impl]
        lower = x["lower_objective"]
        assert lower["other"] == 0 and lower["ours"] + lower["equal"] == 3  # ruptures is never better
        assert x["speedup_per_traj"] > 0
    assert r["ours_seconds_all"] > 0


def test_privileged_key_steps_as_subskills(tmp_path, capsys):
    h5, ts = make_file(tmp_path / "demos", with_keys=True)
    segment_main([str(h5), "--privileged"], prog="cotpc segment")
    labels = read_labels(h5)
    for ep in ts.episodes:
        ends, attrs = labels[f"traj_{ep.episode_id}"]
        # key states obs[7] and obs[13] end the first two subskills; the last ends with the demo
        np.testing.assert_array_equal(ends, [6, 12, ep.num_steps - 1])
        assert attrs["method"] == "key-steps"
    assert "privileged key_steps" in capsys.readouterr().out
    # Files without key_steps get a message, not a traceback.
    h5, _ = make_file(tmp_path / "nokeys")
    with pytest.raises(SystemExit, match="no key_steps"):
        segment_main([str(h5), "--privileged"], prog="cotpc segment")
