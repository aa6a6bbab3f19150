"""Can the Q-learner drive when it reads the vehicles as a set? Double DQN over exact states.

The map-reading policies of ``train-policy`` fail about as often as the rule driver at the
roundabout, the intersection and on the highway. A copy of the planner that reads exact
states through ego-attention (``scripts/state_copy.py --arch attention``) generalized where
a copy through the map or an MLP did not. This script asks the same of reward learning: the
project's multi-agent double DQN (:func:`latentdrive.rl.dqn.update`, its replay and n-step
window) trained on the same scenarios, budget and reward, with the network reading, instead
of the VelocityMap, the exact-state vector of :func:`latentdrive.observe.state.state_features`
(the AV, its route unless ``--no-route``, and its ``--neighbours`` nearest vehicles within
``--radius`` metres) through :class:`EgoAttention` (``--arch attention``, the default) or an
MLP (``--arch mlp``).

It is a diagnostic reference, not the paper's method: the state vector has no raster and no
sensor noise, and holds the AV's route, which the paper's map does not. If this learner beats
the rule driver where the map's does not, the map's reader (or the map) is what holds the
paper's policies back; if it fails as they do, the learner, the reward or the budget does.

Training episodes come from the training seed range (one continuous run, no segments);
every ``--eval-every`` agent-transitions the greedy policy plays ``--eval-episodes`` episodes
per scenario of validation set 0 (the range ``latentdrive tune`` scores on); at the end it and
the rule driver play the test set, the first ``--episodes`` evaluation episodes per scenario
of ``latentdrive evaluate --envs 16``, and are compared pairwise (McNemar). Usage::

    python scripts/state_dqn.py [--scenarios roundabout,intersection,merge,exit,highway]
        [--steps 100000] [--seed 0] [--arch attention|mlp] [--no-route] [--no-pose] [--no-time] [--view-box]
        [--set dqn.KEY=VALUE ...] [--set reward.KEY=VALUE ...] [--out FILE.csv]

``--set`` takes :class:`~latentdrive.rl.dqn.DQNConfig` and
:class:`~latentdrive.scenarios.spec.RewardConfig` fields, as ``train-policy --set`` does; the
defaults are theirs. ``augment_shift``, ``explore_rule``, ``dueling`` and the prioritized
replay's settings are refused (they act on maps, the rule driver's choice, the VFAN's head,
or a replay this script does not build).
"""

from __future__ import annotations

import argparse
import copy
import csv
import runpy
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn
from tqdm import tqdm

from latentdrive.config import ConfigError, parse_override_args, validate
from latentdrive.evaluate.policies import reference_policy
from latentdrive.evaluate.report import compare, format_compare, format_table, policy_report
from latentdrive.evaluate.run import evaluate_policy
from latentdrive.observe.state import PER_NEIGHBOUR, state_size
from latentdrive.rl.dqn import DQNConfig, epsilon, target_step, update, updates_owed
from latentdrive.rl.nstep import NStepWindow
from latentdrive.rl.replay import LatentStore, Replay
from latentdrive.rollout import Policy, PolicyInput, rollout
from latentdrive.scenarios import get_spec
from latentdrive.scenarios.spec import RewardConfig
from latentdrive.seeds import train_reset_seed, validation_reset_seed
from latentdrive.vec import make_vec

_COPY = runpy.run_path(str(Path(__file__).resolve().parent / "state_copy.py"), run_name="state_copy")
EgoAttention: type[nn.Module] = _COPY["EgoAttention"]
batch_features: Callable[..., NDArray[np.float32]] = _COPY["batch_features"]
mlp: Callable[[int, int], nn.Module] = _COPY["mlp"]

#: The map the env renders is not read here: the smallest one keeps rendering cheap.
TINY_MAP = {"height": 4, "width": 4, "frames": 1, "behind": 0.0}
REFUSED = ("augment_shift", "explore_rule", "dueling", "prioritized", "priority_alpha", "priority_beta",
           "priority_eps")
#: The AV's own features that place it in the world (cos and sin of its heading, world x and
#: y, the share of the episode gone): ``--no-pose`` zeroes them.
POSE = slice(2, 7)
#: The share of the episode gone, within :data:`POSE`: ``--no-time`` zeroes it alone.
TIME = 6


