"""The transformer family's configuration, and its named presets: DT, BeT, CoTPC and the paper's ablations.

The baselines (DT, BeT) and the ablations of paper Table 4 are *settings* of one transformer
(:mod:`cotpc.policies.transformer.backbone`, :mod:`cotpc.policies.transformer.model`), not separate models; only ``decoupled`` (which
adds a second transformer for the CoT) differs in structure. ``bc`` is its own family (:mod:`cotpc.policies.mlp`),
and so are ``dp``, Diffusion Policy (:mod:`cotpc.policies.diffusion`), and ``dd``, Decision Diffuser
(:mod:`cotpc.policies.decision_diffuser`); each registers its presets with its family
(:func:`cotpc.policies.base.register_family`), and :data:`cotpc.policies.PRESETS` holds them all.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

from cotpc.policies.base import BaseConfig

Source = Literal["state", "cot", "action"]
CotTarget = Literal["next", "last", "random"]


@dataclass(frozen=True)
class TransformerConfig(BaseConfig):
    """Architecture, loss and recommended optimisation settings of a transformer policy (DT, BeT, CoTPC)."""

    name: str = "cotpc"
    """Preset name this configuration came from (informational)."""

    # --- transformer backbone ---
    context: int = 10
    """Context size T: timesteps of state (and action) history in a window (default: the task's, cotpc.envs.spec.task_defaults)."""
    d_model: int = 128
    """Embedding size."""
    n_layers: int = 4
    """Number of transformer blocks."""
    n_heads: int = 8
    """Attention heads per block."""
    dropout: float = 0.0
    """Dropout on embeddings, attention and residuals (the official CoTPC code trains with 0)."""
    use_actions: bool = True
    """Interleave past action tokens with state tokens (DT style, used by BeT and CoTPC in the paper)."""
    episode_timestep: bool = True
    """Add a learned embedding of the episode timestep to every token (DT style, as the official CoTPC code);
    False: only the index in the window, so the policy reads the task's phase from the states alone."""
    n_cot: int = 0
    """CoT prompt tokens: 0 = none (DT/BeT), -1 = one per timestep (T, CoTPC), or an explicit count."""
    random_cot_mask: bool = True
    """In training, hide a random suffix of the window from the CoT tokens (paper Sec. 4.2.3)."""
    cot_attention: Literal["hybrid", "causal"] = "hybrid"
    """``hybrid``: the paper's CoT tokens, all-to-all (in training they see the targets of earlier window
    positions: docs/policies.md); ``causal``: CoT token i sits at window index i and sees only what is known
    there, like every other token, so no prediction in training sees its target (leak-free)."""

    # --- heads and losses ---
    action_head: Literal["mse", "bet", "gmm"] = "bet"
    """``mse``: continuous MLP decoder (DT, BC); ``bet``: k-means centre classifier + per-centre offsets;
    ``gmm``: a mixture of diagonal Gaussians trained by likelihood, acting with the mean of its most likely
    component (continuous like ``mse``, multi-modal like ``bet``; robomimic's GMM policy head)."""
    centre_from: Source = "state"
    """Token features the centre classifier (or the MSE decoder) reads for timestep i."""
    offset_from: Source = "state"
    """Token features the offset regressor reads for timestep i (``cot``: the i-th CoT token)."""
    n_centres: int = 128
    """k-means clusters K of the normalised actions (default: the task's, cotpc.envs.spec.task_defaults)."""
    action_rule: Literal["mode", "mean", "sample"] = "mode"
    """How a multi-modal head acts (an inference setting; training is the same): ``mode``, the arg-max centre plus
    its offset (``bet``, the paper's) or the most likely Gaussian's mean (``gmm``); ``mean``, the expected action
    under the head's distribution (``bet``: sum over centres of p_k (centre_k + offset_k); ``gmm``: the mixture
    mean); ``sample``, a centre (mode) drawn from the classifier's probabilities plus its offset (its mean), as
    the original BeT acts, from a generator seeded 0 at load. The ``mse`` head has one action.
    ``cotpc eval --action-rule``."""
    n_modes: int = 5
    """Gaussian components of the ``gmm`` head (robomimic's default)."""
    offset_weight: float = 100.0
    """Weight of the offset MSE relative to the centre cross-entropy (paper: 100)."""
    cot_targets: tuple[CotTarget, ...] = ()  # type: ignore[assignment]  (a field here, a property in BaseConfig)
    """What the CoT decoder predicts per CoT token: ``next``/``last`` subskill state, or a ``random`` future state."""
    cot_weight: float = 0.1
    """lambda, the weight of the CoT MSE (paper: 0.1)."""
    cot_layer: int = -1
    """Block whose CoT-token features feed the CoT decoder (-1 = last; a per-task choice in the paper)."""
    decoupled: bool = False
    """A second transformer predicts the CoT, which is fed (with the state) to a BeT-style action transformer."""
    hidden: int = 256
    """Hidden width of the encoders and decoders."""
    action_chunk: int = 1
    """Actions each window index predicts: a(i) .. a(i+k-1), Diffusion Policy's action chunks on the transformer
    (1: one action, the paper's). Not in the paper: on ManiSkill Stack Cube, executing chunks is what lets
    Diffusion Policy place the cube (docs/results/maniskill.md)."""
    action_horizon: int = 1
    """Actions of a predicted chunk executed before predicting again, a(t) .. a(t+action_horizon-1), in
    [1, action_chunk] (an inference setting: ``cotpc eval --action-horizon``). Executed actions enter the context
    as usual."""

    @property
    def n_cot_tokens(self) -> int:
        return self.context if self.n_cot == -1 else self.n_cot

    @property
    def leak_free(self) -> bool:
        """True if no training prediction of window index i can see a(>=i) or s(>i) (tested)."""
        return self.n_cot_tokens == 0 or self.cot_attention == "causal"

    @property
    def window(self) -> int:
        """Timesteps per training window."""
        return self.context

    @property
    def future_actions(self) -> int:
        """A window carries a(t+1) .. a(t+k-1): the chunk of its last index."""
        return self.action_chunk - 1

    @property
    def n_kmeans_centres(self) -> int:
        return self.n_centres if self.action_head == "bet" else 0

    def validate(self) -> None:
        if self.d_model % self.n_heads:
            raise ValueError(f"d_model={self.d_model} must be divisible by n_heads={self.n_heads}")
        if self.action_head == "gmm" and self.n_modes < 1:
            raise ValueError(f"the gmm head needs n_modes >= 1, got {self.n_modes}")
        if self.context < 1:
            raise ValueError("context must be >= 1")
        if self.action_chunk < 1:
            raise ValueError(f"action_chunk must be >= 1, got {self.action_chunk}")
        if not 1 <= self.action_horizon <= self.action_chunk:
            raise ValueError(f"action_horizon={self.action_horizon} must be in [1, action_chunk={self.action_chunk}] "
                             f"(the actions of one predicted chunk)")
        if self.action_head == "mse" and self.action_rule != "mode":  # it would change only the file's name
            raise ValueError(f"the mse head predicts one action; action_rule {self.action_rule!r} is for the "
                             f"bet and gmm heads")
        n_cot = self.n_cot_tokens
        for src in (self.centre_from, self.offset_from):
            if src == "cot" and n_cot != self.context:
                raise ValueError(f"reading a head from CoT tokens needs one CoT token per timestep (n_cot=-1), got {n_cot}")
            if src == "action" and not self.use_actions:
                raise ValueError("a head reads action tokens but use_actions is False")
        if self.cot_targets and n_cot == 0:
            raise ValueError("cot_targets need CoT tokens (n_cot != 0)")
        if n_cot not in (0, 1, self.context):
            raise ValueError(f"n_cot must be 0, 1 or the context size, got {n_cot}")
        if not -self.n_layers <= self.cot_layer < self.n_layers:
            raise ValueError(f"cot_layer={self.cot_layer} out of range for {self.n_layers} layers")
        if self.cot_attention == "causal" and self.random_cot_mask and n_cot:
            raise ValueError("causal CoT attention already hides the future; it takes no random CoT mask")
        if self.decoupled and self.cot_targets != ("next", "last"):
            raise ValueError("decoupled predicts the next and last subskill states")


_COTPC = TransformerConfig(
    name="cotpc", n_cot=-1, action_head="bet", centre_from="state", offset_from="cot", cot_targets=("next", "last")
)

# The transformer family's presets (registered with the family in cotpc.policies.transformer.model).
TRANSFORMER_PRESETS: dict[str, TransformerConfig] = {
    # Baselines (paper appendix "Implementation Details"); bc, dp and dd are families of their own.
    "dt": TransformerConfig(name="dt", action_head="mse"),
    "bet": TransformerConfig(name="bet", action_head="bet"),
    # The method.
    "cotpc": _COTPC,
    # The method without the hybrid mask's target leak: CoT token i sees only what is known at window index i.
    "cotpc-causal": dataclasses.replace(_COTPC, name="cotpc-causal", cot_attention="causal", random_cot_mask=False),
    # CoTPC with the official code's action decoder (an MLP on the state token, MSE loss) instead of the paper's
    # k-means centre + offset heads: the head DT has, with the CoT prompt and loss (docs/results/maze.md).
    "cotpc-mse": dataclasses.replace(_COTPC, name="cotpc-mse", action_head="mse", offset_from="state"),
    # The same decoder on the leak-free design: one regressed action per step, no arg-max among k-means centres
    # (on Stack Cube its gripper chatters at the grasp as the k-means head's does: maniskill.md, "Four times
    # the demos").
    "cotpc-causal-mse": dataclasses.replace(_COTPC, name="cotpc-causal-mse", cot_attention="causal",
                                            random_cot_mask=False, action_head="mse", offset_from="state"),
    # CoTPC with a continuous multi-modal head: the mixture keeps the modes the MSE head averages (a maze action
    # component is +-[1.5, 4]: the MSE head's mean of the two signs lands near 0) without k-means' quantisation.
    "cotpc-gmm": dataclasses.replace(_COTPC, name="cotpc-gmm", action_head="gmm", offset_from="state"),
    # Its control: DT with the same head, so a gain of cotpc-gmm over BeT can be split between head and CoT.
    "dt-gmm": TransformerConfig(name="dt-gmm", action_head="gmm"),
    # Ablations (paper Table 4), all configurations of the CoTPC model.
    "only-last": dataclasses.replace(_COTPC, name="only-last", cot_targets=("last",)),
    "only-next": dataclasses.replace(_COTPC, name="only-next", cot_targets=("next",)),
    "random": dataclasses.replace(_COTPC, name="random", cot_targets=("random",)),
    # The same control for the MSE-headed cotpc-mse: is what the CoT adds to DT's head the subskill states, or
    # any future states of the demo?
    "random-mse": dataclasses.replace(_COTPC, name="random-mse", action_head="mse", offset_from="state",
                                      cot_targets=("random",)),
    "vanilla": dataclasses.replace(_COTPC, name="vanilla", n_cot=1, offset_from="state"),
    "o-shared": dataclasses.replace(_COTPC, name="o-shared", centre_from="cot", offset_from="cot"),
    "swapped": dataclasses.replace(_COTPC, name="swapped", centre_from="cot", offset_from="action"),
    "bet-prompt": dataclasses.replace(_COTPC, name="bet-prompt", cot_targets=(), cot_weight=0.0),
    "no-rand-mask": dataclasses.replace(_COTPC, name="no-rand-mask", random_cot_mask=False),
    "decoupled": dataclasses.replace(_COTPC, name="decoupled", decoupled=True, offset_from="state"),
}
