"""Task suites: what the command line runs for each benchmark, found by name (``cotpc demos NAME``, ``cotpc
reproduce NAME``) or by a run's env id (``cotpc eval``, ``cotpc segment --plot``).

A suite is declared once, in the study module of its environment (``studies/<name>.py`` for each name in
:data:`cotpc.envs.TASKS`: ``maze``, ``maniskill``, ``kitchen``), from the environment's own folder ``envs/<name>/``
(demos, rollouts) and the generic runner. Adding a benchmark is its folder, its study and its name in
``cotpc.envs.TASKS``; nothing in ``cli/`` changes.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

from cotpc.envs import TASKS

# The modules that declare a suite, one per environment folder, imported on first use (each registers its own).
SUITE_MODULES = tuple(f"cotpc.studies.{name}" for name in TASKS)


@dataclass(frozen=True)
class Suite:
    """One benchmark as the command line sees it."""

    name: str
    """Subcommand name: ``cotpc demos NAME``, ``cotpc reproduce NAME``."""
    owns: Callable[[Optional[str]], bool]
    """Whether a run or data file of this env id belongs to the suite."""
    demos: type
    """The tyro config of ``cotpc demos NAME`` (a dataclass whose docstring is the subcommand's help)."""
    make_demos: Callable[[Any], dict[str, Path]]
    """Writes the demos a ``demos`` config asks for; returns the split files."""
    evaluate: Callable[[Any, dict, str], dict]
    """``cotpc eval``: (EvalRequest, the run's config.json, its env id) -> summary (also printed and saved)."""
    reproduce: type
    """The tyro config of ``cotpc reproduce NAME``."""
    run_study: Callable[[Any], Any]
    """Runs a ``reproduce`` config (and prints its summary)."""
    subskill_plots: Optional[Callable[[Path, list, list, list], list[Path]]] = None
    """Extra figures of discovered subskills for ``cotpc segment --plot``: (dir, episodes, ends, titles)."""


_SUITES: dict[str, Suite] = {}


def register_suite(suite: Suite) -> Suite:
    """Make ``suite`` findable (each study module registers its own on import)."""
    if suite.name in _SUITES and _SUITES[suite.name] != suite:
        raise ValueError(f"task suite {suite.name!r} is already registered")
    _SUITES[suite.name] = suite
    return suite


def suites() -> dict[str, Suite]:
    """Every suite, by name (importing the declaring modules on first use)."""
    for module in SUITE_MODULES:
        importlib.import_module(module)
    return dict(_SUITES)


def suite_for_env(env_id: Optional[str]) -> Optional[Suite]:
    """The suite a run or data file of ``env_id`` belongs to, or None."""
    return next((s for s in suites().values() if s.owns(env_id)), None)


def suite_of_config(cfg: Any, kind: str) -> Suite:
    """The suite whose ``kind`` ('demos' or 'reproduce') config ``cfg`` is."""
    return next(s for s in suites().values() if type(cfg) is getattr(s, kind))
