"""The ``kitchen`` task suite: the paper's ordered Franka Kitchen variant (``cotpc/FrankaKitchenOrdered-v0``).

``cotpc demos kitchen`` writes demos from the scripted demonstrator (:mod:`cotpc.demos.kitchen`); ``cotpc eval`` on a
kitchen run reports the success rate and the average number of sub-tasks completed in order
(:mod:`cotpc.evaluation.kitchen`). The full study (``cotpc reproduce kitchen``) is not implemented yet and says so.
Importing this module imports neither mujoco nor gymnasium_robotics (the command line imports every suite module
to build its help).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cotpc.demos.kitchen import KitchenDemos, make_demos
from cotpc.envs.kitchen import ENV_ID
from cotpc.evaluation.kitchen import evaluate_run
from cotpc.studies.suites import Suite, register_suite


@dataclass
class KitchenReproduce:
    """The paper's Franka Kitchen study (not implemented yet): demos -> subskills -> BC/DT/BeT/CoTPC -> success
    rate and average number of completed sub-tasks on seen/val/unseen configs."""

    out: Path = Path("runs/kitchen")
    """Output directory."""


def reproduce(cfg: KitchenReproduce) -> dict:
    """``cotpc reproduce kitchen`` (not implemented yet)."""
    raise SystemExit("kitchen study (cotpc reproduce kitchen) is not implemented yet")


SUITE = register_suite(Suite(
    name="kitchen", owns=lambda env_id: env_id == ENV_ID, demos=KitchenDemos, make_demos=make_demos,
    evaluate=evaluate_run, reproduce=KitchenReproduce, run_study=reproduce,
))