#: The default VelocityMap's view in the AV's frame, metres: behind, ahead, to each side.
MAP_VIEW = (32.0, 64.0, 24.0)


def features(inp: PolicyInput, specs: list[Any], k: int, radius: float, route: bool, pose: bool,
             view_box: tuple[float, float, float] | None = None, show_time: bool = True) -> NDArray[np.float32]:
    """:func:`batch_features` ``(num_envs, n_av, F)``; without ``pose``, :data:`POSE` zeroed,
    without ``show_time``, :data:`TIME`;
    with ``view_box`` (metres behind, ahead, to each side), the neighbours outside it made
    absent (zero rows)."""
    x = batch_features(inp, specs, k, radius, route)
    if not pose:
        x[..., POSE] = 0.0
    if not show_time:
        x[..., TIME] = 0.0
    if view_box is not None:
        start = x.shape[-1] - k * PER_NEIGHBOUR
        rows = x[..., start:].reshape(*x.shape[:2], k, PER_NEIGHBOUR).copy()
        ahead, right = rows[..., 0] * 50.0, rows[..., 1] * 50.0
        behind, front, side = view_box
        rows[(ahead < -behind) | (ahead > front) | (np.abs(right) > side)] = 0.0
        x[..., start:] = rows.reshape(*x.shape[:2], -1)
    return x


class StatePolicy:
    """ε-greedy (``eps() > 0``) or greedy actions of ``net`` over :func:`batch_features`;
    keeps the latest step's features ``(num_envs, n_av, F)`` in :attr:`latest`."""

    def __init__(self, net: nn.Module, k: int, radius: float, route: bool,
                 rng: np.random.Generator | None = None, eps: Callable[[], float] = lambda: 0.0,
                 pose: bool = True, view_box: tuple[float, float, float] | None = None, show_time: bool = True) -> None:
        self.net, self.k, self.radius, self.route, self.rng, self.eps = net, k, radius, route, rng, eps
        self.pose, self.view_box, self.show_time = pose, view_box, show_time
        self.latest: NDArray[np.float32] | None = None

    def __call__(self, inp: PolicyInput) -> NDArray[np.int64]:
        specs = inp.simulator.specs if inp.simulator is not None else [get_spec(n) for n in inp.scenarios]
        x = features(inp, list(specs), self.k, self.radius, self.route, self.pose, self.view_box, self.show_time)
        self.latest = x
        with torch.no_grad():
            q = self.net(torch.from_numpy(x.reshape(-1, x.shape[-1])))
        act = q.argmax(-1).numpy().reshape(x.shape[:2]).astype(np.int64)
        e = self.eps()
        if self.rng is not None and e > 0:
            explore = self.rng.random(act.shape) < e
            act = np.where(explore, self.rng.integers(0, q.shape[-1], size=act.shape), act)
        return act


def evaluate(net: nn.Module, args: argparse.Namespace, scenarios: list[str], episodes: int,
             reset_seed: int | None = None) -> list[Any]:
    def make() -> Policy:
        return StatePolicy(net, args.neighbours, args.radius, not args.no_route, pose=not args.no_pose,
                           view_box=args.view_box, show_time=not args.no_time)

    net.eval()
    try:
        return evaluate_policy(make, scenarios, episodes, envs=16, reset_seed=reset_seed, observation=TINY_MAP)
    finally:
        net.train()


