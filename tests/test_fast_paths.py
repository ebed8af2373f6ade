"""The fast paths of the training step are exact: CPU attention against SDPA, the training loss computed on the
rows the heads read and with the true centre's offset only against the full computation, and the precision
probe leaves the run as it would be without it."""

import json

import pytest
import torch
import torch.nn.functional as F

from cotpc.data import save_trajectories
from cotpc.data.dataset import synthetic_trajectories
from cotpc.policies import PRESETS, TransformerConfig, get_preset, make_model
from cotpc.policies.transformer import RowGatheredLinear
from cotpc.policies.transformer import Layout, MaskedAttention, build_mask, mask_to_bias
from cotpc.policies.transformer.backbone import LONG_WINDOW, attention
from cotpc.training import TrainConfig, train
from cotpc.training.precision import choose_precision, time_alternating

from test_policies import TINY, P, build


def _qkv(B, H, L, d, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(B, H, L, d, generator=g).to(dtype).requires_grad_() for _ in range(3)]


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_cpu_attention_matches_sdpa_with_padding_and_random_cot_masks(dtype):
    lay = Layout(context=6, n_cot=6, use_actions=True)
    B, H, d = 5, 4, 8
    g = torch.Generator().manual_seed(3)
    valid = torch.ones(B, 6, dtype=torch.bool)
    valid[0, :3] = False  # windows that start before the episode
    valid[1, :5] = False
    cot_hide = torch.randint(0, 6, (B,), generator=g)
    mask = build_mask(lay, valid, cot_hide)
    q, k, v = _qkv(B, H, lay.length, d, dtype)
    y = MaskedAttention.apply(q, k, v, mask_to_bias(mask))
    grad = torch.randn(y.shape, generator=g).to(dtype)
    dq, dk, dv = torch.autograd.grad(y, (q, k, v), grad)
    q2, k2, v2 = [t.detach().float().requires_grad_() for t in (q, k, v)]
    ref = F.scaled_dot_product_attention(q2, k2, v2, attn_mask=mask)
    rq, rk, rv = torch.autograd.grad(ref, (q2, k2, v2), grad.float())
    tol = dict(atol=1e-5, rtol=1e-5) if dtype == torch.float32 else dict(atol=3e-2, rtol=3e-2)
    assert y.dtype == dtype and torch.isfinite(y).all()
    torch.testing.assert_close(y.float(), ref, **tol)
    for a, b in ((dq, rq), (dk, rk), (dv, rv)):
        torch.testing.assert_close(a.float(), b, **tol)


@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_long_windows_take_the_flash_kernel_and_stay_exact(dtype, monkeypatch):
    """The official code's ManiSkill context of 60 (CoTPC: 179 tokens) runs SDPA in fp32 on a CPU, never
    MaskedAttention, with values and gradients of the masked attention, its output in the input's dtype."""
    T = 60
    lay = Layout(context=T, n_cot=T, use_actions=True)
    assert lay.length >= LONG_WINDOW
    B, H, d = 3, 2, 8
    g = torch.Generator().manual_seed(4)
    valid = torch.ones(B, T, dtype=torch.bool)
    valid[0, :40] = False
    mask = build_mask(lay, valid, torch.randint(0, T, (B,), generator=g))
    q, k, v = _qkv(B, H, lay.length, d, dtype)

    def fail(*args, **kwargs):
        raise AssertionError("MaskedAttention ran on a long window")

    monkeypatch.setattr(MaskedAttention, "apply", fail)
    with torch.autocast("cpu", dtype=torch.bfloat16, enabled=dtype == torch.bfloat16):
        y = attention(q, k, v, mask, mask_to_bias(mask), 0.0)
    grad = torch.randn(y.shape, generator=g).to(dtype)
    dq, dk, dv = torch.autograd.grad(y, (q, k, v), grad)
    q2, k2, v2 = [t.detach().float().requires_grad_() for t in (q, k, v)]
    scores = (q2 @ k2.transpose(-1, -2) * d ** -0.5).masked_fill(~mask, float("-inf"))
    ref = torch.softmax(scores, -1) @ v2  # the definition, not the kernel under test
    rq, rk, rv = torch.autograd.grad(ref, (q2, k2, v2), grad.float())
    tol = dict(atol=1e-5, rtol=1e-5) if dtype == torch.float32 else dict(atol=2e-2, rtol=2e-2)
    assert y.dtype == dtype and torch.isfinite(y).all()
    torch.testing.assert_close(y.float(), ref, **tol)
    for a, b in ((dq, rq), (dk, rk), (dv, rv)):
        assert a.dtype == dtype
        torch.testing.assert_close(a.float(), b, **tol)


