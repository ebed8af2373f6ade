"""The attention mask is built from the token layout: causal state/action tokens, all-to-all CoT tokens, the
random CoT mask hides exactly the drawn suffix, and left-padding never leaks into real tokens."""

import pytest
import torch

from cotpc.policies import TransformerConfig, get_preset
from cotpc.policies.transformer import GPT, Layout, build_mask

T, Q, P = 5, 3, 2


def small_gpt(name: str = "cotpc", **kw) -> GPT:
    cfg = get_preset(name, **{"context": T, "d_model": 32, "n_heads": 4, "n_layers": 2, **kw})
    torch.manual_seed(0)
    gpt = GPT(cfg, Q, P, max_timestep=50, n_cot=cfg.n_cot_tokens).eval()
    for prm in gpt.parameters():  # non-zero everywhere so every connection carries signal
        torch.nn.init.normal_(prm, std=0.3)
    return gpt


def inputs(B: int = 3):
    g = torch.Generator().manual_seed(1)
    s = torch.randn(B, T, Q, generator=g)
    a = torch.randn(B, T - 1, P, generator=g)
    t = torch.arange(T)[None].repeat(B, 1) + 7
    return s, a, t


def changed(x0: torch.Tensor, x1: torch.Tensor) -> torch.Tensor:
    """(L,) bool: which token outputs differ (any sample, any feature)."""
    return (x0 - x1).abs().amax(dim=(0, 2)) > 0


def perturb_each(gpt, check, cot_hide_for=None, first: int = 0):
    """Perturb every state and action token in turn; ``check(diff, pos)`` on which outputs changed."""
    lay = gpt.layout
    s, a, t = inputs()
    for i in range(first, T):
        hide = None if cot_hide_for is None else torch.full((s.shape[0],), cot_hide_for(i))
        with torch.no_grad():
            x0, _ = gpt(s, a, t, cot_hide=hide)
        for kind in ("state", "action"):
            if kind == "action" and i == T - 1:
                continue
            s1, a1 = s.clone(), a.clone()
            (s1 if kind == "state" else a1)[:, i] += 1.0
            with torch.no_grad():
                x1, _ = gpt(s1, a1, t, cot_hide=hide)
            pos = int((lay.state_pos if kind == "state" else lay.action_pos)[i])
            check(changed(x0, x1), pos, f"{kind} {i}")


def earlier_sa(lay, pos):
    idx = torch.arange(lay.length)
    return (idx >= lay.C) & (idx < pos)


@pytest.mark.parametrize("name", ["dt", "bet"])
def test_future_never_changes_earlier_tokens(name):
    gpt = small_gpt(name)

    def check(diff, pos, what):
        assert not diff[earlier_sa(gpt.layout, pos)].any(), f"{what} leaked into earlier tokens"
        assert diff[pos:].all(), f"{what} does not reach the later tokens"

    perturb_each(gpt, check)


@pytest.mark.parametrize("name", ["cotpc", "vanilla", "swapped"])
def test_cot_models_future_reaches_earlier_tokens_only_through_cot(name):
    # One block: state/action tokens are causal, CoT tokens see the whole window.
    gpt1 = small_gpt(name, n_layers=1)

    def check1(diff, pos, what):
        assert not diff[earlier_sa(gpt1.layout, pos)].any(), f"{what} leaked into earlier tokens"
        assert diff[pos:].all() and diff[: gpt1.layout.C].all(), f"{what} not seen by later or CoT tokens"

    perturb_each(gpt1, check1)

    # Several blocks: a future token can reach an earlier state/action token only by way of a CoT token that
    # sees it (the paper's hybrid mask). Hiding timesteps >= i from the CoT tokens (random CoT mask l = T - i)
    # makes the whole network causal again for a change at timestep i.
    gpt = small_gpt(name)

    def check(diff, pos, what):
        assert not diff[earlier_sa(gpt.layout, pos)].any(), f"{what} leaked into earlier tokens"
        assert not diff[: gpt.layout.C].any(), f"{what} reached the CoT tokens through the random mask"
        assert diff[pos:].all()

    # (window index 0 can never be hidden, l <= T-1, so start at 1)
    perturb_each(gpt, check, cot_hide_for=lambda i: T - i, first=1)


def test_mask_layout():
    lay = Layout(context=3, n_cot=3, use_actions=True)
    m = build_mask(lay).int()
    # rows/cols: c0 c1 c2 s0 a0 s1 a1 s2
    expected = torch.tensor([
        [1, 1, 1, 1, 1, 1, 1, 1],
        [1, 1, 1, 1, 1, 1, 1, 1],
        [1, 1, 1, 1, 1, 1, 1, 1],
        [1, 1, 1, 1, 0, 0, 0, 0],
        [1, 1, 1, 1, 1, 0, 0, 0],
        [1, 1, 1, 1, 1, 1, 0, 0],
        [1, 1, 1, 1, 1, 1, 1, 0],
        [1, 1, 1, 1, 1, 1, 1, 1],
    ])
    assert torch.equal(m, expected)


