"""An ego-attention reader of the VelocityMap (``vfan.reader: attention``; raw mode only).

The paper's VFAN ends its convolutions on a 1 × 4 grid and gives each of those positions
its own weights in the fully connected layer: what it learns of a car at one place does not
carry to a car at another. A Q-network that reads exact states generalizes across vehicles
when it reads them as a set (ego-attention over the neighbours; Leurent and Mercat, "Social
attention for autonomous decision-making in dense traffic", 2019), and not with an MLP that
gives each neighbour's rank its own weights (``scripts/state_dqn.py``; docs/readers.md). This
reader applies the same idea to the map's cells:

- a convolutional stem over the frames stacked as channels, ``(C·T, H, W)``, down to a grid
  of ``(H/4) × (W/4)`` tokens (6 m squares at the default 1.5 m cells), each token one
  cell's features plus a linear embedding of its centre's position relative to the observer
  (metres / 50, along and across its heading). The stem is two overlapping stride-2
  convolutions (``stem="conv"``, the default), or (``stem="patch"``) one convolution over
  non-overlapping 4 × 4 blocks followed by a 1 × 1 convolution: about half the arithmetic
  of an update (``latentdrive bench --train`` prints GFLOP per update), each token seeing
  its own block only;
- optionally (``context`` > 0) residual 3 × 3 convolutions over the token grid: between
  frames a second apart a car's footprint moves by its speed relative to the observer's
  (10 m at 10 m/s, nearly two tokens), so its footprints in two frames can lie in
  different tokens. The conv stem sees 8 cells (12 m at the default cells) around a token,
  one token further each way, so its context layers are dilated by 2 and each lets a
  token see two tokens further each way; the patch stem's token sees its own block, so
  its layers are not dilated and each reaches one token further;
- the token of the observer's own cell, embedded, queries every token with ``heads`` heads
  (shared weights for every cell: a car contributes the same way wherever it is, its
  position entering only as a feature);
- Q-values from the observer's token and what it attended to (or, with the dueling head,
  value and advantage streams from them).

An option measured against the paper's VFAN, never a silent replacement: the paper's body
is ``reader: conv``, the default.
"""

from __future__ import annotations

from typing import Literal

import torch
from torch import Tensor, nn

from latentdrive.actions import N_ACTIONS

__all__ = ["MapAttentionBody", "Stem", "token_grid", "token_shape"]

#: Downsampling of the stem (two stride-2 convolutions, or 4 × 4 patches).
STRIDE = 4

#: The stems :class:`MapAttentionBody` builds.
Stem = Literal["conv", "patch"]