def test_cpu_attention_of_selected_rows_matches_sdpa():
    lay = Layout(context=5, n_cot=5, use_actions=True)
    mask = build_mask(lay)
    q, k, v = _qkv(2, 2, lay.length, 4, torch.float32)
    rows = torch.tensor([0, 4, 5, 13])
    y = MaskedAttention.apply(q[:, :, rows], k, v, mask_to_bias(mask)[..., rows, :])
    ref = F.scaled_dot_product_attention(q, k, v, attn_mask=mask)[:, :, rows]
    torch.testing.assert_close(y, ref)


def test_row_gathered_linear_matches_the_dense_layer():
    g = torch.Generator().manual_seed(0)
    N, K, p, h = 50, 7, 3, 16
    x = torch.randn(N, h, generator=g, requires_grad=True)
    lin = torch.nn.Linear(h, K * p)
    rows = torch.randint(0, K, (N,), generator=g)
    out = RowGatheredLinear.apply(x, lin.weight, lin.bias, rows, p)
    ref = lin(x).view(N, K, p)[torch.arange(N), rows]
    torch.testing.assert_close(out, ref)
    grad = torch.randn(N, p, generator=g)
    got = torch.autograd.grad(out, (x, lin.weight, lin.bias), grad)
    want = torch.autograd.grad(ref, (x, lin.weight, lin.bias), grad)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b)


def _full_loss(model, batch):
    """Reference training loss: every token of every block, the dense offset head read at the true centre."""
    saved = model._rows, model.row_of
    model._rows, model.row_of = (None, None), torch.arange(model.gpt.layout.length)

    def dense(feats, centre):
        out = model.offset_head(feats).view(*centre.shape, model.cfg.n_centres, P)
        return torch.gather(out, -2, centre[..., None, None].expand(*centre.shape, 1, P))[..., 0, :]

    model._true_centre_offsets = dense
    try:
        return model.loss(batch)
    finally:
        model._rows, model.row_of = saved
        del model._true_centre_offsets


@pytest.mark.parametrize("name", [n for n, c in PRESETS.items() if isinstance(c, TransformerConfig)])
def test_training_loss_on_the_rows_read_equals_the_full_computation(name, trajs):
    model, ds = build(name, trajs)
    with torch.no_grad():
        for prm in model.parameters():
            prm.add_(0.05 * torch.randn_like(prm))
    model.train()
    batch = ds.sample(16, torch.Generator().manual_seed(1))
    batch["valid"][0, :2] = False  # some left padding
    loss, metrics = model.loss(batch)
    grads = torch.autograd.grad(loss, list(model.parameters()), allow_unused=True)
    ref, ref_metrics = _full_loss(model, batch)
    ref_grads = torch.autograd.grad(ref, list(model.parameters()), allow_unused=True)
    for k in ref_metrics:
        torch.testing.assert_close(metrics[k], ref_metrics[k], msg=k)
    for (n, _), a, b in zip(model.named_parameters(), grads, ref_grads):
        if b is None:
            assert a is None or not a.any(), n
        else:
            torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-4, msg=n)


@pytest.fixture(scope="module")
def trajs():
    from test_policies import Q

    return synthetic_trajectories(n_episodes=8, obs_dim=Q, action_dim=P, length=20, seed=0)


def test_time_alternating_alternates_and_counts():
    order = []
    times = time_alternating({"a": lambda: order.append("a"), "b": lambda: order.append("b")}, rounds=2, reps=2)
    assert order == ["a", "b"] + ["a", "a", "b", "b"] * 2
    assert {k: len(v) for k, v in times.items()} == {"a": 4, "b": 4}