@pytest.mark.parametrize("hide", range(T))
def test_random_cot_mask_hides_exactly_the_suffix(hide):
    lay = Layout(context=T, n_cot=T, use_actions=True)
    m = build_mask(lay, cot_hide=torch.tensor([hide]))[0, 0]
    visible_steps = lay.step <= T - 1 - hide  # window index i <= T-1-l <=> timestep t' <= t-l
    for r in range(lay.C):
        assert torch.equal(m[r, lay.C:], visible_steps[lay.C:])
        assert m[r, : lay.C].all()
    assert torch.equal(m[lay.C:], build_mask(lay)[lay.C:])  # state/action rows unchanged

    # and in the network: the hidden suffix does not reach the CoT tokens, the last visible step does
    gpt = small_gpt()
    s, a, t = inputs(1)
    l = torch.tensor([hide])
    with torch.no_grad():
        x0, _ = gpt(s, a, t, cot_hide=l)
        for i in range(T):
            s1 = s.clone()
            s1[:, i] += 1.0
            x1, _ = gpt(s1, a, t, cot_hide=l)
            assert changed(x0, x1)[: lay.C].all() == (i <= T - 1 - hide)


def test_padding_is_invisible_and_finite():
    gpt = small_gpt()
    s, a, t = inputs(2)
    valid = torch.tensor([[False, False, True, True, True], [True] * T])
    with torch.no_grad():
        x0, _ = gpt(s, a, t, valid=valid, cot_hide=torch.tensor([4, 0]))
        s1, a1 = s.clone(), a.clone()
        s1[0, :2] = 1e3
        a1[0, :2] = -1e3
        x1, _ = gpt(s1, a1, t, valid=valid, cot_hide=torch.tensor([4, 0]))
    assert torch.isfinite(x0).all() and torch.isfinite(x1).all()
    lay = gpt.layout
    real = (lay.step < 0) | (lay.step >= 2)
    assert torch.equal(x0[0, real], x1[0, real])


def _per_position_predictions(model, batch):
    """(B, T, n) everything the action heads output for each window index in training (random mask drawn)."""
    x, _ = model._features(batch, train=True)
    cfg, valid = model.cfg, batch["valid"]
    if cfg.action_head == "mse":
        return model.action_decoder(model._select(x, cfg.centre_from, valid))
    if cfg.action_head == "gmm":
        return model.mixture_head(model._select(x, cfg.centre_from, valid))
    return torch.cat([model.centre_head(model._select(x, cfg.centre_from, valid)),
                      model.offset_head(model._select(x, cfg.offset_from, valid))], dim=-1)


def _leaks(name: str, **settings) -> list[tuple[int, int, str]]:
    """(i, j, what) for every change of a(j) or s(j+1), j >= i, that changes a training prediction at index i."""
    from cotpc.policies import make_model

    cfg = get_preset(name, context=T, d_model=32, n_heads=4, n_layers=3, n_centres=4, **settings)
    torch.manual_seed(0)
    model = make_model(cfg, Q, P, max_timestep=50).train()
    with torch.no_grad():
        for prm in model.parameters():  # non-zero everywhere so every connection carries signal
            prm.normal_(std=0.3)
    g = torch.Generator().manual_seed(2)
    B = 2
    batch = {"states": torch.randn(B, T, Q, generator=g), "actions": torch.randn(B, T, P, generator=g),
             "timesteps": torch.arange(T)[None].repeat(B, 1), "valid": torch.ones(B, T, dtype=torch.bool),
             "cot": torch.zeros(B, T, 2 * Q), "cot_hide": torch.zeros(B, dtype=torch.long)}  # l = 0: mask hides nothing
    with torch.no_grad():
        base = _per_position_predictions(model, batch)
        found = []
        for j in range(T):
            for key, idx, what in (("actions", j, "a"), ("states", j + 1, "s")):
                if idx >= T:
                    continue
                other = {**batch, key: batch[key].clone()}
                other[key][:, idx] += 1.0
                moved = (_per_position_predictions(model, other) - base).abs().amax(dim=(0, 2)) > 1e-6
                found += [(i, j, f"{what}({idx})") for i in range(j + 1) if moved[i]]
    return found


@pytest.mark.parametrize("name", [n for n, c in __import__("cotpc.policies", fromlist=["PRESETS"]).PRESETS.items()
                                  if c.leak_free and c.window > 1 and isinstance(c, TransformerConfig)])
def test_leak_free_presets_never_see_their_targets(name):
    """For every preset that claims it: a(j) or s(j+1), j >= i, never changes the prediction at index i."""
    assert _leaks(name) == []


@pytest.mark.parametrize("name", ["bet", "cotpc-causal", "dt"])
def test_chunked_leak_free_presets_never_see_their_targets(name):
    """With action chunks (a(i) .. a(i+2) predicted at index i) the targets lie further ahead: still unseen."""
    assert _leaks(name, action_chunk=3) == []


def test_leak_free_design_stays_leak_free_with_the_offset_head_on_the_state_token():
    """`--offset-from state` (the offset head on s(i) instead of cot_i) keeps cotpc-causal leak-free."""
    assert get_preset("cotpc-causal", offset_from="state").offset_from == "state"
    assert _leaks("cotpc-causal", offset_from="state") == []


def test_the_papers_hybrid_mask_leaks_targets_in_training():
    """The check above has teeth: with the paper's mask, CoT tokens carry a(i) into the predictions at i."""
    leaks = _leaks("cotpc")
    assert any(i == j for i, j, _ in leaks) and any(what.startswith("s") for _, _, what in leaks)
