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
