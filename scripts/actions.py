"""What does a policy run do when it drives? Its greedy actions, Q-value gaps and speeds.

Drives ``envs`` environments of one scenario with the run's own greedy policy on
validation episodes (the set ``scripts/agreement.py`` uses, no evaluation set) and records,
for at least ``decisions`` agent-decisions: the share of each action, each action's mean
Q-value, the gap between the best and the second-best Q-value (median and quartiles, in
reward units, beside the mean best value) and the AVs' speeds. A lane change toward a lane
that does not exist keeps the lane (a no-op), so the lane-change shares bound the lane
changes made from above. Usage::

    python scripts/actions.py RUN SCENARIO [--decisions 800] [--envs 8]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from latentdrive.actions import META_ACTIONS
from latentdrive.rl.policy import FeatureCache, load_policy_network, q_values
from latentdrive.rollout import PolicyInput, rollout
from latentdrive.scenarios import get_spec
from latentdrive.seeds import validation_reset_seed
from latentdrive.vec import make_vec


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run")
    ap.add_argument("scenario")
    ap.add_argument("--decisions", type=int, default=800, help="agent-decisions recorded (default 800)")
    ap.add_argument("--envs", type=int, default=8)
    args = ap.parse_args(argv)
    net, cfg = load_policy_network(args.run)
    spec = cfg.specs.get(args.scenario) or get_spec(args.scenario)
    vec = make_vec([spec], args.envs, backend="fast", observation=cfg.observation.model_dump(),
                   reward=cfg.reward.model_dump())
    cache = FeatureCache(net, torch.device("cpu"))
    qs: list[np.ndarray] = []
    speeds: list[np.ndarray] = []

    def drive(inp: PolicyInput) -> np.ndarray:
        q = q_values(net, cache(inp.obs, inp.active)).numpy()
        qs.append(q[inp.active])
        speeds.append(np.concatenate([s.speed[s.agents[a]] for s, a in zip(inp.scenes, inp.active, strict=True)]))
        return q.argmax(-1).astype(np.int64)

    # Validation set 1, as scripts/agreement.py: neither an evaluation set nor the search's.
    for _ in rollout(vec, drive, seed=validation_reset_seed(1)):
        if sum(len(q) for q in qs) >= args.decisions:
            break
    vec.close()
    q_all, v = np.concatenate(qs), np.concatenate(speeds)
    chosen = q_all.argmax(-1)
    top2 = np.sort(q_all, axis=-1)[:, -2:]
    gap = top2[:, 1] - top2[:, 0]
    print(f"{args.run} on {spec.name}: {len(q_all)} decisions of its own greedy policy")
    print("action share   " + " ".join(f"{a} {np.mean(chosen == k):.3f}" for k, a in enumerate(META_ACTIONS)))
    print("mean Q         " + " ".join(f"{a} {m:.3f}" for a, m in zip(META_ACTIONS, q_all.mean(0), strict=True)))
    lo, med, hi = np.quantile(gap, [0.25, 0.5, 0.75])
    print(f"best - second  median {med:.3f} (quartiles {lo:.3f}, {hi:.3f}); mean best Q {top2[:, 1].mean():.3f}")
    print(f"speed m/s      mean {v.mean():.2f}; 10/50/90% {' / '.join(f'{x:.1f}' for x in np.quantile(v, [0.1, 0.5, 0.9]))}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
