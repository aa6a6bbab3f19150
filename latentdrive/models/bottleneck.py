"""The bottleneck network (BNN): a denoising 3D-conv autoencoder over VelocityMap channel pairs.

An observation is a stacked VelocityMap ``(B, 4, T, H, W)`` in [0, 1] with channels
HV, AV, RL, MV (see :class:`latentdrive.config.ObservationConfig`). The BNN splits it into
three channel pairs, HV+AV, RL+AV and MV+AV, and passes each pair through the *same*
:class:`PairAutoencoder` (shared weights, paper section V-B). The three latent codes,
``(B, 3, d)``, are the restricted representation the Q-network sees.

Encoder of one pair ``(B, 2, T, H, W)``::

    Conv3d(2→c0, k=(1,ks,ks), s=(1,2,2))          spatial only: per-frame features
    Conv3d(c_{i-1}→c_i, k=(kt,ks,ks), s=(1,2,2))  for i ≥ 1: spatio-temporal
    [residual 3D conv blocks at the last stage]
    flatten → [Linear → hidden → ReLU] → Linear → d → [LayerNorm] → latent activation

Decoder, the mirror image::

    [Linear(d → hidden) → ReLU] → Linear(→ flat) → reshape to the last stage's (c, T, h, w)
    [residual 3D conv blocks at the last stage]
    ConvTranspose3d(c_i→c_{i-1}, k=(kt,ks+1,ks+1), s=(1,2,2)), crop   for i = L-1 … 1
    ConvTranspose3d(c0→2, k=(1,ks+1,ks+1), s=(1,2,2)), crop → logits → sigmoid

The bracketed parts are :class:`BottleneckConfig` options (``head_hidden``,
``residual_blocks``, ``latent_norm``); ``decoder=broadcast`` replaces the decoder's linear
layers by an MLP shared by the coarse cells, fed the code and each cell's coordinates. With
the first three off and the linear decoder the network is the paper's
structure, a single linear layer on each side of the code. Three things in that plain
structure lose the vehicles (docs/bnn-notes.md): one ReLU layer between the code and the
map leaves the decoder too little capacity to place a handful of cars, and a sigmoid code
fed by one linear layer from thousands of features saturates within a few dozen Adam
steps (the code turns nearly binary). A hidden layer on each side and a LayerNorm before
the activation address them; the code stays bounded in (0, 1) for the Q-network.

Each encoder stage halves H and W, rounding up (``ceil(n/2)``: odd kernels padded by
``k//2`` with stride 2), and keeps T (temporal padding ``kt//2``), so every ``T ≥ 1`` and
``H, W ≥ 1`` is valid; configs require ``H, W ≥ 8`` so that the code still sees a
spatial layout rather than one cell. Each decoder stage exactly doubles H and W (an even
kernel ``ks+1`` padded by ``(ks-1)/2``, which also overlaps every output cell evenly and
so avoids checkerboard artefacts) and is cropped to the size the matching encoder stage
received, which restores odd sizes exactly. Transposed convolutions compute at the
coarse resolution; upsampling followed by a convolution would compute at the fine one,
about ten times slower on CPU for the last stage at the default size. The decoder ends
in logits (:meth:`PairAutoencoder.decode_logits`, for losses computed with logits);
:meth:`~PairAutoencoder.decode` applies the sigmoid, so reconstructions lie in [0, 1]
like the VelocityMap.

This module holds ``nn.Module`` code only; training lives in :mod:`latentdrive.bnn`.
"""

from __future__ import annotations

import math
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import Field, field_validator
from torch import Tensor, nn

from latentdrive.config import Config, ObservationConfig

__all__ = [
    "PAIR_CHANNELS",
    "PAIR_NAMES",
    "BottleneckConfig",
    "BottleneckNetwork",
    "PairAutoencoder",
    "SpatialBroadcast",
    "channel_pairs",
]

#: Observation channel indices of the three pairs, in the order of the latent axis:
#: (HV, AV), (RL, AV), (MV, AV). The AV channel is the second member of every pair.
PAIR_CHANNELS: tuple[tuple[int, int], ...] = ((0, 1), (2, 1), (3, 1))
PAIR_NAMES: tuple[str, ...] = ("HV+AV", "RL+AV", "MV+AV")

# The flat index list used to gather all three pairs in one indexing operation.
_PAIR_INDEX: list[int] = [c for pair in PAIR_CHANNELS for c in pair]