def test_choose_precision_keeps_the_faster_step_and_says_why():
    import time

    from cotpc.training.precision import native_bf16

    def make(slow_precision_is_bf16):
        def make_step(bf16, batch):
            slow = bf16 == slow_precision_is_bf16
            return lambda: time.sleep((0.02 if slow else 0.002) * (batch / 8))
        return make_step

    c = choose_precision(make(True), batch_size=16, device="cpu", native=True)
    assert not c.bf16 and c.fp32_ms < c.bf16_ms and c.batch_size == 16 and "not faster" in c.how
    c = choose_precision(make(False), batch_size=16, device="cpu", native=True)
    assert c.bf16 and c.bf16_ms < c.fp32_ms and c.batch_size == 16 and "faster" in c.how
    assert "fp32" in c.summary() and "bf16" in c.summary()

    def never(bf16, batch):
        raise AssertionError("no race without bf16 instructions")

    c = choose_precision(never, batch_size=16, device="cpu", native=False)
    assert not c.bf16 and c.fp32_ms is None and "no bf16 instructions" in c.how
    assert native_bf16({"avx2", "amx_bf16"}) and native_bf16({"avx512_bf16"}) and not native_bf16({"avx2", "fma"})


def test_precision_probe_is_stored_and_leaves_the_run_unchanged(tmp_path):
    """A run whose precision the probe chose equals the run told that precision: the probe trains copies."""
    data = tmp_path / "d.h5"
    save_trajectories(data, synthetic_trajectories(n_episodes=8, obs_dim=6, action_dim=2, length=20, seed=0))
    kw = dict(context=4, d_model=32, n_heads=4, n_layers=2, n_centres=8, batch_size=16, progress=False,
              iters=6, dropout=0.1, val_every=3)
    probed = train(TrainConfig(data=data, out=tmp_path / "probed", **kw))
    info = json.loads((probed / "config.json").read_text())
    choice = info["precision"]
    assert info["train"]["bf16"] == choice["bf16"]
    from cotpc.training.precision import native_bf16

    if native_bf16():  # raced: both timings stored (else fp32 without a race, and it says why)
        assert choice["fp32_ms"] > 0 and choice["bf16_ms"] > 0
    else:
        assert not choice["bf16"] and "no bf16 instructions" in choice["how"]
    told = train(TrainConfig(data=data, out=tmp_path / "told", bf16=choice["bf16"], **kw))
    from safetensors.torch import load_file

    a, b = load_file(str(probed / "model.safetensors")), load_file(str(told / "model.safetensors"))
    for k in a:
        assert torch.equal(a[k], b[k]), k
    timing = json.loads((probed / "loop_timing.json").read_text())
    assert len(timing) == 1 and timing[0]["to_step"] == 6 and 0 <= timing[0]["overhead_share"] < 1
    assert set(timing[0]["parts_s"]) == {"sample", "step", "log", "validate", "checkpoint"}


@pytest.mark.parametrize("chunk", [1, 2])
def test_dense_offset_path_under_bf16_matches_the_gathered_one(trajs, chunk):
    """Under bf16 autocast with K <= h the offset head runs dense (cheaper there); it must give the true centre's
    offsets and gradients as the row-gathered path does, to bf16 accuracy (one centre per chunk step)."""
    import cotpc.policies.transformer.model as model_module

    model, ds = build("cotpc", trajs)
    if chunk > 1:
        torch.manual_seed(0)
        model = make_model(get_preset("cotpc", **TINY, action_chunk=chunk), model.obs_dim, model.action_dim, 25)
    hidden = torch.randn(4, 6, model.cfg.hidden)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert model_module._dense_offsets_pay(hidden, model.cfg.n_centres) == (model.cfg.n_centres <= model.cfg.hidden)
    assert not model_module._dense_offsets_pay(hidden, model.cfg.n_centres)  # fp32 on a CPU: gathered
    feats = torch.randn(4, 6, model.cfg.d_model, requires_grad=True)
    centre = torch.randint(0, model.cfg.n_centres, (4, 6, chunk))
    results = []
    for dense in (True, False):
        saved = model_module._dense_offsets_pay
        model_module._dense_offsets_pay = lambda x, k: dense
        try:
            with torch.autocast("cpu", dtype=torch.bfloat16):
                off = model._true_centre_offsets(feats, centre).float()
            results.append((off, torch.autograd.grad(off.square().sum(), feats)[0]))
        finally:
            model_module._dense_offsets_pay = saved
    torch.testing.assert_close(results[0][0], results[1][0], atol=2e-2, rtol=2e-2)
    torch.testing.assert_close(results[0][1], results[1][1], atol=5e-2, rtol=5e-2)
