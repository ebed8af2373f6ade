"""scripts/ms-trace.py's phase classification of a Stack Cube episode (the rollout itself needs ManiSkill3)."""

import importlib.util
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "ms-trace.py"


@pytest.fixture(scope="module")
def trace():
    spec = importlib.util.spec_from_file_location("ms_trace", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def rows(flags: str, grippers=None, xy=0.1):
    """One row per character: '.' free, 'G' grasped, 'B' on B while grasped, 'b' on B released, 'S' success."""
    out = []
    for i, c in enumerate(flags):
        out.append({"grasped": c in "GB", "on_b": c in "Bb", "success": c == "S", "a_height": 0.05 if c == "G" else 0.0,
                    "xy_to_b": xy, "gripper": (grippers[i] if grippers else (-1.0 if c in "GB" else 1.0)),
                    "arm": 0.1, "tcp_to_a_xy": 0.002 * (i + 1)})
    return out


@pytest.mark.parametrize("flags, phase", [
    ("......", "no grasp"), ("..GG..GG", "dropped"), ("..GGGG", "not placed"), ("..GGBBb", "not released"),
    ("..GGBbS", "success"),
])
def test_every_phase(trace, flags, phase):
    assert trace.classify(rows(flags))["phase"] == phase


def test_a_drop_records_where_and_how(trace):
    r = rows("..GGG.", grippers=[1, -1, -1, -1, -1, 1], xy=0.2)
    out = trace.classify(r)
    assert out["phase"] == "dropped" and out["loss_step"] == 5 and out["loss_gripper"] == 1
    assert out["grasped_steps_before_loss"] == 3 and out["loss_xy_to_b"] == 0.2 and not out["regrasped"]
    # the offset in the state the close command acted on (step 0), and the open -> close -> open switches
    assert out["close_offset_xy"] == pytest.approx(0.002) and out["gripper_switches"] == 2
    summary = trace.summarise([out, trace.classify(rows("......"))])
    assert summary["phases"]["dropped"] == 1 and summary["phases"]["no grasp"] == 1
    assert summary["dropped"]["gripper_command_at_loss"] == [1.0]


def test_grasp_held_and_lift(trace):
    short = trace.classify(rows("..G.G." + "G" * 3))  # grasps of 1, 1 and 3 steps: none held for 10
    held = trace.classify(rows(".." + "G" * 12))  # held 12 steps, cube A 5 cm up: lifted
    assert (short["longest_grasp"], held["longest_grasp"]) == (3, 12) and held["lifted"]
    s = trace.summarise([short, held, trace.classify(rows("...."))])
    assert s["grasped_once"] == pytest.approx(2 / 3) and s["held_10_steps"] == pytest.approx(1 / 3)
    assert s["lifted_2cm"] == pytest.approx(2 / 3)  # rows() puts a grasped cube 5 cm up


def test_close_offset_split_along_and_across_the_way(trace):
    # the gripper starts 10 cm from cube A in -x; it closes (step 2) 6 mm short of the cube and 3 mm to one side
    r = rows("..GGG", grippers=[1, 1, -1, -1, -1])
    for row in r:
        row["acted_tcp_to_a"] = [0.006, 0.003]
    out = trace.classify(r, start=[-0.1, 0.0])
    assert out["close_step"] == 2
    assert out["close_short"] == pytest.approx(0.006) and abs(out["close_across"]) == pytest.approx(0.003)
    s = trace.summarise([out])
    assert s["close_short_mm_mean"] == 6.0 and s["close_across_mm_abs_mean"] == 3.0
