"""cotpc: Chain-of-Thought Predictive Control (CoTPC, ICML 2024).

Unsupervised subskill discovery from demonstrations and hierarchical imitation learning with a transformer
whose chain-of-thought tokens predict the next and last subskill states.
"""

__version__ = "0.1.0"


def load_policy(run_dir, device: str = "cpu", compile: bool = False):
    """Load a trained run directory (``config.json`` + ``model.safetensors``) as a policy with ``reset()`` and
    ``select_action(obs)`` over a batch of environments. ``compile=True``: ``torch.compile`` the transformer's
    network call (faster control at batch 1 after a compile of ~10-20 s per batch size; docs/performance.md)."""
    from cotpc.policies import load_policy as _load_policy  # lazily: `import cotpc` alone does not load torch

    return _load_policy(run_dir, device=device, compile=compile)
