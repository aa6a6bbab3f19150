from typing import Any

import pytest

from latentdrive.rl.config import PolicyTrainConfig

#: A run that takes seconds: small maps, few envs, a small body, evaluation on 4 episodes.
TINY: dict[str, Any] = {
    "scenarios": ["intersection"], "steps": 300, "envs": 4, "segment": 100, "eval_every": 0,
    "eval_episodes": 4, "observation": {"height": 16, "width": 32, "frames": 2},
    "vfan": {"hidden": 32, "channels": [8, 16, 16]},
    "dqn": {"learning_starts": 50, "buffer_size": 1000, "batch_size": 16, "updates_per_transition": 0.25},
}


@pytest.fixture
def tiny():
    def make(**changes: Any) -> PolicyTrainConfig:
        from latentdrive.config import merge_overrides

        return PolicyTrainConfig.model_validate(merge_overrides(TINY, changes))

    return make
