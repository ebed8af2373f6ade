"""The inference speed path (``Policy.select_action`` -> ``predict_window`` -> ``GPT.infer``) gives the actions of
the reference computation: the original wrapper (rolled windows, a ``valid`` mask) feeding the *training* forward
pass at the last window index, for every preset, at batch 1 and 5, with contexts that are partly filled (after
``reset()`` and after ``reset(mask)`` of some environments)."""

import numpy as np
import pytest
import torch

from cotpc.policies import PRESETS, Policy, get_preset, make_model
from cotpc.policies.transformer import MaskedAttention, build_mask, infer_attention, mask_to_bias

Q, P = 6, 2
TINY = {"d_model": 32, "n_heads": 4, "n_layers": 2, "n_centres": 8, "hidden": 64}


def tiny_model(name: str, context: int = 4, seed: int = 0, **overrides):
    cfg = get_preset(name, context=context, **{**TINY, **overrides})
    torch.manual_seed(seed)
    model = make_model(cfg, Q, P, max_timestep=12)  # episodes below run past it: the clamp is exercised
    with torch.no_grad():  # trained-looking weights and statistics: every token and head carries signal
        for prm in model.parameters():
            prm.add_(0.1 * torch.randn_like(prm))
        model.norm.obs_mean.normal_()
        model.norm.obs_std.uniform_(0.5, 2.0)
        model.norm.act_mean.normal_()
        model.norm.act_std.uniform_(0.5, 2.0)
        if cfg.action_head == "bet":
            model.centres.normal_()
    return model.eval()


def reference_predict(model, batch):
    """Normalised actions from the training forward pass (every block, dense offset head) at the last index."""
    cfg = model.cfg
    if cfg.window == 1 and not hasattr(model, "gpt"):  # the Markovian MLP
        return model.net(batch["states"][:, -1])
    x, _ = model._features(batch, train=False)
    valid = batch.get("valid")
    if cfg.action_head == "mse":
        return model.action_decoder(model._select(x, cfg.centre_from, valid)[:, -1])
    if cfg.action_head == "gmm":
        return model.mixture_mode(model.mixture_head(model._select(x, cfg.centre_from, valid)[:, -1]))
    c = model.centre_head(model._select(x, cfg.centre_from, valid)[:, -1]).argmax(-1)
    offsets = model.offset_head(model._select(x, cfg.offset_from, valid)[:, -1]).view(-1, cfg.n_centres, P)
    return model.centres[c] + offsets[torch.arange(len(c)), c]


class ReferencePolicy:
    """The original inference wrapper: rolled windows and a ``valid`` mask built each step."""

    def __init__(self, model, B):
        self.model, self.T = model, model.cfg.window
        self.states, self.actions = torch.zeros(B, self.T, Q), torch.zeros(B, self.T, P)
        self.t, self.n = torch.zeros(B, dtype=torch.long), torch.zeros(B, dtype=torch.long)

    def reset(self, envs):
        self.t[envs] = 0
        self.n[envs] = 0

    @torch.no_grad()
    def select_action(self, obs):
        norm, T = self.model.norm, self.T
        self.states = torch.roll(self.states, -1, dims=1)
        self.actions = torch.roll(self.actions, -1, dims=1)
        self.states[:, -1] = (torch.as_tensor(obs) - norm.obs_mean) / norm.obs_std
        ar = torch.arange(T)
        batch = {"states": self.states, "actions": self.actions, "timesteps": self.t[:, None] - (T - 1) + ar}
        if T > 1 and bool((self.n < T - 1).any()):
            batch["valid"] = ar[None, :] >= (T - 1 - self.n)[:, None]
        a = reference_predict(self.model, batch)
        self.actions[:, -1] = a
        self.t += 1
        self.n += 1
        return (a * norm.act_std + norm.act_mean).numpy()


