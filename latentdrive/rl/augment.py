"""Random-shift augmentation of sampled maps (DrQ; Kostrikov, Yarats and Fergus, ICLR 2021).

A Q-network that reads the VelocityMap from a few tens of thousands of transitions can fit
the exact cells where each vehicle stood rather than the gaps between them. Shifting each
sampled map by a few cells, the same way for all its channels and frames, keeps every
relation the map shows (the gaps, the lanes, the speeds) and changes only where in the grid
it lies, so the network must read the relations. The observation and the next observation
of a transition are shifted independently, as in DrQ.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

__all__ = ["random_shift"]


def random_shift(maps: torch.Tensor, pad: int, rng: np.random.Generator) -> torch.Tensor:
    """Each map of ``maps`` ``(B, C, T, H, W)`` moved by up to ``pad`` cells along H and W.

    The map is padded by ``pad`` cells on every side with copies of its edge cells, then an
    ``H × W`` window is cut at offsets drawn uniformly from ``[0, 2·pad]`` per map (one
    offset pair for all its channels and frames): the window moves by ``offset − pad``
    cells, so the map's contents move by ``pad − offset``.

    Args:
        maps: ``(B, C, T, H, W)`` stacked maps (any float dtype, any device).
        pad: the largest shift in cells (``pad = 0`` returns ``maps``).
        rng: source of the ``(B, 2)`` offsets (drawn only when ``pad > 0``).
    """
    if pad == 0:
        return maps
    b, c, t, h, w = maps.shape
    offsets = rng.integers(0, 2 * pad + 1, size=(b, 2))
    padded = F.pad(maps.reshape(b, c * t, h, w), (pad, pad, pad, pad), mode="replicate")
    # One slice per map: a per-element gather over the whole batch is several times slower.
    out = torch.stack([padded[i, :, y:y + h, x:x + w] for i, (y, x) in enumerate(offsets.tolist())])
    return out.reshape(b, c, t, h, w)
