"""What ``cotpc eval`` asks of a task suite's evaluation: one request type for every environment, so the command
line never needs to know which environment a run was trained on (the suite registered for the run's env id
evaluates it, :mod:`cotpc.studies.suites`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal, Optional

import tyro

from cotpc.policies.policy import CheckpointError, load_policy


@dataclass
class EvalRequest:
    """Roll a trained policy out on the seen, validation or unseen configs of its task and report its success
    rate with a 95% confidence interval. The task is the one the run was trained on (its config.json)."""

    run: tyro.conf.Positional[Path]
    """Run directory written by `cotpc train` (config.json + model.safetensors)."""
    split: Literal["seen", "val", "unseen"] = "unseen"
    """seen = the training demos' configs; val = the validation demos' configs (for choosing settings and
    checkpoints, where the task's demos have a validation split); unseen = the test demos' configs. The three
    seed ranges are disjoint."""
    episodes: Optional[int] = None
    """Evaluate only the first N configs of the split (default: all)."""
    demos: Optional[Path] = None
    """Directory with the split files, train.{h5,json} and test.{h5,json} (default: the directory of the run's
    training data)."""
    checkpoint: Literal["last", "best"] = "last"
    """last = the run's final weights; best = its best validation action error (never selected on test success)."""
    video: Optional[Path] = None
    """Write GIFs of the first --num-videos rollouts into this directory (where the task renders headless)."""
    num_videos: int = 4
    """How many rollouts to record with --video."""
    rules: Optional[str] = None
    """A rule variant of the task, where its docs define some (default: the paper's rules)."""
    out: Optional[Path] = None
    """Per-episode results as JSON (default: RUN/eval_<split>.json, with the rule variant in the name when not
    the paper's)."""
    device: str = "cpu"
    """Device for the policy."""
    horizon: Optional[int] = None
    """Steps per episode (default: the task's, as in the paper)."""
    procs: int = 1
    """Processes for CPU simulation, each with one environment and a copy of the policy (tasks simulated one
    environment per process)."""
    backend: Literal["auto", "cpu", "gpu"] = "auto"
    """Simulator, for tasks with a GPU-parallel simulation: 'gpu' = --num-envs at once (policy on --device),
    'cpu' = process pool; 'auto' = gpu when CUDA is available."""
    num_envs: int = 256
    """Environments simulated at once with --backend gpu."""
    sampler_steps: Optional[int] = None
    """Denoising steps at inference, for the diffusion policies (dp, dd): DDIM with this many steps instead of
    the run's ``inference_steps`` (fewer: faster control, maybe lower success)."""

    action_rule: Optional[Literal["mode", "mean", "sample"]] = None
    """How a multi-modal transformer head (bet, cotpc, gmm presets) acts: ``mode`` (the run's default: the arg-max
    centre plus its offset, or the most likely Gaussian's mean), ``mean`` (the expected action under the head's
    distribution) or ``sample`` (a centre drawn from the head's probabilities, seeded: the original BeT's rule).
    The evaluation file gets an ``_mean`` / ``_sample`` suffix, so it never replaces the run's own."""
    action_horizon: Optional[int] = None
    """Actions of each planned chunk executed before planning again, for the diffusion policies (dp, dd) and the
    transformers trained with ``--action-chunk`` (at most the chunk), instead of the run's ``action_horizon``
    (1 = predict at every step, closed loop). The file gets an ``_ahN`` suffix."""
    compile: bool = False
    """``torch.compile`` the transformer policies' network call (one compile of ~10-20 s per batch size on a CPU;
    actions agree with the eager path to ~1e-7, not bit for bit, so a closed-loop rollout can rarely differ).
    Recorded in the evaluation file."""

    def __post_init__(self):
        # (not envs.spec.check_flags: the environments' rollouts import this module)
        for flag, value in (("--episodes", self.episodes), ("--horizon", self.horizon), ("--procs", self.procs),
                            ("--num-envs", self.num_envs), ("--num-videos", self.num_videos),
                            ("--sampler-steps", self.sampler_steps), ("--action-horizon", self.action_horizon)):
            if value is not None and value < (0 if flag == "--num-videos" else 1):  # --episodes 0 is not "all"
                raise SystemExit(f"cotpc eval: {flag} must be >= {0 if flag == '--num-videos' else 1}, got {value}")

    def inference_settings(self) -> dict:
        """Every inference setting of the request by its flag's name, None where the run's own is kept (recorded
        in the evaluation file)."""
        return {**{attr: getattr(self, attr) for attr, *_ in INFERENCE_SETTINGS}, "compile": self.compile}

    def inference_overrides(self) -> dict:
        """The inference settings this request replaces in the run's config ({config field: value})."""
        return {field: getattr(self, attr) for attr, _, field, _ in INFERENCE_SETTINGS
                if getattr(self, attr) is not None}

    def variant_suffix(self) -> str:
        """File-name suffix of an evaluation with non-default inference settings (never overwrite the run's own)."""
        return (f"_steps{self.sampler_steps}" if self.sampler_steps else "") + (
            f"_{self.action_rule}" if self.action_rule not in (None, "mode") else "") + (
            f"_ah{self.action_horizon}" if self.action_horizon else "")

    def demos_and_weights(self, info: dict) -> tuple[Path, Path]:
        """The demo directory (given, or that of the run's training data) and the checkpoint to evaluate."""
        demos = self.demos
        if demos is None:
            data_path = info.get("dataset", {}).get("path")
            if not data_path:
                raise SystemExit(f"cotpc eval: {self.run}/config.json does not name its data; pass --demos DIR")
            demos = Path(data_path).parent
        return demos, (self.run if self.checkpoint == "last" else self.run / "best")


# Inference settings a request may override: (EvalRequest field, flag, config field, the families that have it).
INFERENCE_SETTINGS = (
    ("action_rule", "--action-rule", "action_rule", "transformer"),
    ("sampler_steps", "--sampler-steps", "inference_steps", "diffusion"),
    ("action_horizon", "--action-horizon", "action_horizon", "diffusion and transformer"),
)


def load_for_eval(run_dir: str | Path, device: str = "cpu", overrides: Optional[dict] = None, compile: bool = False):
    """:func:`cotpc.load_policy`, with the inference settings in ``overrides`` ({config field: value}, from
    :meth:`EvalRequest.inference_overrides`) replacing the run's (module level, so a process pool can pickle a
    ``functools.partial`` of it); ``compile``: :attr:`EvalRequest.compile`."""
    try:
        policy = load_policy(run_dir, device=device, compile=compile)
    except ValueError as e:
        if not compile or isinstance(e, CheckpointError):
            raise
        raise SystemExit(f"cotpc eval: --compile: {e}") from None
    flags = {field: (flag, families) for _, flag, field, families in INFERENCE_SETTINGS}
    for field, value in (overrides or {}).items():
        flag, families = flags[field]
        cfg = policy.model.cfg
        if not hasattr(cfg, field):
            raise SystemExit(f"cotpc eval: {flag} is for the {families} policies; {run_dir} is {cfg.name!r}")
        try:
            policy.model.cfg = cfg.replace(**{field: value})
        except ValueError as e:
            raise SystemExit(f"cotpc eval: {flag} {value}: {e}") from None
    return policy