def run_both(model, B, steps=16, resets=((7, [0, 2]), (11, [1])), compile=False):
    """Act with the policy and the reference for ``steps`` steps, resetting some environments on the way;
    return the largest action difference."""
    pol, ref = Policy(model, compile=compile), ReferencePolicy(model, B)
    rng = np.random.default_rng(1)
    worst = 0.0
    for step in range(steps):
        for at, envs in resets:
            if step == at and B > 1:
                mask = np.zeros(B, dtype=bool)
                mask[envs] = True
                pol.reset(mask)
                ref.reset(torch.as_tensor(mask))
        obs = rng.normal(size=(B, Q)).astype(np.float32)
        a, want = pol.select_action(obs), ref.select_action(obs)
        assert a.shape == (B, P) and a.dtype == np.float32
        worst = max(worst, float(np.abs(a - want).max()))
    return worst


@pytest.mark.parametrize("B", [1, 5])
# dp, dd sample: tests/test_diffusion_policy.py, tests/test_decision_diffuser.py
@pytest.mark.parametrize("name", [n for n in PRESETS if n not in ("dp", "dd")])
def test_select_action_equals_the_training_forward(name, B):
    assert run_both(tiny_model(name), B) < 1e-5


@pytest.mark.parametrize("name", ["cotpc", "swapped", "decoupled", "dt"])
def test_select_action_equals_the_training_forward_at_context_one_and_with_more_layers(name):
    assert run_both(tiny_model(name, context=1), 3) < 1e-5
    # three layers with the CoT decoder on a middle block (the decoupled CoT transformer stops there)
    assert run_both(tiny_model(name, context=3, n_layers=3, cot_layer=1), 3) < 1e-5


def test_maniskill_shape_matches_at_batch_1():
    """The benchmarked setting (context 10, 16-dim heads, 128 centres) through a whole episode start."""
    cfg = get_preset("cotpc", context=10, n_centres=128)
    torch.manual_seed(0)
    model = make_model(cfg, Q, P, max_timestep=200).eval()
    with torch.no_grad():
        for prm in model.parameters():
            prm.add_(0.05 * torch.randn_like(prm))
    assert run_both(model, 1, steps=14) < 1e-5


@pytest.mark.parametrize("name", ["cotpc", "decoupled"])
def test_compiled_select_action_equals_the_training_forward_in_one_graph(name):
    """``compile=True`` (``cotpc eval --compile``): the reference's actions (to float tolerance, not bit for bit)
    from one graph per batch size: the first steps of an episode (a partly filled context) and resets of some
    environments never recompile (dynamo raises on a recompilation here)."""
    from torch._dynamo.utils import counters

    torch._dynamo.reset()
    counters.clear()
    model = tiny_model(name)
    with torch._dynamo.config.patch(error_on_recompile=True):
        assert run_both(model, 3, compile=True) < 1e-5
        with torch.no_grad():  # weights changed after compiling are used (they are inputs of the graph)
            for prm in model.parameters():
                prm.add_(0.1 * torch.randn_like(prm))
        assert run_both(model, 3, compile=True) < 1e-5
    assert counters["stats"]["unique_graphs"] == 1  # the compiled graph ran, whole (no graph break)


def test_compile_is_refused_for_policies_without_the_transformer_network():
    with pytest.raises(ValueError, match="transformer policies.*Markovian MLP"):
        Policy(tiny_model("bc"), compile=True)


def test_predict_on_a_batch_dict_with_any_padding_equals_the_training_forward():
    model = tiny_model("swapped")
    g = torch.Generator().manual_seed(0)
    B, T = 6, 4
    valid = torch.arange(T)[None, :] >= torch.tensor([0, 1, 2, 3, 0, 2])[:, None]
    batch = {"states": torch.randn(B, T, Q, generator=g), "actions": torch.randn(B, T, P, generator=g),
             "timesteps": torch.arange(T)[None].repeat(B, 1) + 3, "valid": valid}
    with torch.no_grad():
        torch.testing.assert_close(model.predict(batch), reference_predict(model, batch))


def test_padding_bias_table_equals_the_mask_built_from_valid():
    model = tiny_model("cotpc-causal", context=5)
    for gpt in (model.gpt, tiny_model("decoupled", context=5).cot_gpt, tiny_model("bet", context=5).gpt):
        T = gpt.layout.T
        n_prev = torch.tensor([0, 1, 2, 3, 4, 9])
        valid = torch.arange(T)[None, :] >= (T - 1 - n_prev.clamp(max=T - 1))[:, None]
        assert torch.equal(gpt.inference_bias(n_prev=n_prev), mask_to_bias(build_mask(gpt.layout, valid)))
        assert torch.equal(gpt.inference_bias(n_prev=torch.tensor([T - 1]))[0], gpt.base_bias[0])


