"""Run a policy on the fixed evaluation episodes of each scenario.

Each scenario gets its own vector env of ``envs`` environments reset with
:func:`latentdrive.seeds.eval_reset_seed`; environment slot ``i`` contributes its first
``quota[i]`` episodes (the quotas split ``episodes`` as evenly as possible). Episode
``k`` of slot ``i`` is fixed by the seed whatever the policy, so every policy evaluated
with the same ``episodes``, ``envs`` and seed offset meets the same episodes, which is
what the paired comparison needs. Slots that have finished their quota keep running
until the others finish; their extra episodes are not counted.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from latentdrive.outcome import EpisodeOutcome
from latentdrive.rollout import Policy, rollout
from latentdrive.scenarios import ScenarioSpec
from latentdrive.seeds import eval_reset_seed
from latentdrive.vec import make_vec

__all__ = ["evaluate_policy", "quotas"]


def quotas(episodes: int, envs: int) -> list[int]:
    """Episodes per environment slot: ``episodes`` split as evenly as possible."""
    base, extra = divmod(episodes, envs)
    return [base + (1 if i < extra else 0) for i in range(envs)]


def evaluate_policy(
    make_policy: Callable[[], Policy],
    scenarios: Sequence[str | ScenarioSpec],
    episodes: int,
    *,
    envs: int = 16,
    backend: str = "fast",
    seed_offset: int = 0,
    reset_seed: int | None = None,
    progress: Callable[[int], None] | None = None,
    **overrides: Any,
) -> list[EpisodeOutcome]:
    """The outcomes of ``episodes`` evaluation episodes per scenario.

    Args:
        scenarios: names (presets or spec files) or specs.
        make_policy: builds a fresh policy per scenario (so a policy with its own random
            stream starts it afresh for each scenario).
        envs: environments per scenario (at most ``episodes``). Part of the definition
            of the evaluation set: compare policies evaluated with the same value.
        seed_offset: which evaluation set (:func:`latentdrive.seeds.eval_reset_seed`).
        reset_seed: the first environment's reset seed instead of an evaluation set's, for
            another range (:func:`latentdrive.seeds.validation_reset_seed`).
        progress: called with the number of episodes just finished.
        **overrides: env overrides, as for :func:`latentdrive.make_vec`.
    """
    if episodes < 1:
        raise ValueError(f"episodes must be at least 1, got {episodes}")
    k = max(1, min(envs, episodes))
    want = np.asarray(quotas(episodes, k))
    first = eval_reset_seed(seed_offset) if reset_seed is None else reset_seed
    outcomes: list[EpisodeOutcome] = []
    for name in scenarios:
        vec = make_vec(name, k, backend=backend, **overrides)
        got = np.zeros(k, dtype=np.int64)
        for rec in rollout(vec, make_policy(), seed=first):
            done = 0
            for o in rec.outcomes:
                if got[o.env_index] < want[o.env_index]:
                    outcomes.append(o)
                    got[o.env_index] += 1
                    done += 1
            if progress is not None and done:
                progress(done)
            if (got >= want).all():
                break
        vec.close()
    return outcomes
