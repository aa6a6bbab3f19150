"""Shared test helpers: small rollouts with fixed action scripts; a directory lock held elsewhere."""

from __future__ import annotations

import contextlib
import hashlib
import os
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from latentdrive.env import make_env


def examples(n: int) -> int:
    """How many examples a property test draws: ``n`` by default, 20x under ``make fuzz``."""
    return n * 20 if os.environ.get("HYPOTHESIS_PROFILE") == "explore" else n


def rollout_digest(scenario: str, seed: int = 0, steps: int = 6, **overrides: object) -> str:
    """Hash of the observations, rewards and scenes of a seeded rollout with a fixed script."""
    env = make_env(scenario, **overrides)
    obs, info = env.reset(seed=seed)
    h = hashlib.sha256(obs.tobytes())
    h.update(info["scene"].position.tobytes())
    script = np.random.default_rng(1234)
    for _ in range(steps):
        obs, _reward, terminated, truncated, info = env.step(script.integers(0, 5, env.spec_.n_av))
        h.update(obs.tobytes())
        h.update(np.asarray(info["agent_rewards"]).tobytes())
        h.update(info["scene"].position.tobytes())
        h.update(info["scene"].speed.tobytes())
        if terminated or truncated:
            break
    return h.hexdigest()


@contextlib.contextmanager
def held_by_another_process(directory: Path, what: str = "collect") -> Iterator[subprocess.Popen[str]]:
    """Hold ``directory``'s run lock from a child process while the block runs."""
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import time
            from latentdrive.runlock import dir_lock
            with dir_lock({str(directory)!r}, {what!r}):
                print("held", flush=True)
                time.sleep(120)
        """)],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        yield holder
    finally:
        holder.kill()
        holder.wait()


def study_numbers(out: Path) -> dict[str, object]:
    """Every number a study's results.json holds, without its timings and environment."""
    import json

    res = json.loads((out / "results.json").read_text())
    res.pop("steps")
    res.pop("meta")
    return dict(res)
