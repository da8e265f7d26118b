"""Generator networks: `build_model(cfg)` builds the one `cfg.architecture` names.

"genreg" (every shipped model): `genreg.GenRegNet`; "paper": `paper.PaperGenRegNet`, the paper's own
generator kept for ablations. Both run the stages encode -> interact -> generate and return a
`GenRegOutput`.
"""

from __future__ import annotations

from torch import nn

from genreg_core.config import ModelConfig
from genreg_core.model.genreg import GenRegNet, GenRegOutput
from genreg_core.model.paper import PaperGenRegNet

__all__ = ["GenRegNet", "GenRegOutput", "PaperGenRegNet", "build_model"]


def build_model(cfg: ModelConfig) -> nn.Module:
    """The generator of `cfg.architecture`, freshly initialised."""
    return PaperGenRegNet(cfg) if cfg.architecture == "paper" else GenRegNet(cfg)
