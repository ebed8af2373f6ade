"""The machinery every study shares: train a grid of policies x seeds into ``OUT/runs/<policy>/seed<k>/``,
reusing finished runs and resuming interrupted ones (a run on disk trained with other settings is an error),
several at once (``--jobs``); cached evaluations that are reused while they are newer than the weights; the
statistics over seeds, and the training curves read back from TensorBoard. :func:`train_and_evaluate` is the
generic study runner: a study declares its runs and its :class:`Evaluation` s and writes its own report."""

from __future__ import annotations

import dataclasses
import functools
import json
import multiprocessing as mp
import os
import platform
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, Callable, Optional

import numpy as np
import torch

from cotpc.envs.spec import check_flags
from cotpc.policies import config_from_dict, config_to_dict, get_preset, load_policy
from cotpc.training.precision import cpu_info
from cotpc.training.train import PROTOCOL_CHECKPOINTS, SettingsError, TrainConfig, check_settings, policy_config, train


def stats(rates: list[float]) -> dict:
    a = np.array(rates, dtype=float)
    return {"mean": float(a.mean()), "std": float(a.std(ddof=0)), "best": float(a.max()), "runs": [float(r) for r in a]}


def provenance(*packages: str) -> dict:
    """What a study's results.json records about where it ran: the command, versions (python, torch, numpy and
    ``packages``, by distribution name) and hardware."""
    def version_of(dist: str) -> str | None:
        try:
            return version(dist)
        except PackageNotFoundError:
            return None

    return {
        "command": " ".join(["cotpc"] + sys.argv[1:]) if sys.argv and "cotpc" in sys.argv[0] else None,
        "versions": {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
                     **{p.replace("-", "_"): version_of(p) for p in packages}},
        "hardware": {"machine": platform.machine(), "processor": platform.processor(), "cpus": cpu_count(),
                     "cpu": cpu_info(),  # model and the flags that decide the precision (AMX, AVX512-BF16)
                     "cuda": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None},
    }


def describe_hardware(hardware: dict) -> str:
    """One line for a report: CPU count, model and fast-path flags, and the GPU (older results lack some)."""
    cpu = hardware.get("cpu") or {}
    text = f"{hardware.get('cpus')} CPU(s), {cpu.get('model') or hardware.get('machine')}"
    if cpu.get("flags"):
        text += f" ({' '.join(cpu['flags'])})"
    return text + (f", {hardware['cuda']}" if hardware.get("cuda") else "")


