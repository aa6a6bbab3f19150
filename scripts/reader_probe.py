"""How well a map reader can be taught to see the vehicles, in minutes instead of a training run.

    python scripts/reader_probe.py RUN [--readout query|queries|self-attention] [--stem conv|patch]
                                       [--steps 3000] [--held-out 1024] [--block 2000] [--seed 0]

Takes the maps and the auxiliary targets (``dqn.aux_scale``: the AV's speeds and its
nearest vehicles in view, exact) that a finished run's replay holds, fits a fresh attention
reader (:class:`~latentdrive.models.attention.MapAttentionBody`, the run's width and
heads) and an auxiliary head to them by the auxiliary loss alone (no Q-learning; Adam at the
run's ``dqn.lr``, its batch size), and prints R² of the head's predictions
(:func:`latentdrive.rl.auxiliary.field_fit`) on observations it did not train on: the
replay's observation ids in blocks of ``--block`` (2,000), every tenth block held out
(neighbouring ids are neighbouring steps of the same episodes). The readout is the reader's own (``query``:
the observer's token queries every token once), four queries (``queries``: the observer's
query plus four learned offsets, their four answers beside it), or one self-attention
layer over the tokens before the query (``self-attention``). A probe for comparing readers
of the same maps, not a driving result: the reader is trained on sight alone. Moves and
writes nothing.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from latentdrive.bnn.checkpoint import CheckpointError
from latentdrive.config import ConfigError
from latentdrive.models.attention import MapAttentionBody
from latentdrive.rl.auxiliary import aux_head, field_fit, fit_table
from latentdrive.rl.learner import restore_with_targets

READOUTS = ("query", "queries", "self-attention")


class Probe(nn.Module):
    """A reader and its readout: maps ``(B, C, T, H, W)`` → summaries ``(B, size)``."""

    def __init__(self, body: MapAttentionBody, readout: str, width: int, heads: int) -> None:
        super().__init__()
        self.body, self.readout = body, readout
        self.me = body.me[0] * body.cols + body.me[1]
        self.size = 2 * width
        if readout == "queries":
            self.offsets = nn.Parameter(0.1 * torch.randn(4, width))
            self.size = 5 * width
        elif readout == "self-attention":
            self.mix = nn.TransformerEncoderLayer(width, heads, dim_feedforward=2 * width, dropout=0.0, batch_first=True)

    def forward(self, x: Tensor) -> Tensor:
        tokens = self.body.tokens(x)
        if self.readout == "self-attention":
            tokens = self.mix(tokens)
        if self.readout != "queries":
            return self.body.summary(tokens, self.me)
        query = self.body.query(tokens[:, self.me])
        answers, _ = self.body.attend(query[:, None] + self.offsets[None], tokens, tokens, need_weights=False)
        return torch.cat([query, answers.flatten(1)], dim=1)


def split(ids: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Observation ids → (training ids, held-out ids): every tenth block of ``block`` ids held out."""
    held = (ids // block) % 10 == 0
    return ids[~held], ids[held]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("--readout", choices=READOUTS, default="query")
    ap.add_argument("--stem", choices=("conv", "patch"), default="conv")
    ap.add_argument("--steps", type=int, default=3000, help="Adam steps (default 3000)")
    ap.add_argument("--held-out", type=int, default=1024, help="held-out observations scored (default 1024)")
    ap.add_argument("--block", type=int, default=2000, help="observation ids per block of the split (default 2000)")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args(argv)
    if min(args.steps, args.held_out, args.block) < 1:
        raise SystemExit("--steps, --held-out and --block must be at least 1")
    try:
        cfg, _, learner = restore_with_targets(args.run)
    except (ConfigError, CheckpointError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    assert learner.aux is not None
    train_ids, held_ids = split(np.unique(learner.replay.obs_id[: len(learner.replay)]), args.block)
    if not len(train_ids) or not len(held_ids):
        print(f"error: {args.run}: its replay is too small to hold observations out in blocks of {args.block}",
              file=sys.stderr)
        return 2
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    held_ids = rng.choice(held_ids, min(args.held_out, len(held_ids)), replace=False)
    maps, targets = learner.replay.store, learner.aux.store
    v = cfg.vfan
    body = MapAttentionBody(tuple(maps.get(train_ids[:1]).shape[1:]), cfg.observation.resolution,
                            cfg.observation.behind, width=v.attention_width, heads=v.attention_heads,
                            hidden=v.hidden, stem=args.stem)
    probe = Probe(body, args.readout, v.attention_width, v.attention_heads)
    head = aux_head(probe.size, v.hidden, learner.aux.k)
    # The Q head is not part of what sees.
    params = [p for name, p in probe.named_parameters() if not name.startswith("body.head.")] + list(head.parameters())
    optimizer = torch.optim.Adam(params, lr=cfg.dqn.lr)
    start = time.perf_counter()
    for _ in range(args.steps):
        ids = rng.choice(train_ids, cfg.dqn.batch_size)
        loss = F.mse_loss(head(probe(torch.from_numpy(maps.get(ids)))), torch.from_numpy(targets.get(ids)))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
    seconds = time.perf_counter() - start
    with torch.no_grad():
        pred = np.concatenate([head(probe(torch.from_numpy(maps.get(held_ids[i: i + 64])))).numpy()
                               for i in range(0, len(held_ids), 64)])
    fit = field_fit(pred, targets.get(held_ids), learner.aux.k)
    print(f"{args.run}: readout {args.readout}, stem {args.stem}; {args.steps} steps of {cfg.dqn.batch_size} "
          f"in {seconds:.0f} s ({sum(p.numel() for p in params):,} parameters); R² on {len(held_ids)} held-out "
          f"observations: speed {fit['speed']:.2f}, lane speed {fit['lane speed']:.2f}")
    print("\n".join(fit_table(fit)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
