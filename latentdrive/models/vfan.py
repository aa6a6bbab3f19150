"""The VFAN (value-function approximator network): a 3D-conv Q-network over the meta-actions.

One body serves every input mode, so a comparison between modes differs only in what the
body is fed (paper section V-C):

- ``raw``: the stacked VelocityMap ``(4, T, H, W)``, the paper's baseline;
- ``latent``: the frozen bottleneck network's pair latents ``(3, d)``;
- ``latent-random``: the same encoder with untrained random weights, frozen;
- ``end-to-end``: the encoder architecture trained from scratch by the Q-loss.

Body::

    Conv3d(c_in → c1, k=(1, k1, k1), s=(1, s1, s1))   per-frame features
    Conv3d(c1 → c2, k=(kt, k2, k2), s=(1, s2, s2))     spatio-temporal
    Conv3d(c2 → c3, k=(kt, k3, k3))
    flatten → Linear(hidden) → Linear(n_actions)

with ReLUs between, the layer pattern of the authors' Conv3D Q-net. The dueling head
(Wang et al., 2016) replaces the last two layers by a value stream
``Linear(hidden) → Linear(1)`` and an advantage stream ``Linear(hidden) → Linear(n_actions)``
and returns ``V + A − mean(A)``; the body's convolutions are the same. Every kernel is
clipped to the extent of its input on each axis, so the same definition accepts any
``(C, T, H, W)``.

How latents enter a 3D-conv body: the latents ``(3, d)`` have no spatial or temporal
axes; their d coordinates are unordered features, not positions. Laying them out along a
spatial axis would make the convolutions share weights between unrelated features, as if
feature 5 were "next to" feature 6. They are therefore given as ``3·d`` channels of a
``1 × 1 × 1`` volume: each convolution's kernel clips to ``1 × 1 × 1`` and becomes a
dense layer over every latent feature. The body's depth, widths, activations and head
stay those of the raw mode; only the input representation differs, which is the
comparison the paper makes.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import Field, model_validator
from torch import Tensor, nn

from latentdrive.actions import N_ACTIONS
from latentdrive.config import Config
from latentdrive.models.attention import MapAttentionBody, Stem
from latentdrive.models.bottleneck import BottleneckNetwork
from latentdrive.models.objects import ObjectsBody

__all__ = ["LATENT_MODES", "MODES", "Mode", "QNetwork", "VFANConfig"]

Mode = Literal["raw", "latent", "latent-random", "end-to-end"]
MODES: tuple[str, ...] = ("raw", "latent", "latent-random", "end-to-end")
#: Modes whose encoder is frozen: replay stores its latents, encoded once at collection.
LATENT_MODES: tuple[str, ...] = ("latent", "latent-random")


class VFANConfig(Config):
    """Architecture of the VFAN body (the same in every input mode)."""

    channels: tuple[int, int, int] = Field((32, 64, 64), description="Output channels of the three Conv3d layers (the authors' 32, 64, 64).")
    kernels: tuple[int, int, int] = Field((8, 4, 3), description="Spatial kernel sizes (cells) of the three layers, clipped to the input extent.")
    strides: tuple[int, int] = Field((4, 2), description="Spatial strides of the first two layers (the third has stride 1).")
    temporal_kernel: int = Field(3, ge=1, le=8, description="Temporal kernel (frames) of the second and third layers, clipped to T.")
    hidden: int = Field(512, ge=8, le=4096, description="Width of the fully connected layer before the Q-values.")
    reader: Literal["conv", "attention", "objects"] = Field("conv", description="How the raw map is read: 'conv', the paper's 3D-convolutional body (the fields above); 'attention', a convolutional stem to a grid of 6 m tokens that the observer's own token queries by multi-head attention, the same weights for every cell (latentdrive.models.attention); 'objects', the vehicles of the newest frame (or frames: objects_frames) found by a fixed rule (connected HV and AV cells), the objects_k nearest, which the observer's own embedding (its speed and the road around it) queries by multi-head attention (latentdrive.models.objects; no dueling head). Both others: raw mode only; channels, kernels, strides and temporal_kernel do not apply, attention_width and attention_heads do.")
    objects_k: int = Field(16, ge=1, le=256, description="Vehicles the objects reader reads per frame, nearest first (reader 'objects').")
    objects_frames: int = Field(1, ge=1, le=16, description="The newest frames whose vehicles the objects reader reads, each frame's objects_k nearest, marked by a learned embedding of the frame's age (reader 'objects'; at most observation.frames). 1, the default, reads the newest frame only.")
    objects_layers: int = Field(0, ge=0, le=8, description="Self-attention layers (pre-norm transformer encoder layers, feed-forward 2 x attention_width) over the observer's and the vehicles' embeddings before the observer's query (reader 'objects'): they let a vehicle's rows meet its rows in other frames (objects_frames) and its neighbours. 0, the default, is the reader without them.")
    attention_width: int = Field(64, ge=8, le=1024, description="Token features of the attention reader, or vehicle and observer embedding features of the objects reader (readers 'attention' and 'objects').")
    attention_heads: int = Field(4, ge=1, le=64, description="Attention heads of the attention and objects readers; must divide attention_width.")
    attention_context: int = Field(0, ge=0, le=8, description="Residual 3x3 convolutions over the attention reader's token grid, dilated by 2 over the default stem (reader 'attention'): each lets a token see two tokens (12 m at the default cells) further each way, so that a car's footprints in frames a second apart, which lie in different tokens once it moves more than a token's 6 m relative to the observer, meet. 0, the default, is the reader without them.")
    attention_stem: Stem = Field("conv", description="The attention reader's stem: 'conv', two overlapping stride-2 convolutions (the default); 'patch', one convolution over non-overlapping 4 x 4 blocks of cells and a 1 x 1 convolution, about half the arithmetic per update (latentdrive bench --train prints GFLOP per update), each token seeing its own 6 m block only (attention_context's layers are then not dilated), and the last rows or columns of a map whose sides are not multiples of 4 left unread.")

    @model_validator(mode="after")
    def _heads_divide(self) -> VFANConfig:
        if self.attention_width % self.attention_heads:
            raise ValueError(f"attention_heads={self.attention_heads} does not divide attention_width={self.attention_width}")
        return self


def _conv(c_in: int, c_out: int, size: tuple[int, int, int], kernel: tuple[int, int, int],
          stride: tuple[int, int, int]) -> tuple[nn.Conv3d, tuple[int, int, int]]:
    """A Conv3d whose kernel (and stride) are clipped to ``size``; returns it and its output size."""
    k = (min(kernel[0], size[0]), min(kernel[1], size[1]), min(kernel[2], size[2]))
    s = (min(stride[0], k[0]), min(stride[1], k[1]), min(stride[2], k[2]))
    out = ((size[0] - k[0]) // s[0] + 1, (size[1] - k[1]) // s[1] + 1, (size[2] - k[2]) // s[2] + 1)
    return nn.Conv3d(c_in, c_out, kernel_size=k, stride=s), out


class VFANBody(nn.Module):
    """The shared body: input ``(B, C, T, H, W)`` → Q-values ``(B, n_actions)``.

    With ``dueling`` the fully connected part is two streams, value and advantage
    (see the module docstring); ``net`` then ends at the flattened convolution features.
    """

    def __init__(self, cfg: VFANConfig, input_shape: tuple[int, int, int, int], n_actions: int = N_ACTIONS,
                 dueling: bool = False) -> None:
        super().__init__()
        c, *size_ = input_shape
        size = (size_[0], size_[1], size_[2])
        kt = cfg.temporal_kernel
        k1, k2, k3 = cfg.kernels
        s1, s2 = cfg.strides
        conv1, size = _conv(c, cfg.channels[0], size, (1, k1, k1), (1, s1, s1))
        conv2, size = _conv(cfg.channels[0], cfg.channels[1], size, (kt, k2, k2), (1, s2, s2))
        conv3, size = _conv(cfg.channels[1], cfg.channels[2], size, (kt, k3, k3), (1, 1, 1))
        flat = cfg.channels[2] * size[0] * size[1] * size[2]
        self.pointwise = input_shape[1:] == (1, 1, 1)
        self.dueling = dueling
        convs: list[nn.Module] = [conv1, nn.ReLU(), conv2, nn.ReLU(), conv3, nn.ReLU(), nn.Flatten()]
        if dueling:
            self.net = nn.Sequential(*convs)
            self.value = nn.Sequential(nn.Linear(flat, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, 1))
            self.advantage = nn.Sequential(nn.Linear(flat, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, n_actions))
        else:
            # One Sequential, as before the dueling option: its parameter names are those
            # of every checkpoint trained without it.
            self.net = nn.Sequential(*convs, nn.Linear(flat, cfg.hidden), nn.ReLU(), nn.Linear(cfg.hidden, n_actions))

    def forward(self, x: Tensor) -> Tensor:
        if not self.pointwise:
            if x.device.type == "cpu":
                # oneDNN's 3D convolutions run faster on channels-last input (docs/performance.md,
                # "Channels-last maps"); the weights keep their layout, so checkpoints do not
                # change. Replay's CPU batches come laid out so; this copies only other input.
                # Not measured on CUDA, where input stays as it comes.
                x = x.contiguous(memory_format=torch.channels_last_3d)
            h = self.net(x)
        else:
            # A 1×1×1 volume: each convolution is exactly a dense layer over the channels;
            # computing it as one skips the 3D-convolution machinery (same parameters, same math).
            h = x.flatten(1)
            for layer in self.net:
                if isinstance(layer, nn.Conv3d):
                    h = F.linear(h, layer.weight.flatten(1), layer.bias)
                elif not isinstance(layer, nn.Flatten):
                    h = layer(h)
        if not self.dueling:
            return h
        adv = self.advantage(h)
        # Subtracting the mean advantage makes V and A identifiable without moving the argmax.
        return self.value(h) + adv - adv.mean(dim=1, keepdim=True)


class QNetwork(nn.Module):
    """A VFAN with its input mode: what replay stores → Q-values ``(B, n_actions)``.

    Replay holds, per agent-observation, :attr:`stored_shape`:

    - ``raw`` and ``end-to-end``: the observation ``(4, T, H, W)`` (kept as uint8 frames
      by the replay buffer);
    - ``latent`` and ``latent-random``: its latents ``(3, d)``, from :meth:`features`;
    - ``raw`` with the objects reader: the vehicles and road it reads of the map
      ``(F,)``, from :meth:`features`.

    Args:
        cfg: the body's architecture.
        mode: the input mode.
        observation_shape: ``(4, T, H, W)``.
        encoder: the bottleneck network (latent modes and end-to-end); its parameters are
            frozen in the latent modes and trained in end-to-end.
        dueling: a dueling head (value and advantage streams) instead of one output layer.
        geometry: the map's cell size and the distance it sees behind the observer,
            metres (``ObservationConfig.resolution``, ``.behind``): where the attention
            reader's tokens and the objects reader's vehicles lie (readers ``"attention"``
            and ``"objects"``, which need it).
    """

    def __init__(self, cfg: VFANConfig, mode: Mode, observation_shape: tuple[int, int, int, int],
                 encoder: BottleneckNetwork | None = None, dueling: bool = False,
                 geometry: tuple[float, float] | None = None) -> None:
        super().__init__()
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}: choose one of {', '.join(MODES)}")
        if (mode == "raw") != (encoder is None):
            raise ValueError(f"mode {mode!r} {'takes no' if mode == 'raw' else 'needs an'} encoder")
        self.cfg = cfg
        self.mode: Mode = mode
        self.observation_shape = observation_shape
        self.encoder = encoder
        if encoder is not None:
            if tuple(encoder.cfg.observation_shape) != tuple(observation_shape):
                raise ValueError(f"the encoder takes observations {encoder.cfg.observation_shape}, "
                                 f"not {observation_shape}")
            if mode in LATENT_MODES:
                encoder.eval().requires_grad_(False)
            else:
                # end-to-end: the Q-loss reaches the encoder half only.
                ae = encoder.autoencoder
                for part in ae.decoder_modules():
                    part.requires_grad_(False)
            n_latent = encoder.latent_size
            body_input: tuple[int, int, int, int] = (n_latent, 1, 1, 1)
        else:
            body_input = observation_shape
        self.body: nn.Module
        if cfg.reader != "conv":
            if mode != "raw":
                raise ValueError(f"the {cfg.reader} reader reads raw maps; mode {mode!r} feeds the body latents")
            if geometry is None:
                raise ValueError(f"the {cfg.reader} reader needs the map's geometry (resolution, behind)")
        if cfg.reader == "objects":
            if dueling:
                raise ValueError("the objects reader has no dueling head (dqn.dueling=false)")
            assert geometry is not None
            self.body = ObjectsBody(observation_shape, *geometry, k=cfg.objects_k, width=cfg.attention_width,
                                    heads=cfg.attention_heads, hidden=cfg.hidden, frames=cfg.objects_frames,
                                    layers=cfg.objects_layers)
        elif cfg.reader == "attention":
            assert geometry is not None
            self.body = MapAttentionBody(observation_shape, *geometry, width=cfg.attention_width,
                                         heads=cfg.attention_heads, context=cfg.attention_context,
                                         hidden=cfg.hidden, dueling=dueling, stem=cfg.attention_stem)
        else:
            self.body = VFANBody(cfg, body_input, dueling=dueling)

    @property
    def stores_features(self) -> bool:
        """Whether replay stores a fixed function of each observation (:meth:`features`,
        computed once when it is collected) rather than its map frames: the frozen
        encoder's code in the latent modes, the vehicles found in the map by the objects reader."""
        return self.mode in LATENT_MODES or isinstance(self.body, ObjectsBody)

    @property
    def stored_shape(self) -> tuple[int, ...]:
        """Per-observation shape of what replay stores."""
        if self.mode in LATENT_MODES:
            assert self.encoder is not None
            return self.encoder.latent_shape
        if isinstance(self.body, ObjectsBody):
            return (self.body.feature_size,)
        return self.observation_shape

    def trainable_parameters(self) -> list[nn.Parameter]:
        """What the Q-loss updates: the body, plus the encoder in end-to-end mode."""
        return [p for p in self.parameters() if p.requires_grad]

    def parameter_count(self) -> dict[str, int]:
        """Parameters of the body (with its head), of the encoder part that feeds it, and trainable in all."""
        body = sum(p.numel() for p in self.body.parameters())
        enc = 0
        if self.encoder is not None:
            ae = self.encoder.autoencoder
            enc = sum(p.numel() for m in ae.encoder_modules() for p in m.parameters())
        return {"body": body, "encoder": enc, "trainable": sum(p.numel() for p in self.trainable_parameters())}

    @torch.no_grad()
    def features(self, obs: Tensor) -> Tensor:
        """Observations ``(B, 4, T, H, W)`` → what replay stores for them (no gradient)."""
        if self.mode in LATENT_MODES:
            assert self.encoder is not None
            return self.encoder.encode(obs)
        if isinstance(self.body, ObjectsBody):
            return self.body.features(obs)
        return obs

    def forward(self, stored: Tensor) -> Tensor:
        """Stored inputs ``(B, *stored_shape)`` → Q-values ``(B, n_actions)``."""
        if self.mode == "end-to-end":
            assert self.encoder is not None
            stored = self.encoder.encode(stored)
        if self.mode != "raw":
            stored = stored.reshape(stored.shape[0], -1, 1, 1, 1)
        return self.body(stored)

    def summary(self, stored: Tensor) -> Tensor:
        """Stored inputs ``(B, *stored_shape)`` → what the attention reader's head reads,
        ``(B, 2·attention_width)`` (an auxiliary loss's input; reader 'attention' only)."""
        if not isinstance(self.body, MapAttentionBody):
            raise ValueError("only the attention reader (vfan.reader 'attention') exposes a summary")
        return self.body.embed(stored)

    def q_from_summary(self, z: Tensor) -> Tensor:
        """Q-values ``(B, n_actions)`` from :meth:`summary`'s rows ``z``: ``forward(x)``
        equals ``q_from_summary(summary(x))`` (reader 'attention' only)."""
        if not isinstance(self.body, MapAttentionBody):
            raise ValueError("only the attention reader (vfan.reader 'attention') exposes a summary")
        return self.body.q_values(z)

    @property
    def summary_size(self) -> int:
        """Length of :meth:`summary`'s rows."""
        return 2 * self.cfg.attention_width

    def train(self, mode: bool = True) -> QNetwork:
        super().train(mode)
        if self.mode in LATENT_MODES and self.encoder is not None:
            self.encoder.eval()  # frozen: no dropout/batch-norm statistics may move
        return self
