"""Each environment declares what the rest of the package needs to know about it (cotpc.envs.spec)."""

import pytest

from cotpc.envs import MAZE_ENV_ID, env_spec, task_defaults
from cotpc.envs.maniskill import env as maniskill
from cotpc.envs.maze import env as moving_maze
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


# ------------------------------------------------------------------ task suites: what the command line runs


def test_suites_are_found_by_name_and_env_id():
    from cotpc.envs.maze.env import ENV_ID
    from cotpc.studies.suites import suite_for_env, suites

    assert {"maze", "maniskill"} <= set(suites())
    assert suite_for_env(ENV_ID).name == "maze"
    assert suite_for_env("StackCube-v1").name == "maniskill"
    assert suite_for_env("SomeoneElsesTask-v0") is None and suite_for_env(None) is None


def test_a_new_suite_is_reached_by_the_command_line_without_touching_cli(tmp_path):
    """Registering a suite is all a benchmark needs: `cotpc demos NAME` and `cotpc eval` on its runs reach it."""
    from dataclasses import dataclass

    import pytest

    from cotpc.cli.main import main as cotpc_main
    from cotpc.studies import suites as registry

    calls = []

    @dataclass
    class ToyDemos:
        """Toy demos."""

        n: int = 1
        """How many."""

    @dataclass
    class ToyStudy:
        """Toy study."""

        seeds: int = 1
        """Seeds."""

    toy = registry.Suite(
        name="toy", owns=lambda env_id: env_id == "Toy-v0", demos=ToyDemos,
        make_demos=lambda cfg: calls.append(("demos", cfg.n)) or {},
        evaluate=lambda req, info, env_id: calls.append(("eval", env_id, req.split)) or {},
        reproduce=ToyStudy, run_study=lambda cfg: calls.append(("study", cfg.seeds)),
    )
    registry.register_suite(toy)
    try:
        cotpc_main(["demos", "toy", "--n", "3"])
        cotpc_main(["reproduce", "toy", "--seeds", "2"])
        run = tmp_path / "run"
        run.mkdir()
        (run / "config.json").write_text('{"format": "cotpc-policy", "dataset": {"env_id": "Toy-v0"}}')
        cotpc_main(["eval", str(run), "--split", "val"])
        assert calls == [("demos", 3), ("study", 2), ("eval", "Toy-v0", "val")]
        (run / "config.json").write_text('{"format": "cotpc-policy", "dataset": {"env_id": "Nobody-v0"}}')
        with pytest.raises(SystemExit, match="no task suite evaluates"):
            cotpc_main(["eval", str(run)])
    finally:
        registry._SUITES.pop("toy")
