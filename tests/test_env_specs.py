"""Each environment declares what the rest of the package needs to know about it (cotpc.envs.spec)."""

import pytest

from cotpc.envs import MAZE_ENV_ID, env_spec, task_defaults
from cotpc.envs import maniskill, moving_maze
from cotpc.envs.spec import GENERIC, SeedRanges


def test_each_environment_is_found_by_its_id_with_the_papers_settings():
    maze = env_spec(MAZE_ENV_ID)
    assert maze is moving_maze.SPEC and maze.horizon == moving_maze.HORIZON == 60
    assert (maze.defaults.context, maze.defaults.n_centres) == (20, 1024)  # the paper's maze settings
    assert (maze.defaults.beta, maze.defaults.cost) == (1.0, "sum-cosine")  # chosen in docs/subskills.md
    assert maze.paper_success["cotpc"] == 44.0
    for env_id, horizon in maniskill.HORIZONS.items():
        spec = env_spec(env_id)
        assert spec.horizon == horizon and task_defaults(env_id) == spec.defaults
        assert (spec.defaults.context, spec.defaults.n_centres, spec.defaults.beta) == (10, 128, 0.05)
    assert env_spec("StackCube-v1").paper_success["cotpc"] == 86.0


def test_unregistered_data_gets_the_generic_defaults():
    assert env_spec("MyRobot-v0") is None and env_spec(None) is None
    assert task_defaults("MyRobot-v0") == GENERIC == task_defaults(None)
    assert (GENERIC.context, GENERIC.n_centres, GENERIC.beta, GENERIC.cost) == (10, 128, 0.05, "mean-cosine")


def test_one_seed_range_mechanism_for_every_environment():
    assert isinstance(moving_maze.SEEDS, SeedRanges) and isinstance(maniskill.SEEDS, SeedRanges)
    assert moving_maze.seeds_for("val", 2, offset=3).tolist() == [1_000_003, 1_000_004]
    assert moving_maze.split_of_seed(2_000_000) == "test"
    with pytest.raises(ValueError, match="belongs to the test split"):
        moving_maze.check_seed(2_000_000, "train")
    with pytest.raises(ValueError, match="overlap"):
        SeedRanges({"a": (0, 10), "b": (5, 20)})
