"""The transformer family, one folder: DT, BeT, CoTPC and every ablation of the paper as settings of one model.

- ``config.py``: :class:`TransformerConfig` and the family's named presets (``dt``, ``bet``, ``cotpc``, ...);
- ``backbone.py``: the GPT backbone (token layout, the hybrid attention mask, attention fast on a CPU);
- ``model.py``: :class:`TransformerPolicy` (embeddings, heads, losses, inference), registered with its presets.
"""

from cotpc.policies.transformer.config import TRANSFORMER_PRESETS, TransformerConfig
from cotpc.policies.transformer.backbone import (GPT, Layout, MaskedAttention, build_mask, infer_attention,  # isort: skip
                                                 mask_to_bias)
from cotpc.policies.transformer.model import RowGatheredLinear, TransformerPolicy  # registers the family  # isort: skip

__all__ = ["GPT", "TRANSFORMER_PRESETS", "Layout", "MaskedAttention", "RowGatheredLinear", "TransformerConfig",
           "TransformerPolicy", "build_mask", "infer_attention", "mask_to_bias"]
