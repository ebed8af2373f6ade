"""ManiSkill3 tasks (StackCube-v1, PegInsertionSide-v1, PickCube-v1, ...) with state observations, headless.

Install with ``pip install -e '.[maniskill]'`` (``mani-skill==3.0.1`` with ``numpy<2``). Nothing in the rest of
the package imports this module, so Moving Maze never needs ManiSkill.

**Machines with no render device.** SAPIEN needs a Vulkan device to *construct* ``RenderMaterial`` and
``RenderTexture2D`` objects, and ManiSkill's URDF/MJCF loaders and actor builders construct them even with
``render_backend="none"``; without a device every environment fails to build with ``RuntimeError: failed to
find a rendering device``. :func:`ensure_headless` probes for a device (by constructing a
``sapien.render.RenderMaterial()``) and, **only when that fails**, replaces those two classes with inert
stand-ins in the modules that hold them. Physics is untouched (rendering components are never added to a scene
that cannot render), so the simulation is the same as on a machine with a device; where a device exists nothing
is patched at all. Images (``obs_mode="rgb"``, videos) still need a real device.

Seeds: ManiSkill3 draws a task's initial state (cube poses, and for PegInsertionSide also the peg and hole
sizes) from ``reset(seed=...)``. Training demos use seeds from :data:`SEEDS` ``"train"`` and test demos from
``"test"``; the two ranges are disjoint and checked wherever a seed is used (see :func:`check_seed`).
"""

from __future__ import annotations

import importlib
import os
from typing import Any

import gymnasium as gym

import numpy as np

from cotpc.envs.spec import DEFAULT_SEEDS, EnvSpec, SeedRanges, TaskDefaults, register  # noqa: F401 (SeedRanges: re-exported)

# Tasks with an official ManiSkill3 motion-planning solution that need no asset download, and the evaluation
# horizon for each: the paper's 200 for Stack Cube and Peg Insertion (ManiSkill3's registered limits, 50 and
# 100, are shorter than the planner's own demos: about 107 and 151 steps).
HORIZONS = {
    "StackCube-v1": 200,
    "PegInsertionSide-v1": 200,
    "PickCube-v1": 200,
    "PushCube-v1": 200,
    "PullCube-v1": 200,
    "LiftPegUpright-v1": 200,
    "PlugCharger-v1": 200,
    "StackPyramid-v1": 300,
}
CONTROL_MODES = ("pd_joint_delta_pos", "pd_ee_delta_pose")


def is_maniskill_env(env_id: str | None) -> bool:
    """True for ManiSkill3 task ids such as ``StackCube-v1`` (without importing mani_skill)."""
    return bool(env_id) and env_id in HORIZONS


# ManiSkill3's own examples and datasets use seeds from 0; our test seeds start far above any train seed.
SEEDS = DEFAULT_SEEDS
check_seed = SEEDS.check
# The paper's ManiSkill2 numbers (state observations; unseen configs, Peg Insertion 0-shot), success %.
PAPER_SUCCESS = {
    "StackCube-v1": {"bc": 1.0, "dt": 19.0, "bet": 73.0, "dp": 84.5, "dd": 26.0, "cotpc": 86.0},
    "PegInsertionSide-v1": {"bc": 0.0, "dt": 17.5, "bet": 42.5, "dp": 57.6, "dd": 12.6, "cotpc": 59.3},
}
for _env_id, _horizon in HORIZONS.items():  # the paper's ManiSkill settings: context 10, K 128, beta 0.05
    register(EnvSpec(_env_id, _horizon, TaskDefaults(context=10, n_centres=128, beta=0.05, cost="mean-cosine"),
                     SEEDS, PAPER_SUCCESS.get(_env_id, {})))


_HEADLESS: bool | None = None  # None: not probed yet; True: the stand-ins are installed; False: a device exists


