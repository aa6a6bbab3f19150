"""An objects reader of the VelocityMap (``vfan.reader: objects``; raw mode only).

The learned readers of the map (the paper's convolutions, the attention reader) must learn
to find the vehicles before they can learn to drive among them, and at 100,000
agent-transitions they find them poorly (docs/readers.md). A Q-network that reads the
vehicles as a set generalizes across them (ego-attention; Leurent and Mercat, "Social
attention for autonomous decision-making in dense traffic", 2019). This reader finds the
vehicles by a fixed rule instead of learning to and reads them so:

- the vehicles of the newest frame, :func:`latentdrive.observe.objects.map_objects`: the
  ``k`` nearest, each its place, value, kind and size; no gradient flows through the rule;
  with ``frames`` > 1, the ``k`` nearest of each of the newest ``frames`` frames as well,
  each marked by a learned embedding of its frame's age: the sensor noise moves a car's
  place and drops it from frames independently, and attention over its footprints in
  several frames can average the one and bridge the other;
- the observer's own part: its speed in the two newest frames (the MV channel's peak,
  ``|v| / max_speed``) and the newest road channel averaged over ``pool`` × ``pool`` cells;
- with ``layers`` > 0, that many self-attention layers over the observer's and every
  vehicle's embedding first (pre-norm transformer encoder layers), so that a vehicle's
  rows can meet its rows in other frames and its neighbours before the observer reads
  them: the query alone can only weigh rows, not relate them;
- the observer's embedding queries every vehicle's, its own included, with ``heads``
  heads (layers shared by all vehicles, so a car contributes the same way wherever it is
  and whatever its rank); Q-values from the observer's embedding and what it attended to.

It reads only the map, like every raw-mode reader. An option measured against the paper's
VFAN, never a silent replacement: the paper's body is ``reader: conv``, the default.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from latentdrive.actions import N_ACTIONS
from latentdrive.observe.objects import PER_OBJECT, map_objects
from latentdrive.observe.velocitymap import MV, RL

__all__ = ["ROAD_POOL", "ObjectsBody"]

#: Cells per side of the blocks the road channel is averaged over (6 m at the default cells).
ROAD_POOL = 4


class ObjectsBody(nn.Module):
    """What it reads of the maps, :meth:`features` ``(B, feature_size)`` → Q-values
    ``(B, n_actions)`` (module docstring).

    Args:
        input_shape: ``(4, T, H, W)``; T at least 2, H and W multiples of :data:`ROAD_POOL`.
        resolution, behind: the map's cell size and the distance it sees behind the
            observer, metres (``ObservationConfig``): where the vehicles lie.
        k: vehicles read per frame; frames: the newest frames whose vehicles are read (1 to
            T); width: embedding features; heads: attention heads (must divide width);
            hidden: the head's hidden layer; layers: self-attention layers over the
            embeddings before the observer's query (0: none).
    """

    def __init__(self, input_shape: tuple[int, int, int, int], resolution: float, behind: float, k: int = 16,
                 width: int = 64, heads: int = 4, hidden: int = 256, n_actions: int = N_ACTIONS,
                 frames: int = 1, layers: int = 0) -> None:
        super().__init__()
        c, t, h, w = input_shape
        if c != 4 or t < 2:
            raise ValueError(f"the objects reader reads stacks of at least 2 frames of 4 channels, got {input_shape}")
        if not 1 <= frames <= t:
            raise ValueError(f"the objects reader reads the vehicles of 1 to {t} frames of these stacks, got {frames}")
        if h % ROAD_POOL or w % ROAD_POOL:
            raise ValueError(f"the objects reader needs maps whose sides are multiples of {ROAD_POOL}, got {h} × {w}")
        self.resolution, self.behind, self.k, self.frames = resolution, behind, k, frames
        self._ego = 2 + (h // ROAD_POOL) * (w // ROAD_POOL)
        self.embed_ego = nn.Sequential(nn.Linear(self._ego, width), nn.ReLU(), nn.Linear(width, width))
        self.embed_vehicle = nn.Sequential(nn.Linear(PER_OBJECT, width), nn.ReLU(), nn.Linear(width, width))
        # Only where there are several frames to tell apart: a one-frame reader's weights
        # stay those it always had.
        self.age = nn.Parameter(torch.zeros(frames, width)) if frames > 1 else None
        self.mix = nn.ModuleList(
            nn.TransformerEncoderLayer(width, heads, dim_feedforward=2 * width, dropout=0.0, batch_first=True,
                                       norm_first=True) for _ in range(layers))
        self.attend = nn.MultiheadAttention(width, heads, batch_first=True)
        self.head = nn.Sequential(nn.Linear(2 * width, hidden), nn.ReLU(), nn.Linear(hidden, n_actions))

    @property
    def feature_size(self) -> int:
        """Length of :meth:`features`' rows: 2 speeds, the pooled road, ``frames·k`` vehicle rows."""
        return self._ego + self.frames * self.k * PER_OBJECT

    @torch.no_grad()
    def features(self, x: Tensor) -> Tensor:
        """Maps ``(B, 4, T, H, W)`` → what the reader reads of them, ``(B, feature_size)`` float32:
        the two newest speeds, the newest road pooled, then ``k`` vehicle rows of each of
        the newest ``frames`` frames, newest frame first.

        A fixed function of the map, so replay stores it once per observation (as latent
        modes store the frozen encoder's code) instead of finding the vehicles again at
        every update. fp32 under any autocast: none of its ops is one autocast lowers."""
        x = x.float()
        b, t = x.shape[0], x.shape[2]
        # Each frame as a stack that ends there, all in one batch (blob labels are unique
        # across a batch): (frames·B, k, 6) → (B, frames·k, 6).
        ends = torch.cat([x[:, :, t - 1 - age:t - age] for age in range(self.frames)])
        vehicles = map_objects(ends, self.resolution, self.behind, self.k)
        vehicles = vehicles.view(self.frames, b, self.k, PER_OBJECT).transpose(0, 1)
        speed = x[:, MV, -2:].amax(dim=(-2, -1))  # (B, 2)
        road = F.avg_pool2d(x[:, RL, -1:], ROAD_POOL).flatten(1)
        return torch.cat([speed, road, vehicles.flatten(1)], dim=1)

    def forward(self, f: Tensor) -> Tensor:
        """:meth:`features`' rows ``(B, feature_size)`` → Q-values ``(B, n_actions)``."""
        b = f.shape[0]
        vehicles = f[:, self._ego:].reshape(b, self.frames * self.k, PER_OBJECT)
        me = self.embed_ego(f[:, :self._ego])
        seen = self.embed_vehicle(vehicles)
        if self.age is not None:
            seen = seen + self.age.repeat_interleave(self.k, dim=0)
        tokens = torch.cat([me[:, None], seen], dim=1)
        # A vehicle row's last value is 1, a padding row's 0; the observer's token is always read.
        absent = torch.cat([torch.zeros(b, 1, dtype=torch.bool, device=f.device), vehicles[:, :, -1] < 0.5], dim=1)
        for layer in self.mix:
            tokens = layer(tokens, src_key_padding_mask=absent)
            me = tokens[:, 0]
        mixed, _ = self.attend(me[:, None], tokens, tokens, key_padding_mask=absent, need_weights=False)
        return self.head(torch.cat([me, mixed[:, 0]], dim=1))
