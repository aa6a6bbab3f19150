"""Observation datasets for the bottleneck network: behaviour policies, collection, loading.

- :mod:`~latentdrive.data.policies`: behaviour policies that drive the AVs while collecting.
- :mod:`~latentdrive.data.collect`: :func:`collect` rolls out episodes into sharded,
  resumable datasets of (noisy, clean) VelocityMap pairs.
- :mod:`~latentdrive.data.dataset`: :class:`ShardDataset` checks a dataset and streams
  shuffled, scenario-mixed :class:`~latentdrive.bnn.batch.BNNBatch` es.
- :mod:`~latentdrive.data.shards`: the on-disk format.

Names are imported from their submodules on first use, so that importing this package
(e.g. for the CLI's argument parser) loads neither torch nor the simulator.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from latentdrive.data.collect import CollectConfig, CollectSummary, collect
    from latentdrive.data.dataset import ShardDataset
    from latentdrive.data.policies import episode_policy, random_policy, rule_policy
    from latentdrive.data.shards import QUANT_MAX_ERROR, DatasetError, dequantize, quantize

__all__ = [
    "QUANT_MAX_ERROR",
    "CollectConfig",
    "CollectSummary",
    "DatasetError",
    "ShardDataset",
    "collect",
    "dequantize",
    "episode_policy",
    "quantize",
    "random_policy",
    "rule_policy",
]

_WHERE = {
    "CollectConfig": "collect", "CollectSummary": "collect", "collect": "collect",
    "ShardDataset": "dataset",
    "episode_policy": "policies", "random_policy": "policies", "rule_policy": "policies",
    "QUANT_MAX_ERROR": "shards", "DatasetError": "shards", "dequantize": "shards", "quantize": "shards",
}


def __getattr__(name: str) -> Any:
    module = _WHERE.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)
