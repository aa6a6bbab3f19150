"""How often does a policy run's greedy action match an expert's, on the expert's own states?

Drives ``envs`` environments of one scenario with the expert on validation episodes, and
at every step asks the run's network what it would do. The expert is an imitation run's
own (``imitation.expert``: the planner with the run's ``imitation.planner`` settings, or
the rule driver), so the script measures how well the network fits its expert where the
expert drives; for a DQN run it is the planner at the default settings. Prints the
confusion matrix (rows: the expert's action, columns: the network's), the agreement and
both action distributions. Usage::

    python scripts/agreement.py RUN SCENARIO [--decisions 400] [--envs 8]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from latentdrive.actions import META_ACTIONS, N_ACTIONS
from latentdrive.rl.imitate import expert_policy
from latentdrive.rl.policy import FeatureCache, greedy_actions, load_policy_network
from latentdrive.rollout import PolicyInput, rollout
from latentdrive.scenarios import get_spec
from latentdrive.seeds import validation_reset_seed
from latentdrive.vec import make_vec


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("scenario")
    ap.add_argument("--decisions", type=int, default=400, help="agent-decisions compared (default 400)")
    ap.add_argument("--envs", type=int, default=8)
    args = ap.parse_args()
    net, cfg = load_policy_network(args.run)
    spec = cfg.specs.get(args.scenario) or get_spec(args.scenario)
    vec = make_vec([spec], args.envs, backend="fast", observation=cfg.observation.model_dump(),
                   reward=cfg.reward.model_dump())
    cache = FeatureCache(net, torch.device("cpu"))
    confusion = np.zeros((N_ACTIONS, N_ACTIONS), dtype=np.int64)
    # A DQN run's imitation section holds the defaults: the planner.
    plan = expert_policy(cfg.imitation, cfg.reward)
    expert = cfg.imitation.expert

    def both(inp: PolicyInput) -> np.ndarray:
        """The expert drives; the network is asked about the very same input."""
        planned = plan(inp)
        own = greedy_actions(net, cache, inp)
        np.add.at(confusion, (planned[inp.active], own[inp.active]), 1)
        return planned

    # Validation set 1: neither the evaluation sets nor the set a search scores on.
    for _ in rollout(vec, both, seed=validation_reset_seed(1)):
        if confusion.sum() >= args.decisions:
            break
    vec.close()
    total = confusion.sum()
    print(f"{args.run} on {spec.name}: {total} decisions; rows: the expert's ({expert}) action, columns: the network's")
    width = max(len(a) for a in META_ACTIONS) + 2
    print(" " * width + "".join(f"{a:>{width}}" for a in META_ACTIONS))
    for a, row in zip(META_ACTIONS, confusion, strict=True):
        print(f"{a:<{width}}" + "".join(f"{v:>{width}}" for v in row))
    print(f"agreement {np.trace(confusion) / total:.3f}")
    print(f"{expert:<9}" + " ".join(f"{a} {v:.2f}" for a, v in zip(META_ACTIONS, confusion.sum(1) / total, strict=True)))
    print("network  " + " ".join(f"{a} {v:.2f}" for a, v in zip(META_ACTIONS, confusion.sum(0) / total, strict=True)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
