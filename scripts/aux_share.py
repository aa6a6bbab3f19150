"""How much of the reader's step the auxiliary loss takes in a run with ``dqn.aux_scale``.

    python scripts/aux_share.py RUN [--batches 20] [--scale S] [--fit]

Loads a policy run's checkpoint as ``train-policy --resume`` would (its network, target
network, auxiliary head and replay), samples ``--batches`` minibatches of its replay (seed
0, so every call reads the same ones), and prints the means of
:func:`latentdrive.rl.auxiliary.gradient_share`: the Q-loss, the auxiliary term
(``aux_scale`` × the head's squared error), and the norms of their gradients on the reader.
With ``dqn.aux_joint`` the Q-learner's Adam steps their sum, so ``aux / Q`` says how much
of the reader's direction the auxiliary loss sets; without it, the auxiliary loss takes an
Adam step of its own, whatever its norm. ``--scale S`` computes the term as if
``aux_scale`` were ``S`` (its gradient grows in proportion). ``--fit`` also prints how
much of each target the auxiliary head's predictions explain on the same minibatches
(:func:`latentdrive.rl.auxiliary.field_fit`, R² per value and group of neighbour ranks).
Moves and writes nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import torch

from latentdrive.bnn.checkpoint import CheckpointError
from latentdrive.config import ConfigError
from latentdrive.rl.auxiliary import field_fit, fit_table, gradient_share
from latentdrive.rl.learner import restore_with_targets


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--batches", type=int, default=20, help="minibatches averaged (default 20)")
    ap.add_argument("--scale", type=float, default=None, help="aux_scale to compute the term with (default: the run's)")
    ap.add_argument("--fit", action="store_true", help="also print R² of the head's prediction of each target")
    args = ap.parse_args(argv)
    if args.batches < 1:
        raise SystemExit(f"--batches must be at least 1, got {args.batches}")
    try:
        torch.manual_seed(0)
        cfg, net, learner = restore_with_targets(args.run)
        dqn = cfg.dqn if args.scale is None else cfg.dqn.model_copy(update={"aux_scale": args.scale})
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    assert learner.aux is not None
    rng = np.random.default_rng(0)
    rows, preds, wanted = [], [], []
    for _ in range(args.batches):
        batch = learner.replay.sample(rng, dqn.batch_size, torch.device("cpu"))
        assert batch.slots is not None
        targets = torch.from_numpy(learner.aux.store.get(learner.replay.obs_id[batch.slots]))
        rows.append(gradient_share(net, learner.target, learner.aux.head, batch, targets, dqn))
        if args.fit:
            with torch.no_grad():
                preds.append(learner.aux.head(net.summary(batch.obs)).float().numpy())
            wanted.append(targets.numpy())
    r = np.asarray(rows, dtype=np.float64)
    print(f"{args.run}: {learner.transitions} agent-transitions, {learner.updates} updates; aux_scale {dqn.aux_scale:g}"
          f"{' (joint)' if cfg.dqn.aux_joint else ''}; means over {args.batches} minibatches of {dqn.batch_size}")
    print(f"Q-loss {r[:, 0].mean():.4f}  auxiliary term {r[:, 1].mean():.4f}  reader gradient norm: "
          f"Q {r[:, 2].mean():.4f}, auxiliary {r[:, 3].mean():.4f}, aux / Q {np.mean(r[:, 3] / r[:, 2]):.2f}")
    if args.fit:
        fit = field_fit(np.concatenate(preds), np.concatenate(wanted), learner.aux.k)
        print(f"R² of the auxiliary head's predictions: speed {fit['speed']:.2f}, lane speed {fit['lane speed']:.2f}")
        print("\n".join(fit_table(fit)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