class BottleneckConfig(Config):
    """Architecture of the bottleneck network (one shared pair autoencoder)."""

    input_shape: tuple[int, int, int] = Field(
        (4, 32, 64),
        description="(T, H, W) of the observation: stacked frames, grid rows, grid columns "
        "(cells). T ≥ 1, H and W ≥ 8.",
    )
    latent_dim: int = Field(
        64, ge=2, le=512,
        description="d: size of each pair's latent code (dimensionless units). The paper "
        "compares 16, 32 and 64 and keeps 64.",
    )
    channels: tuple[int, ...] = Field(
        (16, 32),
        description="Feature channels of the encoder stages; each stage halves H and W "
        "(rounding up). The decoder mirrors them. 1 to 6 stages, each 1..512. Two stages "
        "leave an 8×16 map of 6 m squares for the linear layer to compress at the default "
        "32×64 grid of 1.5 m cells. With a third stage (4×8 squares of 12 m), the same "
        "training recovered fewer held-out vehicles at a higher error "
        "(docs/bnn-notes.md, 'Architecture and loss').",
    )
    spatial_kernel: int = Field(
        3, ge=1, le=9, description="Spatial kernel size (cells) of every convolution; odd."
    )
    temporal_kernel: int = Field(
        3, ge=1, le=7,
        description="Temporal kernel size (frames) of the convolutions after the first; odd. "
        "Reduced to 1 when T = 1, where wider kernels would only see padding.",
    )
    latent_activation: Literal["sigmoid", "tanh", "identity"] = Field(
        "sigmoid",
        description="σ_y of paper eq. 9 applied to the code. Sigmoid keeps latents in [0, 1], "
        "the same range as the VelocityMaps the Q-network sees in the baseline.",
    )
    latent_norm: bool = Field(
        True,
        description="LayerNorm (with its own scale and shift) on the code before the latent "
        "activation. Without it a sigmoid code fed by one linear layer from thousands of "
        "features saturates within tens of steps (docs/bnn-notes.md). False is the paper's "
        "structure.",
    )
    head_hidden: int = Field(
        256, ge=0, le=8192,
        description="Width of a hidden ReLU layer between the convolutional features and the "
        "code, on both sides (flat → hidden → d, d → hidden → flat; the decoder's side only with "
        "decoder=linear). 0: one linear layer each side, the paper's structure.",
    )
    residual_blocks: int = Field(
        0, ge=0, le=8,
        description="Residual 3D conv blocks (two convolutions each) at the last, coarsest "
        "stage of the encoder and, mirrored, of the decoder. 0 is the paper's structure.",
    )
    decoder: Literal["linear", "broadcast"] = Field(
        "linear",
        description="How the decoder turns the code into the coarsest stage's feature map. "
        "'linear': one linear layer (through head_hidden when set) to every cell's features "
        "at once, the paper's structure. 'broadcast': a spatial broadcast decoder (Watters et "
        "al., 2019): the code goes to every coarse cell with that cell's (frame, row, column) "
        "coordinates, and one small MLP, shared by all cells, computes each cell's features "
        "(broadcast_hidden wide). A car at one place and a car at another are then drawn by "
        "the same weights. Measured worse than 'linear' on the small study's d = 64 "
        "(docs/bnn-notes.md, 'A spatial broadcast decoder').",
    )
    broadcast_hidden: int = Field(
        128, ge=8, le=1024,
        description="Width of the broadcast decoder's two hidden layers (decoder=broadcast only).",
    )
    initial_output: float = Field(
        0.05, gt=0.0, lt=1.0,
        description="Reconstruction value at initialization (the sigmoid of the output bias), "
        "in [0, 1] cell units. VelocityMaps are mostly empty; starting near their mean cell "
        "value rather than 0.5 keeps the first updates from pushing every output down at "
        "once, which silences the decoder's ReLUs and stalls training at the all-zero map.",
    )

    @field_validator("input_shape")
    @classmethod
    def _check_input_shape(cls, v: tuple[int, int, int]) -> tuple[int, int, int]:
        frames, height, width = v
        if frames < 1 or height < 8 or width < 8:
            raise ValueError(f"need T >= 1, H >= 8 and W >= 8, got (T, H, W) = {v}")
        return v

    @field_validator("channels")
    @classmethod
    def _check_channels(cls, v: tuple[int, ...]) -> tuple[int, ...]:
        if not 1 <= len(v) <= 6 or any(not 1 <= c <= 512 for c in v):
            raise ValueError(f"need 1 to 6 stages of 1..512 channels, got {v}")
        return v

    @field_validator("spatial_kernel", "temporal_kernel")
    @classmethod
    def _check_odd(cls, v: int) -> int:
        # Odd kernels with padding k//2 give the ceil(n/2) stage sizes the decoder relies on.
        if v % 2 == 0:
            raise ValueError(f"must be odd, got {v}")
        return v

    @classmethod
    def for_observation(cls, obs: ObservationConfig, **fields: object) -> BottleneckConfig:
        """A config whose ``input_shape`` matches ``obs`` (other fields from ``fields``)."""
        return cls.model_validate({"input_shape": (obs.frames, obs.height, obs.width), **fields})

    @property
    def observation_shape(self) -> tuple[int, int, int, int]:
        """Per-agent observation shape ``(4, T, H, W)`` this network accepts."""
        return (4, *self.input_shape)

    @property
    def pair_shape(self) -> tuple[int, int, int, int]:
        """Shape ``(2, T, H, W)`` of one channel pair."""
        return (2, *self.input_shape)


