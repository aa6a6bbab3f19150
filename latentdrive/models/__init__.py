"""Neural network modules (``nn.Module`` only; training code lives elsewhere)."""

from latentdrive.models.bottleneck import (
    PAIR_CHANNELS,
    PAIR_NAMES,
    BottleneckConfig,
    BottleneckNetwork,
    PairAutoencoder,
    channel_pairs,
)

__all__ = [
    "PAIR_CHANNELS",
    "PAIR_NAMES",
    "BottleneckConfig",
    "BottleneckNetwork",
    "PairAutoencoder",
    "channel_pairs",
]
