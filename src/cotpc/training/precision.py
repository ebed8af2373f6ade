"""Choosing bf16 or fp32 by timing the real training step, and the alternating timer it uses.

Machines of one kind differ: on a CPU with AMX-BF16 a bf16 matmul is ~7x an fp32 one, on a CPU with only
AVX512-BF16 it is ~0.5x, and on one without bf16 instructions far slower (emulated; `cotpc bench train`
prints both matmul peaks). A lone matmul says little about
the whole step (attention, GELU, LayerNorm, copies and the optimiser do not speed up alike), so the decision times
the step itself: the model being trained, at its batch size, in both precisions, alternating, fastest of a few
rounds (a busy machine only ever slows a round down, so the minimum is the fair figure).
"""

from __future__ import annotations

import contextlib
import platform
import time
from contextlib import nullcontext
from pathlib import Path
from dataclasses import asdict, dataclass
from typing import Callable, Optional

import torch


def autocast_for(device: str, bf16: bool):
    """A zero-argument context-manager factory: bf16 autocast on ``device``, or nothing (fp32)."""
    if not bf16:
        return nullcontext
    kind = device.split(":")[0]
    return lambda: torch.autocast(kind, dtype=torch.bfloat16)


def synchronize(device: str) -> None:
    """Wait for the device's queued work (CUDA runs asynchronously; a timer must not stop before it ends)."""
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def time_alternating(fns: dict[str, Callable[[], object]], rounds: int = 3, reps: int = 2, warmup: int = 1,
                     device: str = "cpu") -> dict[str, list[float]]:
    """Seconds of each call of each function. Rounds alternate the functions (``reps`` calls each), so a slow
    spell of a shared machine hits all of them alike; ``warmup`` untimed calls of each come first."""
    for fn in fns.values():
        for _ in range(warmup):
            fn()
    synchronize(device)
    times: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(rounds):
        for name, fn in fns.items():
            for _ in range(reps):
                t = time.perf_counter()
                fn()
                synchronize(device)
                times[name].append(time.perf_counter() - t)
    return times


@dataclass
class PrecisionChoice:
    """What training (and ``cotpc bench``) chose, and the timings it chose on (stored in the run's config)."""

    bf16: bool
    """bf16 autocast of the forward pass (weights, optimiser and losses stay fp32)."""
    how: str
    """How it was decided, in words."""
    fp32_ms: Optional[float] = None
    """Fastest fp32 training step (ms) at the batch size the decision was made at."""
    bf16_ms: Optional[float] = None
    """Fastest bf16 training step (ms) at that batch size."""
    batch_size: Optional[int] = None
    """The batch size of the timed steps."""

    def as_dict(self) -> dict:
        return asdict(self)

    def summary(self) -> str:
        times = ""
        if self.fp32_ms is not None and self.bf16_ms is not None:
            times = f" (step at batch {self.batch_size}: fp32 {self.fp32_ms:.1f} ms, bf16 {self.bf16_ms:.1f} ms)"
        return f"precision {'bf16 autocast' if self.bf16 else 'fp32'}: {self.how}{times}"


def _race(make_step, batch: int, rounds: int, min_s: float = 0.1) -> tuple[float, float]:
    """Fastest fp32 and bf16 step at ``batch``: alternating rounds, each of enough calls to last ~``min_s``
    (a millisecond step timed once is timer noise)."""
    fp32, bf16 = make_step(False, batch), make_step(True, batch)
    fp32()  # warm-up, and the length of one call
    t = time.perf_counter()
    fp32()
    reps = max(1, min(50, round(min_s / max(time.perf_counter() - t, 1e-6))))
    bf16()
    best = {"fp32": float("inf"), "bf16": float("inf")}
    for _ in range(rounds):
        for name, fn in (("fp32", fp32), ("bf16", bf16)):
            for _ in range(reps):
                t = time.perf_counter()
                fn()
                best[name] = min(best[name], time.perf_counter() - t)
    return best["fp32"], best["bf16"]


def cpu_flags() -> set[str]:
    """The CPU's feature flags (``/proc/cpuinfo``; empty where it cannot be read)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    return set(line.split(":", 1)[1].split())
    except OSError:
        pass
    return set()


def native_bf16(flags: set[str] | None = None) -> bool:
    """Whether the CPU has bf16 instructions (AMX-BF16 or AVX512-BF16). Without them torch emulates bf16 and a bf16
    step is several times slower than fp32 (measured 6-10x on AVX2 EPYCs), so there is nothing to race. Where the
    flags cannot be read, assume the instructions may be there and let the race decide."""
    flags = cpu_flags() if flags is None else flags
    return not flags or bool({"amx_bf16", "avx512_bf16"} & flags)


def choose_precision(make_step: Callable[[bool, int], Callable[[], object]], batch_size: int, device: str,
                     rounds: int = 3, margin: float = 0.9, native: bool | None = None) -> PrecisionChoice:
    """Time the training step in fp32 and bf16 and keep the faster (bf16 only if under ``margin`` x fp32).

    ``make_step(bf16, batch)`` returns a function doing one training step of the real model (on a copy, so the
    run itself is untouched) in that precision at that batch size. On a CPU without bf16 instructions
    (``native``, default :func:`native_bf16`) fp32 is chosen without racing: an emulated bf16 step at the full
    batch can take seconds. Elsewhere the race runs every round (fastest of ``rounds``): on a shared machine one
    busy spell can make a single round look 5-10x slow (seen: a small-batch race under load called AMX bf16
    "emulated"). On CUDA bf16 is used where the device supports it (tensor cores), without timing.
    """
    if device.startswith("cuda"):
        ok = torch.cuda.is_bf16_supported()
        return PrecisionChoice(ok, "CUDA device " + ("supports bf16" if ok else "without bf16 support"))
    if not (native_bf16() if native is None else native):
        return PrecisionChoice(False, "no bf16 instructions on this CPU (neither amx_bf16 nor avx512_bf16 in its "
                                      "flags): bf16 would be emulated")
    fp32, bf16 = _race(make_step, batch_size, rounds=rounds)
    use = bf16 < margin * fp32
    how = (f"bf16 step {'faster' if use else 'not faster'} than fp32 by the {margin} margin "
           f"(fastest of {rounds} alternating rounds)")
    return PrecisionChoice(use, how, 1000 * fp32, 1000 * bf16, batch_size)


def cpu_info() -> dict:
    """The CPU model and the flags that decide the fast path (AMX, AVX512-BF16), from /proc/cpuinfo."""
    model, flags = platform.processor() or platform.machine(), set()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name") and model in ("", platform.machine(), platform.processor()):
                model = line.split(":", 1)[1].strip()
            if line.startswith("flags"):
                flags = set(line.split(":", 1)[1].split())
                break
    keep = sorted(f for f in flags if f.startswith(("amx", "avx512_bf16", "avx512f", "avx2", "avx_vnni")))
    return {"model": model, "flags": keep, "amx_bf16": "amx_bf16" in flags}