def train(args: argparse.Namespace, scenarios: list[str], cfg: DQNConfig,
          reward: RewardConfig) -> tuple[nn.Module, Replay]:
    """The trained network and its replay."""
    # Seeding: the weights (torch), exploration and replay sampling (numpy), and the
    # training episodes (the vector env's reset seed) all follow --seed.
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(np.random.SeedSequence([args.seed, 0x51]))
    route = not args.no_route
    n_in = state_size(args.neighbours, route)
    net = (EgoAttention(state_size(0, route), PER_NEIGHBOUR, args.neighbours, args.hidden)
           if args.arch == "attention" else mlp(n_in, args.hidden))
    target = copy.deepcopy(net).requires_grad_(False)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, eps=cfg.adam_eps)
    print(f"state DQN: {n_in} inputs, {sum(p.numel() for p in net.parameters()):,} parameters, {args.arch}")
    vec = make_vec(scenarios, args.envs, backend="fast", observation=TINY_MAP, reward=reward.model_dump())
    slots = (args.envs, vec.n_av)
    # Every step stores at most one next observation per agent and, for new episodes, one
    # first observation per agent; the replay's oldest entry reaches n-1 steps further back.
    replay = Replay(cfg.buffer_size, LatentStore(2 * cfg.buffer_size + (2 * cfg.n_step + 4) * args.envs * vec.n_av,
                                                 (n_in,)))
    window = NStepWindow(cfg.n_step, cfg.gamma, slots)
    transitions = updates = 0
    policy = StatePolicy(net, args.neighbours, args.radius, route, rng, lambda: epsilon(cfg, transitions, args.steps),
                         pose=not args.no_pose, view_box=args.view_box, show_time=not args.no_time)
    cur = np.full(slots, -1, dtype=np.int64)
    fresh = np.ones(args.envs, dtype=bool)  # environments whose current observation is not stored yet

    def act(inp: PolicyInput) -> NDArray[np.int64]:
        actions = policy(inp)
        assert policy.latest is not None
        for e in np.flatnonzero(fresh):
            cur[e] = replay.store.add(policy.latest[e], np.full(vec.n_av, -1, dtype=np.int64))
        fresh[:] = False
        return actions

    writer = None
    if args.out:
        handle = open(args.out, "w", newline="")
        writer = csv.writer(handle)
        writer.writerow(["transitions", "seconds", "validation_failure"])
    t0 = time.perf_counter()
    next_eval = args.eval_every or args.steps + 1
    bar = tqdm(total=args.steps, desc="agent-transitions", unit="tr", mininterval=15)
    loss = float("nan")
    specs = list(vec.simulator.specs)
    names = np.asarray([s.name for s in specs], dtype=object)
    for rec in rollout(vec, act, seed=train_reset_seed(args.seed, 0)):
        ag = rec.agents
        ei, ai = np.nonzero(ag.acting)
        # Where each transition leads: the Scene the step led to (the ended episode's last
        # where it ended); exact states carry no noise, so this is what the policy reads there.
        after = features(PolicyInput(rec.obs_after, rec.scenes, ag.active, names, vec.simulator), specs,
                         args.neighbours, args.radius, route, not args.no_pose, args.view_box, not args.no_time)
        next_ids = replay.store.add(after[ei, ai], cur[ei, ai])
        # Terminated (crash, mission done) does not bootstrap; cut off (a partner crashed,
        # time ran out) does: the n-step window keeps them apart (rl.nstep).
        out = window.push(ei, ai, cur[ei, ai], rec.actions[ei, ai], ag.reward[ei, ai], next_ids,
                          ag.terminated[ei, ai], ag.truncated[ei, ai])
        replay.add(out.obs_id, out.action, out.reward, out.next_id, out.terminated, out.steps)
        cur[ei, ai] = next_ids
        fresh[rec.ended] = True
        transitions += len(ei)
        bar.update(len(ei))
        for _ in range(max(0, updates_owed(cfg, transitions) - updates)):
            stats = update(net, target, opt, replay.sample(rng, cfg.batch_size), cfg)
            loss = stats.loss
            updates += 1
            target_step(target, net, cfg, updates)
        bar.set_postfix(loss=f"{loss:.3f}", eps=f"{epsilon(cfg, transitions, args.steps):.2f}", refresh=False)
        if transitions >= next_eval or transitions >= args.steps:
            rate = float(np.mean([o.failed for o in evaluate(net, args, scenarios, args.eval_episodes,
                                                             validation_reset_seed(0))]))
            seconds = time.perf_counter() - t0
            tqdm.write(f"{transitions} agent-transitions, {seconds:.0f} s: validation failure {rate:.3f}")
            if writer is not None:
                writer.writerow([transitions, f"{seconds:.1f}", f"{rate:.4f}"])
                handle.flush()
            next_eval += args.eval_every or args.steps + 1
        if transitions >= args.steps:
            break
    bar.close()
    vec.close()
    if writer is not None:
        handle.close()
    print(f"trained on {transitions} agent-transitions, {updates} updates, {time.perf_counter() - t0:.0f} s")
    return net, replay