@pytest.mark.parametrize("per_sample", [False, True])
def test_infer_attention_matches_masked_attention(per_sample):
    g = torch.Generator().manual_seed(0)
    B, H, L, d = 3, 4, 9, 8
    q, k, v = (torch.randn(B, H, L, d, generator=g) for _ in range(3))
    mask = torch.rand(B if per_sample else 1, 1, L, L, generator=g) > 0.4
    mask |= torch.eye(L, dtype=torch.bool)
    bias = mask_to_bias(mask)
    want = MaskedAttention.apply(q, k, v, bias)
    got = infer_attention(q.flatten(0, 1), k.flatten(0, 1), v.flatten(0, 1), bias, H).view(B, H, L, d)
    torch.testing.assert_close(got, want)
    rows = torch.tensor([2, 8])  # only some query rows, as the last block computes
    got = infer_attention(q[:, :, rows].flatten(0, 1), k.flatten(0, 1), v.flatten(0, 1), bias[..., rows, :], H)
    torch.testing.assert_close(got.view(B, H, 2, d), want[:, :, rows])


def test_select_action_takes_the_inference_path(monkeypatch):
    """The speed path never runs the training forward or its autograd attention (a regression back to them
    would still give the right actions, only slower)."""
    model = tiny_model("cotpc")
    pol = Policy(model)

    def fail(*args, **kwargs):
        raise AssertionError("the training path ran at inference")

    monkeypatch.setattr(MaskedAttention, "apply", fail)
    monkeypatch.setattr(type(model.gpt), "forward", fail)
    for _ in range(6):
        pol.select_action(np.zeros((2, Q), np.float32))


def test_reset_takes_masks_and_indices_as_numpy_lists_or_tensors():
    model = tiny_model("bet")
    pol, ref = Policy(model), ReferencePolicy(model, 4)
    rng = np.random.default_rng(0)
    for step, envs in enumerate([None, torch.tensor([True, False, False, True]), [2], np.array([0, 1]), None]):
        if envs is not None:
            pol.reset(envs)
            ref.reset(torch.as_tensor(np.asarray(envs)))
        obs = rng.normal(size=(4, Q)).astype(np.float32)
        np.testing.assert_allclose(pol.select_action(obs), ref.select_action(obs), atol=1e-5)
    with pytest.raises(ValueError, match="reset mask"):
        pol.reset(np.ones(3, dtype=bool))


def test_the_accelerator_step_equals_the_cpu_step():
    """``_step`` (torch buffers, used on CUDA) gives the actions of ``_step_cpu`` (NumPy buffers); run on a CPU."""
    model = tiny_model("swapped")
    cpu, acc = Policy(model), Policy(model)
    B = 3
    acc._allocate(B)
    acc._states, acc._actions = torch.from_numpy(acc._states), torch.from_numpy(acc._actions)
    rng = np.random.default_rng(2)
    for step in range(7):
        if step == 5:
            cpu.reset([1])
            acc.reset([1])
        obs = rng.normal(size=(B, Q)).astype(np.float32)
        with torch.inference_mode():
            got = acc._step(torch.as_tensor(obs))
        np.testing.assert_allclose(got, cpu.select_action(obs), atol=1e-6)


def test_a_failing_compile_says_what_to_do(monkeypatch, tmp_path):
    """No C++ compiler: a clear error naming the cause and the way out, not inductor's traceback."""
    import torch._inductor.config as inductor_config

    monkeypatch.setenv("TORCHINDUCTOR_CACHE_DIR", str(tmp_path))  # nothing compiled earlier is reused
    torch._dynamo.reset()
    model = tiny_model("bet", d_model=16, n_heads=2, n_layers=1)  # shapes no other test compiles
    with inductor_config.patch({"cpp.cxx": (None, "no-such-cxx"), "fx_graph_cache": False}):
        pol = Policy(model, compile=True)
        with pytest.raises(RuntimeError, match="needs a C\\+\\+ compiler.*run without --compile"):
            pol.select_action(np.zeros((1, Q), np.float32))
    torch._dynamo.reset()