def _activation(name: str) -> nn.Module:
    if name == "sigmoid":
        return nn.Sigmoid()
    if name == "tanh":
        return nn.Tanh()
    return nn.Identity()


class _Residual(nn.Module):
    """``x + conv(relu(conv(relu(x))))`` at one resolution: same channels, same size."""

    def __init__(self, channels: int, kt: int, ks: int) -> None:
        super().__init__()
        pad = (kt // 2, ks // 2, ks // 2)
        self.conv1 = nn.Conv3d(channels, channels, (kt, ks, ks), padding=pad)
        self.conv2 = nn.Conv3d(channels, channels, (kt, ks, ks), padding=pad)

    def forward(self, x: Tensor) -> Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class SpatialBroadcast(nn.Module):
    """Code ``(B, d)`` → coarse features ``(B, c·T·h·w)`` in ``(c, T, h, w)`` order: a shared
    MLP of each coarse cell's code and coordinates (each axis scaled to [-1, 1]).

    The first layer is linear in code and coordinates, so its code part is computed once per
    sample and its coordinate part once per cell, rather than once per sample and cell."""

    def __init__(self, latent_dim: int, code_shape: tuple[int, int, int, int], hidden: int) -> None:
        super().__init__()
        c, t, h, w = code_shape
        axes = [torch.linspace(-1.0, 1.0, n) if n > 1 else torch.zeros(1) for n in (t, h, w)]
        coords = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(t * h * w, 3)
        self.coords: Tensor
        self.register_buffer("coords", coords, persistent=False)
        self.from_code = nn.Linear(latent_dim, hidden)
        self.from_place = nn.Linear(3, hidden, bias=False)
        self.cell = nn.Sequential(nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(), nn.Linear(hidden, c))

    def forward(self, z: Tensor) -> Tensor:
        a = self.from_code(z)[:, None, :] + self.from_place(self.coords.to(z.dtype))[None]
        return self.cell(a).transpose(1, 2).reshape(z.shape[0], -1)


def _head(sizes: list[int]) -> nn.Sequential:
    """Linear layers through ``sizes`` with ReLUs between them (none after the last)."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        if i:
            layers.append(nn.ReLU())
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
    return nn.Sequential(*layers)


class PairAutoencoder(nn.Module):
    """Denoising 3D-conv autoencoder for one channel pair.

    ``encode``: ``(B, 2, T, H, W)`` in [0, 1] → ``(B, d)``;
    ``decode_logits``: ``(B, d)`` → ``(B, 2, T, H, W)`` logits; ``decode``: their sigmoid,
    in [0, 1]; ``forward``: encode and decode, returning ``(reconstruction, latent)``.
    """

    def __init__(self, cfg: BottleneckConfig) -> None:
        super().__init__()
        self.cfg = cfg
        frames, height, width = cfg.input_shape
        ks = cfg.spatial_kernel
        kt = cfg.temporal_kernel if frames > 1 else 1
        widths = (2, *cfg.channels)

        enc: list[nn.Module] = []
        for i in range(len(cfg.channels)):
            # The first stage is purely spatial (per-frame), later stages mix frames too.
            kt_i = 1 if i == 0 else kt
            enc.append(
                nn.Conv3d(
                    widths[i], widths[i + 1], kernel_size=(kt_i, ks, ks),
                    stride=(1, 2, 2), padding=(kt_i // 2, ks // 2, ks // 2),
                )
            )
            enc.append(nn.ReLU())
        self.encoder_convs = nn.Sequential(*enc)
        kt_last = 1 if len(cfg.channels) == 1 else kt
        c_last = cfg.channels[-1]
        self.encoder_blocks = nn.Sequential(
            *(_Residual(c_last, kt_last, ks) for _ in range(cfg.residual_blocks))
        )
        self.decoder_blocks = nn.Sequential(
            *(_Residual(c_last, kt_last, ks) for _ in range(cfg.residual_blocks))
        )

        # Record every stage's (T, H, W) with a dummy forward so the decoder can crop to
        # exactly those sizes, whatever the input shape.
        sizes: list[tuple[int, int, int]] = [(frames, height, width)]
        with torch.no_grad():
            h = torch.zeros(1, 2, frames, height, width)
            for layer in self.encoder_convs:
                h = layer(h)
                if isinstance(layer, nn.Conv3d):
                    t_, h_, w_ = h.shape[2:]
                    sizes.append((int(t_), int(h_), int(w_)))
        self.stage_sizes: tuple[tuple[int, int, int], ...] = tuple(sizes)
        self.code_shape: tuple[int, int, int, int] = (c_last, *sizes[-1])
        flat = int(h.numel())

        hidden = [cfg.head_hidden] if cfg.head_hidden else []
        self.to_latent = _head([flat, *hidden, cfg.latent_dim])
        self.latent_norm: nn.Module = nn.LayerNorm(cfg.latent_dim) if cfg.latent_norm else nn.Identity()
        self.latent_act = _activation(cfg.latent_activation)
        self.from_latent: nn.Module = (
            SpatialBroadcast(cfg.latent_dim, self.code_shape, cfg.broadcast_hidden) if cfg.decoder == "broadcast"
            else _head([cfg.latent_dim, *hidden, flat])
        )

        dec: list[nn.Module] = []
        for i in range(len(cfg.channels) - 1, -1, -1):
            kt_i = 1 if i == 0 else kt
            # Output size 2(n-1) - (ks-1) + (ks+1) = 2n spatially, T unchanged in time.
            dec.append(
                nn.ConvTranspose3d(
                    widths[i + 1], widths[i], kernel_size=(kt_i, ks + 1, ks + 1),
                    stride=(1, 2, 2), padding=(kt_i // 2, (ks - 1) // 2, (ks - 1) // 2),
                )
            )
        self.decoder_convs = nn.ModuleList(dec)
        out_conv = dec[-1]
        assert isinstance(out_conv, nn.ConvTranspose3d) and out_conv.bias is not None
        with torch.no_grad():
            p = cfg.initial_output
            out_conv.bias.fill_(math.log(p / (1.0 - p)))

    @property
    def latent_dim(self) -> int:
        """d, the size of the code."""
        return self.cfg.latent_dim

    def encoder_modules(self) -> tuple[nn.Module, ...]:
        """The modules of :meth:`encode` (observation → code)."""
        return (self.encoder_convs, self.encoder_blocks, self.to_latent, self.latent_norm)

    def decoder_modules(self) -> tuple[nn.Module, ...]:
        """The modules of :meth:`decode` (code → reconstruction)."""
        return (self.from_latent, self.decoder_blocks, self.decoder_convs)

    def encode(self, x: Tensor) -> Tensor:
        """Pairs ``(B, 2, T, H, W)`` → latents ``(B, d)``."""
        h = self.encoder_blocks(self.encoder_convs(x))
        return self.latent_act(self.latent_norm(self.to_latent(h.flatten(1))))

    def decode_logits(self, z: Tensor) -> Tensor:
        """Latents ``(B, d)`` → reconstruction logits ``(B, 2, T, H, W)``."""
        h = F.relu(self.from_latent(z)).view(z.shape[0], *self.code_shape)
        h = self.decoder_blocks(h)
        n = len(self.decoder_convs)
        for j, conv in enumerate(self.decoder_convs):
            # Mirror of encoder stage i = n-1-j: double H and W, then crop to the size that
            # stage received (2·ceil(k/2) exceeds an odd size k by one cell).
            t, hh, ww = self.stage_sizes[n - 1 - j]
            h = conv(h)[:, :, :t, :hh, :ww]
            if j < n - 1:
                h = F.relu(h)
        return h

    def decode(self, z: Tensor) -> Tensor:
        """Latents ``(B, d)`` → reconstructed pairs ``(B, 2, T, H, W)`` in [0, 1]."""
        return torch.sigmoid(self.decode_logits(z))

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Pairs ``(B, 2, T, H, W)`` → ``(reconstruction (B, 2, T, H, W), latent (B, d))``."""
        z = self.encode(x)
        return self.decode(z), z


def channel_pairs(x: Tensor) -> Tensor:
    """The three channel pairs of observations ``(B, 4, T, H, W)`` → ``(B, 3, 2, T, H, W)``.

    Pair ``k`` holds channels ``PAIR_CHANNELS[k]``: HV+AV, RL+AV, MV+AV.
    """
    if x.ndim != 5 or x.shape[1] != 4:
        raise ValueError(f"expected observations of shape (B, 4, T, H, W), got {tuple(x.shape)}")
    b, _, t, h, w = x.shape
    return x[:, _PAIR_INDEX].view(b, len(PAIR_CHANNELS), 2, t, h, w)


class BottleneckNetwork(nn.Module):
    """One shared :class:`PairAutoencoder` applied to the three channel pairs of an observation.

    The representation handed to the Q-network is :meth:`encode`'s ``(B, 3, d)``: three
    "channels" (HV+AV, RL+AV, MV+AV, in that order) of a d-vector each. A Q-network may
    use it as ``(B, 3, d)`` or flattened to ``(B, 3·d)`` (:attr:`latent_size`).
    """

    def __init__(self, cfg: BottleneckConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.autoencoder = PairAutoencoder(cfg)

    @property
    def latent_shape(self) -> tuple[int, int]:
        """``(3, d)``: per-observation shape of :meth:`encode`'s output."""
        return (len(PAIR_CHANNELS), self.cfg.latent_dim)

    @property
    def latent_size(self) -> int:
        """``3·d``: size of the flattened representation."""
        return len(PAIR_CHANNELS) * self.cfg.latent_dim

    def _check(self, x: Tensor) -> None:
        expected = self.cfg.observation_shape
        if x.ndim != 5 or tuple(x.shape[1:]) != expected:
            raise ValueError(
                f"expected observations of shape (B, {', '.join(map(str, expected))}), "
                f"got {tuple(x.shape)}"
            )

    @staticmethod
    def pairs(x: Tensor) -> Tensor:
        """Pair targets ``(B, 3, 2, T, H, W)`` built from observations ``(B, 4, T, H, W)``."""
        return channel_pairs(x)

    def encode(self, x: Tensor) -> Tensor:
        """Observations ``(B, 4, T, H, W)`` → latents ``(B, 3, d)``."""
        self._check(x)
        p = channel_pairs(x)
        b = p.shape[0]
        # The three pairs go through the one autoencoder as a single batch of 3B.
        z = self.autoencoder.encode(p.reshape(b * len(PAIR_CHANNELS), *p.shape[2:]))
        return z.view(b, len(PAIR_CHANNELS), -1)

    def decode(self, z: Tensor) -> Tensor:
        """Latents ``(B, 3, d)`` → reconstructed pairs ``(B, 3, 2, T, H, W)`` in [0, 1]."""
        return torch.sigmoid(self.decode_logits(z))

    def decode_logits(self, z: Tensor) -> Tensor:
        """Latents ``(B, 3, d)`` → reconstruction logits ``(B, 3, 2, T, H, W)``."""
        b, k, _ = z.shape
        r = self.autoencoder.decode_logits(z.reshape(b * k, -1))
        return r.view(b, k, *r.shape[1:])

    def forward_logits(self, x_noisy: Tensor) -> tuple[Tensor, Tensor]:
        """Noisy observations ``(B, 4, T, H, W)`` → ``(logits (B, 3, 2, T, H, W), latents (B, 3, d))``."""
        z = self.encode(x_noisy)
        return self.decode_logits(z), z

    def forward(self, x_noisy: Tensor) -> tuple[Tensor, Tensor]:
        """Noisy observations ``(B, 4, T, H, W)`` → ``(recon, latents)``.

        ``recon`` is ``(B, 3, 2, T, H, W)`` in [0, 1], ``latents`` ``(B, 3, d)``. The
        reconstruction is compared with :meth:`pairs` of the *clean* observation.
        """
        z = self.encode(x_noisy)
        return self.decode(z), z