def configs(items: list[str]) -> tuple[DQNConfig, RewardConfig]:
    parsed = parse_override_args(items)
    bad = sorted(k for k in parsed if k.partition(".")[0] not in ("dqn", "reward") or not k.partition(".")[2])
    if bad:
        raise ConfigError(f"--set {bad[0]}: expected dqn.KEY=VALUE or reward.KEY=VALUE")
    refused = sorted(k for k in parsed if k.removeprefix("dqn.") in REFUSED)
    if refused:
        raise ConfigError(f"--set {refused[0]}: not used by a policy over exact states")
    part = {p: {k.partition(".")[2]: v for k, v in parsed.items() if k.startswith(p + ".")} for p in ("dqn", "reward")}
    return validate(DQNConfig, part["dqn"], prefix="dqn."), validate(RewardConfig, part["reward"], prefix="reward.")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default="roundabout,intersection,merge,exit,highway")
    ap.add_argument("--steps", type=int, default=100_000, help="agent-transitions (default 100000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--envs", type=int, default=16)
    ap.add_argument("--neighbours", type=int, default=12)
    ap.add_argument("--radius", type=float, default=80.0, help="metres")
    ap.add_argument("--no-route", action="store_true", help="leave the AV's planned route out of its features")
    ap.add_argument("--no-pose", action="store_true",
                    help="zero the AV's world heading and position and the share of the episode gone, which "
                         "an ego-centred map does not show")
    ap.add_argument("--no-time", action="store_true", help="zero only the share of the episode gone")
    ap.add_argument("--view-box", nargs="?", const=",".join(f"{v:g}" for v in MAP_VIEW), metavar="BEHIND,AHEAD,SIDE",
                    help="see only the neighbours inside this box, metres (alone: the default map's view, "
                         "32 m behind, 64 m ahead, 24 m to each side)")
    ap.add_argument("--arch", choices=("attention", "mlp"), default="attention")
    ap.add_argument("--hidden", type=int, default=256)
    ap.add_argument("--eval-every", type=int, default=25_000, help="agent-transitions between validations (0: at the end only)")
    ap.add_argument("--eval-episodes", type=int, default=40, help="validation episodes per scenario (default 40)")
    ap.add_argument("--episodes", type=int, default=200, help="test episodes per scenario (default 200)")
    ap.add_argument("--out", help="write the validation curve to this CSV file")
    ap.add_argument("-s", "--set", action="append", default=[], metavar="dqn.KEY=VALUE")
    args = ap.parse_args()
    for name in ("steps", "envs", "neighbours", "hidden", "eval_episodes", "episodes"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be at least 1")
    if args.eval_every < 0:
        ap.error("--eval-every must be at least 0")
    if args.view_box is not None:
        try:
            box = tuple(float(v) for v in args.view_box.split(","))
        except ValueError:
            box = ()
        if len(box) != 3 or min(box) < 0:
            ap.error(f"--view-box takes three distances in metres, BEHIND,AHEAD,SIDE, got {args.view_box!r}")
        args.view_box = box
    try:
        cfg, reward = configs(args.set)
    except ConfigError as err:
        ap.error(str(err))
    torch.set_num_threads(1)
    scenarios = args.scenarios.split(",")
    net, _ = train(args, scenarios, cfg, reward)
    net.eval()
    outcomes = {"state DQN": evaluate(net, args, scenarios, args.episodes),
                "rule": evaluate_policy(reference_policy("rule"), scenarios, args.episodes, envs=16)}
    print(f"test set: the first {args.episodes} evaluation episodes per scenario (envs 16)")
    print(format_table({name: policy_report(o) for name, o in outcomes.items()}))
    print(format_compare(compare(outcomes["state DQN"], outcomes["rule"]), ("state DQN", "rule")))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