def jsonable(settings) -> dict:
    """A study's settings dataclass (nested TrainConfig included) as JSON values: paths as strings."""
    def convert(v):
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, dict):
            return {k: convert(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [convert(x) for x in v]
        return v

    return convert(dataclasses.asdict(settings))


def _train_worker(config: TrainConfig) -> tuple[str, int, float | None]:
    return config.policy, config.seed, train_run(config, step="[3/5]")


def run_config(template: TrainConfig, run_dir: Path, policy: str, seed: int) -> TrainConfig:
    """One run of a study's grid: the study's ``template`` (data, schedule and every setting the runs share) with
    this run's policy, seed and directory; resuming when a training state is there, ten validation points, and
    ``cotpc train``'s checkpoint interval (a tenth of the run, every twentieth kept with ``keep_checkpoints``): a
    killed study loses at most that much of one run."""
    return dataclasses.replace(
        template, policy=policy, seed=seed, out=run_dir, resume=(run_dir / "training_state.pt").exists(),
        progress=sys.stderr.isatty(), val_every=max(template.iters // 10, 1),
    )


def check_study_flags(prog: str, template: TrainConfig, policies, counts: dict[str, int | None],
                      env_ids=(None,)) -> None:
    """Before a study generates anything: the shared training flags (:func:`check_settings`), each policy with
    them on each task (``--policy bet`` with ``--offset-from cot`` fails here, not when BeT's run starts), and
    ``counts`` ({"--seeds": n, "--jobs": n, ...}, each >= 1 where set); SystemExit naming the first bad one."""
    check_flags(prog, 1, counts)
    try:
        check_settings(template)
        for name in policies:
            get_preset(name)  # an unknown name first, as itself
            for env_id in env_ids:
                policy_config(dataclasses.replace(template, policy=name), env_id)
    except (SettingsError, KeyError, ValueError) as e:
        raise SystemExit(f"{prog}: {e.args[0] if e.args else e}") from None


def train_parallel(out: Path, template: TrainConfig, runs: list[tuple[str, int]], jobs: int) -> None:
    """Train the unfinished ``runs`` in ``jobs`` processes at once. One small model leaves a GPU (or a many-core
    CPU) mostly idle, so independent runs in parallel finish the study several times sooner. Each process gets
    cores / jobs threads; the runs are the same as trained one by one with that thread count."""
    template = dataclasses.replace(template, threads=template.threads or max(1, cpu_count() // jobs))
    todo = [run_config(template, out / "runs" / name / f"seed{seed}", name, seed) for name, seed in runs]
    todo = [config for config in todo if not finished(config.out, config)]
    if not todo:
        return
    print(f"[3/5] training {len(todo)} runs, {jobs} at a time", flush=True)
    # spawn: a forked child must not inherit CUDA or OpenMP state
    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
        for name, seed, seconds in pool.map(_train_worker, todo):
            print(f"[3/5] done: {name} seed {seed} ({seconds} s)", flush=True)


def policy_loader(run_dir: Path, device: str):
    """A function that loads the run's policy on its first call only (no load when every evaluation is cached)."""
    return functools.cache(lambda: load_policy(run_dir, device=device))


def cpu_count() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def fresh_eval(run_dir: Path, name: str) -> dict | None:
    """``run_dir/name`` parsed, if it exists and was written after the run's current weights; else None."""
    path, weights = run_dir / name, run_dir / "model.safetensors"
    if not path.exists() or path.stat().st_mtime_ns < weights.stat().st_mtime_ns:
        return None
    try:
        return json.loads(path.read_text())
    except ValueError:
        return None


def train_run(config: TrainConfig, step: str = "") -> float | None:
    """Train ``config`` (a :func:`run_config`) unless a finished run of it is in ``config.out`` (resuming an
    interrupted one). Returns the training seconds measured when the run was trained (maybe by an earlier call)."""
    run_dir = config.out
    t0 = time.perf_counter()
    if not finished(run_dir, config):
        print(f"{step} train {config.policy} seed {config.seed} ({config.iters} iters) -> {run_dir}".strip(),
              flush=True)
        train(config)
        (run_dir / "timing.json").write_text(json.dumps({"train_seconds": round(time.perf_counter() - t0, 1)}))
    timing = run_dir / "timing.json"
    return json.loads(timing.read_text())["train_seconds"] if timing.exists() else None


# Train settings that do not change what a run learns (where it ran, how it reports): ignored when a run on disk
# is compared with the one a study asks for.
RUN_ONLY = {"data", "out", "resume", "device", "threads", "progress", "keep_checkpoints", "val_every", "ckpt_every",
            "log_every", "stop_after", "bf16"}
_DEFAULTS = {f.name: f.default for f in dataclasses.fields(TrainConfig) if f.default is not dataclasses.MISSING}


def finished(run_dir: Path, wanted: TrainConfig) -> bool:
    """Whether ``run_dir`` holds a finished run of ``wanted``. A run on disk trained with other settings (any
    TrainConfig field that changes what a run learns, or the preset's design) is an error, not something to reuse
    or resume silently."""
    cfg = run_dir / "config.json"
    if not cfg.exists():
        return False
    info = json.loads(cfg.read_text())
    saved = info.get("train", {})
    ignore = set(RUN_ONLY)
    preset = get_preset(wanted.policy)
    if not preset.n_kmeans_centres:
        ignore |= {"n_centres", "offset_from"}  # no k-means head: K and its offsets' source change nothing
    if not preset.cot_targets:
        ignore.add("cot_weight")  # no CoT loss: its weight changes nothing
    diff = {}
    for f in dataclasses.fields(TrainConfig):
        now, was = getattr(wanted, f.name), saved.get(f.name, _DEFAULTS.get(f.name))  # (keys older runs lack)
        now, was = (list(x) if isinstance(x, tuple) else x for x in (now, was))  # config.json holds tuples as lists
        if f.name == "offset_from" and f.name not in ignore:  # unset = the preset's own
            now, was = now or preset.offset_from, was or preset.offset_from
        if f.name not in ignore and was != now:
            diff[f.name] = (was, now)
    if "policy" in info:  # the preset's design (a preset name can change meaning)
        diff.update(_design_diff(info["policy"], preset))
    if diff:
        raise ValueError(f"{run_dir} holds a run trained with other settings (saved, asked for): {diff}. "
                         "Use another --out, or delete that run to train it again.")
    return info.get("step") == wanted.iters


def _design_diff(saved_policy: dict, preset) -> dict:
    """The fields of the preset's config that training flags cannot change (attention design, heads, CoT targets,
    ...) and that differ in a saved run's config: a run of another design under the same preset name."""
    flags = {f.name for f in dataclasses.fields(TrainConfig)} | {"name"}
    saved, now = config_to_dict(config_from_dict(saved_policy)), config_to_dict(preset)
    return {f"policy.{k}": (saved.get(k), v) for k, v in now.items() if k not in flags and saved.get(k) != v}


def plot_learning_curves(runs: Path, names: list[str], path: Path) -> Path:
    """BC loss of ``runs/<name>/seed0`` for each name (from TensorBoard logs), one panel per policy (the losses
    of MSE and centre/offset heads are not on one scale): in training (all window positions, random CoT mask)
    and on validation windows at the last position, as at inference (``val/last_bc``). Runs logged before the
    last-position metrics existed fall back to their all-position ``val/bc``, labelled so."""
    import matplotlib  # heavy (about 1 s): imported only when a figure is drawn

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # after use("Agg"): no display needed

    cols = min(4, len(names))
    rows = (len(names) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.0 * cols, 2.4 * rows), squeeze=False)
    for ax, n in zip(axes.flat, names):
        logdir = runs / n / "seed0" / "tb"
        for tags, style, label in ((("train/bc",), "-", "train (all positions)"),
                                   (("val/last_bc", "val/bc"), "o-", "val (last position)")):
            for tag in tags:
                steps, values = _scalar(logdir, tag)
                if steps:
                    ax.plot(steps, values, style, ms=3, label=label if tag != "val/bc" else "val (all positions)")
                    break
        ax.set_title(n, fontsize=9)
        ax.set_xlabel("iteration", fontsize=8)
        ax.tick_params(labelsize=7)
        if ax.get_lines():  # a run without logs has nothing to label
            ax.legend(fontsize=7)
    for ax in list(axes.flat)[len(names):]:
        ax.axis("off")
    fig.supylabel("BC loss", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _scalar(logdir: Path, tag: str) -> tuple[list[int], list[float]]:
    if not logdir.exists():
        return [], []
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator  # heavy: only for reports

    acc = EventAccumulator(str(logdir))
    acc.Reload()
    if tag not in acc.Tags().get("scalars", []):
        return [], []
    events = acc.Scalars(tag)
    return [e.step for e in events], [e.value for e in events]


@dataclass(frozen=True)
class Evaluation:
    """One evaluation that a study makes of each of its runs, saved in the run's directory and reused."""

    cached: Callable[[Path], Optional[dict]]
    """``run_dir`` -> the summary saved there if it is fresh (written after the run's weights, for the same configs
    and settings), else None."""
    evaluate: Callable[[Path, Callable[[], Any]], dict]
    """(``run_dir``, ``load_policy``) -> the summary of a new evaluation, which it saves. ``load_policy()`` loads
    the run's policy (once, and only when some evaluation is not cached)."""


@dataclass
class GridResults:
    """What :func:`train_and_evaluate` returns; each study turns it into its results.json."""

    summaries: dict[str, dict[str, list[dict]]]
    """policy -> evaluation key -> one summary per seed of that policy, in the order of the runs."""
    train_seconds: dict[str, Optional[float]]
    """``<policy>/seed<k>`` -> the training seconds measured when the run was trained (None: not measured)."""


def train_and_evaluate(out: Path, template: TrainConfig, runs: list[tuple[str, int]],
                       evaluations: dict[str, Evaluation], jobs: int = 1, device: str = "cpu", step: str = "",
                       after_run: Optional[Callable[[str, int, Path, dict[str, dict]], None]] = None) -> GridResults:
    """The grid of a study: train each (policy, seed) of ``runs`` into ``out/runs/<policy>/seed<k>/`` with the
    settings of ``template`` (a TrainConfig with the study's data and schedule; :func:`run_config`) unless it is
    finished there (in ``jobs`` processes at once when jobs > 1; else one by one, resuming), then make
    every evaluation of ``evaluations`` that is not cached. ``after_run(policy, seed, run_dir, summaries by key)``
    is called after each run's evaluations (a study prints its line, or evaluates its checkpoints, there).
    ``step`` prefixes the training lines printed by a one-by-one run."""
    if jobs > 1:
        train_parallel(out, template, runs, jobs)
    summaries: dict[str, dict[str, list[dict]]] = {}
    seconds: dict[str, Optional[float]] = {}
    for name, seed in runs:
        run_dir = out / "runs" / name / f"seed{seed}"
        seconds[f"{name}/seed{seed}"] = train_run(run_config(template, run_dir, name, seed), step=step)
        load = policy_loader(run_dir, device)
        per_key = summaries.setdefault(name, {key: [] for key in evaluations})
        this_run = {}
        for key, ev in evaluations.items():
            summary = ev.cached(run_dir)
            this_run[key] = summary if summary is not None else ev.evaluate(run_dir, load)
            per_key[key].append(this_run[key])
        if after_run is not None:
            after_run(name, seed, run_dir, this_run)
    return GridResults(summaries, seconds)
