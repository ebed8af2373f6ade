"""The inference wrapper (``reset()`` + ``select_action(obs)`` over a batch of environments) and checkpoint I/O.

A checkpoint directory holds ``config.json`` (the full policy config, obs/action dims, dataset info, training
config) and ``model.safetensors`` (weights, normalisation statistics and k-means centres).
"""

from __future__ import annotations

import json
import os
import shutil
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from cotpc.policies.base import BaseConfig, config_from_dict, config_to_dict, make_model
from cotpc.policies.transformer import TransformerPolicy

FORMAT = "cotpc-policy"


class CheckpointError(ValueError):
    """A run directory is missing, malformed, or its weights do not match its config."""


def _atomic_write(path: Path, write) -> None:
    tmp = path.with_name(path.name + ".tmp")
    write(tmp)
    os.replace(tmp, path)


def save_checkpoint(directory: str | os.PathLike, model: torch.nn.Module, meta: dict) -> Path:
    """Write ``config.json`` + ``model.safetensors`` (each atomically: temporary file renamed into place)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    info = {"format": FORMAT, "policy": config_to_dict(model.cfg), "obs_dim": model.obs_dim,
            "action_dim": model.action_dim, **meta}
    _atomic_write(directory / "model.safetensors", lambda p: save_file(state, str(p), metadata={"format": FORMAT}))
    _atomic_write(directory / "config.json", lambda p: p.write_text(json.dumps(info, indent=1, default=str)))
    return directory


def link_checkpoint(source: str | os.PathLike, directory: str | os.PathLike) -> Path:
    """Keep the checkpoint just written in ``source`` under ``directory`` too, as hard links where the file system
    allows (no second serialisation; ``save_checkpoint`` replaces files rather than rewriting them, so a link
    keeps its content when the source is next written), else as copies."""
    source, directory = Path(source), Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for name in ("model.safetensors", "config.json"):
        dst = directory / name
        dst.unlink(missing_ok=True)
        try:
            os.link(source / name, dst)
        except OSError:
            shutil.copy2(source / name, dst)
    return directory


def read_config(directory: str | os.PathLike) -> dict:
    directory = Path(directory)
    path = directory / "config.json"
    if not path.exists():
        raise CheckpointError(f"{directory}: no config.json; not a cotpc run directory")
    try:
        info = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise CheckpointError(f"{path}: not readable as JSON ({e}); a truncated or foreign file") from None
    if not isinstance(info, dict) or info.get("format") != FORMAT:
        found = info.get("format") if isinstance(info, dict) else type(info).__name__
        raise CheckpointError(f"{path}: not a cotpc policy config (format {found!r})")
    return info


def load_model(directory: str | os.PathLike, device: str = "cpu") -> tuple[torch.nn.Module, dict]:
    directory = Path(directory)
    info = read_config(directory)
    try:
        cfg = config_from_dict(info["policy"])
    except (ValueError, TypeError) as e:
        raise CheckpointError(f"{directory}/config.json: {e}") from None
    model = make_model(cfg, info["obs_dim"], info["action_dim"], info.get("max_timestep", 1))
    weights = directory / "model.safetensors"
    if not weights.exists():
        raise CheckpointError(f"{directory}: no model.safetensors")
    try:
        state = load_file(str(weights))
    except SafetensorError as e:  # a truncated copy or another format under the name
        raise CheckpointError(f"{weights}: not a readable safetensors file ({e}); a truncated or foreign file") from None
    load_state(model, state, f"{weights} (config: policy {cfg.name!r})")
    return model.to(device).eval(), info


def load_state(model: torch.nn.Module, state: dict, where: str) -> None:
    """``load_state_dict`` that names every mismatch (another policy, context, size or data dimensions)."""
    own = model.state_dict()
    missing = sorted(set(own) - set(state))
    unexpected = sorted(set(state) - set(own))
    shapes = [f"{k}: checkpoint {tuple(state[k].shape)} vs model {tuple(own[k].shape)}"
              for k in own if k in state and state[k].shape != own[k].shape]
    if missing or unexpected or shapes:
        lines = [f"{where}: the weights were trained with a different configuration or data dimensions"]
        if missing:
            lines.append(f"  missing: {', '.join(missing[:8])}{' ...' if len(missing) > 8 else ''}")
        if unexpected:
            lines.append(f"  unexpected: {', '.join(unexpected[:8])}{' ...' if len(unexpected) > 8 else ''}")
        lines += [f"  shape {s}" for s in shapes[:8]]
        raise CheckpointError("\n".join(lines))
    model.load_state_dict(state)


class Policy:
    """A trained policy acting in B environments at once; keeps each environment's last T states and actions.

    ``select_action(obs)`` takes (B, q) raw observations (one per environment) and returns (B, p) actions.
    ``reset()`` clears every environment's context; ``reset(envs)`` only those given as a boolean mask or
    indices (for vectorised environments that finish at different times).

    A model that plans action chunks from a state history (``predict_chunk``: Diffusion Policy, and Decision
    Diffuser, whose chunk is the inverse dynamics of its planned states) keeps a queue of actions per
    environment: an environment whose queue is empty plans (one sampler call for all environments that need
    it) from its last ``cfg.window`` states, the first one repeated before its episode's start (the start padding
    of both), and its next ``action_horizon`` calls pop the chunk (one call for Decision Diffuser, which plans at
    every step). ``reset(envs)`` empties those environments' queues and histories. A transformer with
    ``action_horizon`` H > 1 (trained with ``action_chunk`` >= H) also queues: an environment with an empty
    queue predicts a chunk from its window, and its next H calls execute it; every executed action enters its
    context as usual.

    At batch 1 a step is ~150 small ops, so their count matters more than their arithmetic: on a CPU the
    windows, step counters and (de)normalisation are NumPy (a small NumPy op costs a fraction of a torch op),
    the attention mask of a partly filled context is looked up (:meth:`GPT.inference_bias`) and the network
    runs its inference path (:meth:`TransformerPolicy.predict_window`), the values of the training forward at
    the last window index (tested in tests/test_inference_speedpath.py).
    """

    def __init__(self, model: torch.nn.Module, info: dict | None = None, device: str = "cpu", compile: bool = False):
        self.model = model.to(device).eval()
        self.info = info or {}
        self.device = torch.device(device)
        self.obs_dim, self.action_dim = model.obs_dim, model.action_dim
        self.T = self.cfg.window
        self._transformer = isinstance(model, TransformerPolicy)
        self._chunked = hasattr(model, "predict_chunk")  # action chunks with a queue per environment
        self._network = self._compile_network() if compile else None  # None: the eager predict_window
        n = model.norm
        self._obs_mean, self._obs_std, self._act_mean, self._act_std = n.obs_mean, n.obs_std, n.act_mean, n.act_std
        # NumPy views of the same buffers (copies on a GPU, for the queueing policies' NumPy bookkeeping)
        self._np_stats = tuple(x.cpu().numpy() for x in (n.obs_mean, n.obs_std, n.act_mean, n.act_std))
        self._window_steps = np.arange(self.T) - (self.T - 1)  # timestep of each window index, minus the last
        self._states = None  # (B, T, q) normalised, oldest first (NumPy on a CPU)
        self._actions = None  # (B, T, p) normalised; the last slot is the action just taken (NumPy on a CPU)
        self._t = None  # (B,) NumPy: timestep of the next observation
        self._n = None  # (B,) NumPy: number of earlier steps held in the context
        self._queue_chunks = False  # a transformer executing H > 1 actions per prediction (set per episode batch)

    @property
    def cfg(self) -> BaseConfig:
        """The model's config, read live: an inference setting replaced on the model (``cotpc eval
        --action-horizon``, ``--sampler-steps``) takes effect on the next episode."""
        return self.model.cfg

    @property
    def num_envs(self) -> int | None:
        return None if self._states is None else self._states.shape[0]

    def reset(self, envs=None) -> None:
        if envs is None or self._states is None:
            self._states = None
            return
        idx = np.asarray(envs.cpu() if isinstance(envs, torch.Tensor) else envs)
        if idx.dtype == bool and idx.shape[0] != self._states.shape[0]:
            raise ValueError(f"reset mask has {idx.shape[0]} entries for {self._states.shape[0]} environments")
        self._t[idx] = 0
        self._n[idx] = 0
        if self._chunked or self._queue_chunks:
            self._queued[idx] = 0

    def _allocate(self, B: int) -> None:
        # the inference settings are read live (cotpc eval --action-horizon): fixed here for this batch's episodes
        H = getattr(self.cfg, "action_horizon", 1)
        self._queue_chunks = self._transformer and H > 1
        if self._chunked or self._queue_chunks:
            self._queue = np.zeros((B, H, self.action_dim), dtype=np.float32)  # normalised actions to execute
            self._queued = np.zeros(B, dtype=np.int64)  # actions left in each queue (taken from the back)
        if self._chunked:  # NumPy bookkeeping on any device: the sampler's network calls dominate
            self._states = np.zeros((B, self.T, self.obs_dim), dtype=np.float32)
        elif self.device.type == "cpu" or self._queue_chunks:  # queueing: one network call per H steps
            self._states = np.zeros((B, self.T, self.obs_dim), dtype=np.float32)
            self._actions = np.zeros((B, self.T, self.action_dim), dtype=np.float32)
        else:
            self._states = torch.zeros(B, self.T, self.obs_dim, device=self.device)
            self._actions = torch.zeros(B, self.T, self.action_dim, device=self.device)
        self._t = np.zeros(B, dtype=np.int64)
        self._n = np.zeros(B, dtype=np.int64)

    def _compile_network(self):
        """``torch.compile`` of the transformer's inference call: one whole graph per batch size (``fullgraph``,
        static shapes; the padding of a partly filled context is always passed as ``n_prev``, so the start of an
        episode takes the same graph). On a CPU with inductor's C++ wrapper, which calls the kernels without
        Python in between: at batch 1 a step is ~150 small ops whose dispatch costs more than their arithmetic
        (docs/performance.md). The weights stay inputs of the graph, so weights loaded or changed later are used.
        Compiles lazily, on the first call of each batch size (~10-20 s on a CPU); the graphs are shared by every
        policy of the same structure in a process, and past torch's limit of 8 graphs per process
        (``torch._dynamo.config.recompile_limit``) further shapes run eager. Actions agree with the eager path
        to ~1e-7, not bit for bit."""
        if not self._transformer:
            raise ValueError(f"compile=True is for the transformer policies; {self.cfg.name!r} runs eager "
                             f"({'it plans chunks with a sampler' if self._chunked else 'a Markovian MLP'})")
        # a CPU: the C++ wrapper; a GPU: inductor's defaults (unmeasured)
        options = {"cpp_wrapper": True} if self.device.type == "cpu" else None
        return torch.compile(self.model.predict_window_chunk, fullgraph=True, dynamic=False, options=options)

    @torch.inference_mode()
    def select_action(self, obs) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float32)
        if obs.ndim == 1:
            raise ValueError(f"select_action takes a batch (B, {self.obs_dim}); got shape {tuple(obs.shape)}")
        if obs.ndim != 2 or obs.shape[1] != self.obs_dim:
            raise ValueError(
                f"observation has shape {tuple(obs.shape)}, but this policy was trained on {self.obs_dim}-dim "
                f"observations (data: {self.info.get('dataset', {}).get('path', '?')})"
            )
        if not np.isfinite(obs).all():  # a NaN would spread through the whole context window, silently
            row = int(np.argwhere(~np.isfinite(obs))[0, 0])
            raise ValueError(f"observation {row} of the batch holds NaN/inf: {obs[row].tolist()}")
        B = obs.shape[0]
        if self._states is None:
            self._allocate(B)
        elif B != self._states.shape[0]:
            raise ValueError(f"got {B} observations for {self._states.shape[0]} environments; call reset() first")
        if self._chunked:
            return self._step_chunked(obs)
        if self.device.type == "cpu" or self._queue_chunks:
            return self._step_cpu(obs)
        return self._step(torch.as_tensor(obs, device=self.device))

    def _step_chunked(self, obs: np.ndarray) -> np.ndarray:
        """One step of a chunking policy: every environment's state history moves on; those with an empty queue
        sample a new chunk (batched); each environment executes the next action of its queue."""
        obs_mean, obs_std, act_mean, act_std = self._np_stats
        s = (obs - obs_mean) / obs_std
        self._states[:, :-1] = self._states[:, 1:]
        self._states[:, -1] = s
        fresh = self._n == 0  # an episode's first step: the history before it repeats the first state
        self._states[fresh] = s[fresh, None]
        plan = np.flatnonzero(self._queued == 0)
        if len(plan):
            states = torch.from_numpy(self._states[plan]).to(self.device)
            self._queue[plan] = self.model.predict_chunk(states).float().cpu().numpy()
            self._queued[plan] = self._queue.shape[1]
        B = obs.shape[0]
        a = self._queue[np.arange(B), self._queue.shape[1] - self._queued]
        self._queued -= 1
        self._advance()
        return a * act_std + act_mean

    def _step_cpu(self, obs: np.ndarray) -> np.ndarray:
        """One step on a CPU: the window bookkeeping in NumPy (each small NumPy op costs a fraction of a torch
        op; the elementwise float32 maths is the same), the network in torch on views of the NumPy buffers."""
        obs_mean, obs_std, act_mean, act_std = self._np_stats
        s = (obs - obs_mean) / obs_std
        # shift the window one step left (oldest out, newest in); slots before an episode's start keep stale
        # values, which the padding mask hides from every real token
        self._states[:, :-1] = self._states[:, 1:]
        self._states[:, -1] = s
        self._actions[:, :-1] = self._actions[:, 1:]  # [:, :-1] are now this window's T-1 earlier actions
        if self._queue_chunks:
            a = self._next_queued()
        else:
            states, prev = torch.from_numpy(self._states), torch.from_numpy(self._actions[:, :-1])
            a = self._predict(states, prev)[:, 0].numpy()
            self._advance()
        self._actions[:, -1] = a
        return a * act_std + act_mean

    def _next_queued(self) -> np.ndarray:
        """(B, p) normalised actions for a transformer executing chunks: the environments whose queue is empty
        predict a chunk from their windows (one network call), and every environment takes its queue's next."""
        plan = np.flatnonzero(self._queued == 0)
        if len(plan):
            to = lambda x: torch.from_numpy(np.ascontiguousarray(x)).to(self.device)  # noqa: E731
            chunk = self._predict(to(self._states[plan]), to(self._actions[plan, :-1]), plan).float().cpu().numpy()
            H = self._queue.shape[1]
            self._queue[plan] = chunk[:, :H]
            self._queued[plan] = H
        a = self._queue[np.arange(len(self._queued)), self._queue.shape[1] - self._queued]
        self._queued -= 1
        self._advance()
        return a

    def _step(self, obs: torch.Tensor) -> np.ndarray:
        """One step on an accelerator: the same as :meth:`_step_cpu` with the buffers on the device."""
        s = (obs - self._obs_mean) / self._obs_std
        self._states = torch.cat([self._states[:, 1:], s[:, None]], dim=1)
        prev = self._actions[:, 1:]
        a = self._predict(self._states, prev)[:, 0]
        self._advance()
        self._actions = torch.cat([prev, a[:, None]], dim=1)
        return (a * self._act_std + self._act_mean).cpu().numpy()

    def _advance(self) -> None:
        """Every environment has taken one more step: the next observation's timestep and the history held."""
        self._t += 1
        self._n += 1

    def _predict(self, states: torch.Tensor, prev: torch.Tensor, envs: np.ndarray | None = None) -> torch.Tensor:
        """Normalised action chunks (B, k, p) (k = 1 but for a chunking transformer) for the windows ``states``
        (B, T, q) and earlier actions ``prev`` (B, T-1, p) of the environments ``envs`` (default: all)."""
        t_now, n = (self._t, self._n) if envs is None else (self._t[envs], self._n[envs])
        if self._transformer:
            t = torch.from_numpy(t_now[:, None] + self._window_steps).to(self.device)  # (B, T); clamped inside
            if self._network is not None:
                return self._compiled_call(states, prev, t, n)
            # None: every context is full, the constant mask applies
            partly_filled = self.T > 1 and n.min() < self.T - 1
            return self.model.predict_window_chunk(states, prev, t, self._n_prev(n) if partly_filled else None)
        return self.model.predict({"states": states})[:, None]  # the Markovian MLP reads the current state only

    def _n_prev(self, n: np.ndarray) -> torch.Tensor:
        """(B,) earlier steps each environment's window holds, capped at T - 1 (the padding mask's index)."""
        return torch.from_numpy(np.minimum(n, self.T - 1)).to(self.device)

    def _compiled_call(self, states: torch.Tensor, prev: torch.Tensor, t: torch.Tensor, n: np.ndarray) -> torch.Tensor:
        try:  # n_prev always given: one graph whether or not a context is partly filled
            return self._network(states, prev, t, self._n_prev(n))
        except torch._dynamo.exc.BackendCompilerFailed as e:
            raise RuntimeError(
                "select_action: compiling the policy failed (on a CPU torch.compile needs a C++ compiler, g++ or "
                f"$CXX); run without --compile / compile=True. Cause: {str(e).splitlines()[0][:300]}") from e


def load_policy(run_dir: str | os.PathLike, device: str = "cpu", compile: bool = False) -> Policy:
    """Load ``run_dir`` (``config.json`` + ``model.safetensors``) as a :class:`Policy` (``compile``: see
    :meth:`Policy._compile_network`)."""
    model, info = load_model(run_dir, device)
    return Policy(model, info, device, compile=compile)