class _InertRenderObject:
    """Accepts any constructor arguments and attribute writes; stands in for SAPIEN render objects."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self._attrs: dict[str, Any] = dict(kwargs)

    def __setattr__(self, name: str, value: Any) -> None:
        object.__setattr__(self, name, value)

    def __getattr__(self, name: str) -> Any:  # only called for attributes never set
        attrs = object.__getattribute__(self, "_attrs")
        if name in attrs:
            return attrs[name]
        raise AttributeError(name)


class InertRenderMaterial(_InertRenderObject):
    """Stand-in for ``sapien.render.RenderMaterial`` on machines with no render device."""


class InertRenderTexture2D(_InertRenderObject):
    """Stand-in for ``sapien.render.RenderTexture2D`` on machines with no render device."""


def has_render_device() -> bool:
    """Whether SAPIEN finds a rendering (Vulkan) device: constructing a RenderMaterial needs one."""
    import sapien  # the optional [maniskill] extra: imported only when a ManiSkill3 task is used

    if _HEADLESS:  # already patched: the class in sapien.render is ours, ask the original
        return False
    try:
        sapien.render.RenderMaterial()
    except RuntimeError:
        return False
    return True


def ensure_headless() -> bool:
    """Make ManiSkill3 environments build on a machine with no render device; a no-op where one exists.

    Returns True when the stand-ins were installed (no device), False when a device was found. Idempotent;
    call it in every process before the first ``gym.make`` (:func:`make_env` does). Set ``COTPC_NO_HEADLESS=1``
    to never patch (the environment then fails to build without a device, with SAPIEN's own error).
    """
    global _HEADLESS
    if _HEADLESS is not None:
        return _HEADLESS
    if os.environ.get("COTPC_NO_HEADLESS") == "1" or has_render_device():
        _HEADLESS = False
        return False
    import sapien  # the optional [maniskill] extra

    targets = ["sapien.render", "sapien.pysapien.render", "sapien.wrapper.urdf_loader", "sapien.wrapper.renderer",
               "mani_skill.utils.building._mjcf_loader"]
    for name in targets:
        module = importlib.import_module(name)
        if hasattr(module, "RenderMaterial"):
            module.RenderMaterial = InertRenderMaterial
        if hasattr(module, "RenderTexture2D"):
            module.RenderTexture2D = InertRenderTexture2D
    assert sapien.render.RenderMaterial is InertRenderMaterial
    _HEADLESS = True
    return True


def import_maniskill():
    """Import mani_skill (registering its tasks) with a clear message when the extra is not installed."""
    try:
        import mani_skill.envs  # noqa: F401  (the optional extra; importing it registers the tasks with gymnasium)
    except ImportError as e:
        raise SystemExit(
            f"ManiSkill3 is not installed ({e}). Install the extra: pip install -e '.[maniskill]' "
            "(mani-skill==3.0.1 needs numpy<2)"
        ) from None
    if int(np.__version__.split(".")[0]) >= 2:
        raise SystemExit(
            f"numpy {np.__version__} is installed, but ManiSkill3's motion planner (mplib 0.1.1) crashes with "
            "numpy 2; install 'numpy<2' (the [maniskill] extra pins it)"
        )


def make_env(
    env_id: str,
    control_mode: str = "pd_joint_delta_pos",
    obs_mode: str = "state",
    max_episode_steps: int | None = None,
    num_envs: int = 1,
    sim_backend: str = "physx_cpu",
    **kwargs: Any,
):
    """``gym.make`` a ManiSkill3 task without rendering (headless-safe), with state observations by default.

    ``max_episode_steps`` defaults to :data:`HORIZONS` (the paper's horizon), not ManiSkill's shorter limit.
    ``sim_backend="physx_cuda"`` with ``num_envs=N`` runs N environments on the GPU in one process.
    """
    import_maniskill()
    ensure_headless()
    if max_episode_steps is None:
        max_episode_steps = HORIZONS.get(env_id)
    make_kwargs = dict(
        obs_mode=obs_mode,
        control_mode=control_mode,
        sim_backend=sim_backend,
        render_backend="none" if _HEADLESS else kwargs.pop("render_backend", "none"),
        render_mode=kwargs.pop("render_mode", None),
        num_envs=num_envs,
        **kwargs,
    )
    if max_episode_steps is not None:
        make_kwargs["max_episode_steps"] = max_episode_steps
    return gym.make(env_id, **make_kwargs)


def flat_obs(obs) -> np.ndarray:
    """A state observation (torch tensor (B, q) or (q,)) as a float32 numpy array of shape (B, q)."""
    if hasattr(obs, "detach"):
        obs = obs.detach().cpu().numpy()
    obs = np.asarray(obs, dtype=np.float32)
    return obs[None] if obs.ndim == 1 else obs


# --- privileged key states: the official CoTPC code's chain of thought --------------------------------------
# The official code (SeanJia/CoTPC, src/data.py) reads its key states from flags that its patched ManiSkill2
# environments report each step. We compute the same flags from the simulator while a demo is recorded (no
# patch) and store them beside the demo, so discovered subskills can be scored against them and CoTPC trained
# on them (`cotpc segment --privileged`). The flags of step t are about the state after action t, obs[t + 1].
KEY_STATE_FLAGS = {
    "StackCube-v1": ("is_cubeA_grasped", "is_cubeA_on_cubeB"),
    "PegInsertionSide-v1": ("is_grasped", "pre_inserted"),
    "PickCube-v1": ("is_grasped",),
}


def _flags(x) -> np.ndarray:
    return np.asarray(x.detach().cpu() if hasattr(x, "detach") else x, dtype=bool).reshape(-1)


def key_state_arrays(env_id: str, env, info: dict) -> dict[str, np.ndarray]:
    """This step's key-state flags of ``env_id`` (:data:`KEY_STATE_FLAGS`; none for other tasks), one (B,) bool
    array per flag (B parallel environments), from ``info`` or, for Peg Insertion, from the simulator as the
    official code's patch and ManiSkill3's dense reward define them: grasped with the gripper at most 20 degrees
    off, and pre-inserted when the peg and its head are both within 1 cm of the hole's axis (in the goal frame's
    y-z plane) while grasped."""
    if env_id == "PegInsertionSide-v1":
        task = env.unwrapped
        grasped = task.agent.is_grasping(task.peg, max_angle=20)
        head = (task.goal_pose.inv() * task.peg_head_pose).p[:, 1:]
        centre = (task.goal_pose.inv() * task.peg.pose).p[:, 1:]
        lined_up = (head.norm(dim=1) < 0.01) & (centre.norm(dim=1) < 0.01)
        return {"is_grasped": _flags(grasped), "pre_inserted": _flags(grasped & lined_up)}
    return {name: _flags(info[name]) for name in KEY_STATE_FLAGS.get(env_id, ())}


def key_state_flags(env_id: str, env, info: dict) -> dict[str, bool]:
    """:func:`key_state_arrays` of a single environment (its first), as bools."""
    return {name: bool(value[0]) for name, value in key_state_arrays(env_id, env, info).items()}


def key_steps_from_flags(env_id: str, flags: np.ndarray) -> np.ndarray:
    """The privileged key steps (state indices, ascending) of one demo from its per-step ``flags`` (N, F), F the
    flags of :data:`KEY_STATE_FLAGS` in order, by the official code's rules: the first state in which each flag
    holds, except Stack Cube's second key state, the state *before* cube A first rests on cube B released (its
    "right before" rule). A flag that never holds gives no key step (the final state is always a key state and
    is not listed)."""
    flags = np.asarray(flags, dtype=bool)
    names = KEY_STATE_FLAGS.get(env_id, ())
    if flags.ndim != 2 or flags.shape[1] != len(names):
        raise ValueError(f"{env_id}: expected flags of shape (steps, {len(names)}) for {names}, got {flags.shape}")
    events = [flags[:, i] for i in range(len(names))]
    shift = [1] * len(names)  # flags[t] describe obs[t + 1]
    if env_id == "StackCube-v1":
        events[1] = flags[:, 1] & ~flags[:, 0]  # on cube B and no longer grasped
        shift[1] = 0
    steps = [int(np.argmax(e)) + s for e, s in zip(events, shift) if e.any()]
    return np.unique(np.clip(steps, 1, len(flags))).astype(np.int64)