def token_shape(height: int, width: int, stem: Stem = "conv") -> tuple[int, int]:
    """Rows and columns of tokens the stem makes of an ``height × width`` map: each stride-2
    convolution of ``"conv"`` (kernel 4 padding 1, then kernel 3 padding 1) gives
    floor(n/2), then ceil(n/2), positions; ``"patch"`` gives floor(n/4), the whole blocks
    (a remainder of fewer than 4 cells at the far edge is not read)."""
    if stem == "patch":
        return height // STRIDE, width // STRIDE
    return -(-(height // 2) // 2), -(-(width // 2) // 2)


def token_grid(height: int, width: int, resolution: float, behind: float,
               stem: Stem = "conv") -> tuple[Tensor, tuple[int, int]]:
    """Where the stem's tokens stand, relative to the observer, metres / 50, along (x,
    ahead) and across (y, to the right: row order) its heading, ``(rows · cols, 2)``
    float32 in row-major order; and the (row, column) of the observer's token.

    The frame's columns run from ``behind`` metres behind the observer forward, its rows
    across the heading with the observer on the line between the two middle rows
    (:func:`latentdrive.observe.velocitymap.render_frame`). Token ``j`` stands for the
    block of cells ``STRIDE·j`` to ``STRIDE·j + 3`` that the strided stem reduces to it, and
    its position is that block's centre. (With the stem's padding, its receptive field,
    cells ``4j − 3`` to ``4j + 4``, is centred one cell further back: the same offset for
    every token, which the position layer's bias absorbs; the patch stem's is the block
    itself.) The observer's token is the block that holds the observer, clipped to the grid."""
    rows, cols = token_shape(height, width, stem)
    size = STRIDE * resolution
    x = (torch.arange(cols, dtype=torch.float64) + 0.5) * size - behind
    y = (torch.arange(rows, dtype=torch.float64) + 0.5) * size - height * resolution / 2.0
    grid = torch.stack(torch.meshgrid(x, y, indexing="xy"), dim=-1).reshape(-1, 2) / 50.0
    me = (min(rows - 1, int(height / 2.0 // STRIDE)), min(cols - 1, int(behind / resolution // STRIDE)))
    return grid.float(), me


class MapAttentionBody(nn.Module):
    """Input ``(B, C, T, H, W)`` maps → Q-values ``(B, n_actions)`` (module docstring).

    Args:
        input_shape: ``(C, T, H, W)``; H and W at least 4.
        resolution, behind: the map's cell size and the distance it sees behind the
            observer, metres (``ObservationConfig``): where the tokens lie.
        width: token features; heads: attention heads (must divide width); context:
            dilated convolutions over the token grid (0: none); hidden: the head's hidden layer;
            stem: ``"conv"`` or ``"patch"`` (module docstring).
    """

    def __init__(self, input_shape: tuple[int, int, int, int], resolution: float, behind: float,
                 width: int = 64, heads: int = 4, context: int = 0, hidden: int = 256, n_actions: int = N_ACTIONS,
                 dueling: bool = False, stem: Stem = "conv") -> None:
        super().__init__()
        c, t, h, w = input_shape
        if h < STRIDE or w < STRIDE:
            raise ValueError(f"the attention reader needs maps of at least {STRIDE} × {STRIDE} cells, got {h} × {w}")
        if stem == "patch":
            self.stem = nn.Sequential(
                nn.Conv2d(c * t, width, kernel_size=STRIDE, stride=STRIDE), nn.ReLU(),
                nn.Conv2d(width, width, kernel_size=1), nn.ReLU(),
            )
        elif stem == "conv":
            self.stem = nn.Sequential(
                nn.Conv2d(c * t, width // 2, kernel_size=4, stride=2, padding=1), nn.ReLU(),
                nn.Conv2d(width // 2, width, kernel_size=3, stride=2, padding=1), nn.ReLU(),
            )
        else:
            raise ValueError(f"unknown stem {stem!r}: 'conv' or 'patch'")
        grid, self.me = token_grid(h, w, resolution, behind, stem)
        self.rows, self.cols = token_shape(h, w, stem)
        self.grid: Tensor
        self.register_buffer("grid", grid, persistent=False)
        self.position = nn.Linear(2, width)
        reach = 2 if stem == "conv" else 1
        self.context = nn.ModuleList(nn.Conv2d(width, width, kernel_size=3, padding=reach, dilation=reach)
                                     for _ in range(context))
        self.query = nn.Sequential(nn.Linear(width, width), nn.ReLU(), nn.Linear(width, width))
        self.attend = nn.MultiheadAttention(width, heads, batch_first=True)
        self.dueling = dueling
        if dueling:
            self.value = nn.Sequential(nn.Linear(2 * width, hidden), nn.ReLU(), nn.Linear(hidden, 1))
            self.advantage = nn.Sequential(nn.Linear(2 * width, hidden), nn.ReLU(), nn.Linear(hidden, n_actions))
        else:
            self.head = nn.Sequential(nn.Linear(2 * width, hidden), nn.ReLU(), nn.Linear(hidden, n_actions))

    def tokens(self, x: Tensor) -> Tensor:
        """Maps ``(B, C, T, H, W)`` → tokens ``(B, N, width)``: each cell's features (after
        the context layers, if any) plus its position."""
        b, c, t, h, w = x.shape
        f = self.stem(x.reshape(b, c * t, h, w))  # (B, width, rows, cols)
        if (f.shape[2], f.shape[3]) != (self.rows, self.cols):
            raise ValueError(f"maps of {h} × {w} cells, not those this reader was built for")
        for conv in self.context:
            f = f + torch.relu(conv(f))
        return f.flatten(2).transpose(1, 2) + self.position(self.grid.to(f.dtype))

    def summary(self, tokens: Tensor, me: int) -> Tensor:
        """What the head reads, ``(B, 2·width)``: the observer's query from ``tokens``
        ``(B, N, width)`` (token ``me`` the observer's) and what it attended to. The other
        tokens are read as a set: their order does not matter."""
        query = self.query(tokens[:, me])
        mixed, _ = self.attend(query[:, None], tokens, tokens, need_weights=False)
        return torch.cat([query, mixed[:, 0]], dim=1)

    def read(self, tokens: Tensor, me: int) -> Tensor:
        """Q-values ``(B, n_actions)`` from ``tokens`` ``(B, N, width)`` (:meth:`summary`)."""
        return self.q_values(self.summary(tokens, me))

    def q_values(self, z: Tensor) -> Tensor:
        """Q-values ``(B, n_actions)`` from what the head reads, ``z`` ``(B, 2·width)``
        (:meth:`embed`): a loss on ``z`` can then share the forward pass with the Q-loss."""
        if not self.dueling:
            return self.head(z)
        adv = self.advantage(z)
        # Subtracting the mean advantage makes V and A identifiable without moving the argmax.
        return self.value(z) + adv - adv.mean(dim=1, keepdim=True)

    def embed(self, x: Tensor) -> Tensor:
        """Maps ``(B, C, T, H, W)`` → what the head reads, ``(B, 2·width)`` (:meth:`summary`)."""
        return self.summary(self.tokens(x), self.me[0] * self.cols + self.me[1])

    def forward(self, x: Tensor) -> Tensor:
        return self.read(self.tokens(x), self.me[0] * self.cols + self.me[1])
