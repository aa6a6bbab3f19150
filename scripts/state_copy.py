"""Can a policy that reads the vehicles' exact states copy the planner where a map reader cannot?

The imitation reference (``train-policy --learner dagger``) copies the lookahead planner
through the VelocityMap and fails about as often as the rule driver at the roundabout and
the intersection. This script asks whether the map or the expert is what limits it: it runs
the same DAgger scheme (the planner labels every acting AV's decision; the AV plays the
planner's action with probability β, falling from 1 to 0 over the first half of the budget,
else the network's; class-weighted cross-entropy on the aggregated labels) with a small MLP
that reads, instead of the map, a vector of exact states (:func:`latentdrive.observe.state.state_features`):

- the AV itself: speed and lane speed, heading, world position, the share of the episode's
  time gone, and, unless ``--no-route``, the lane-graph edges of its planned route
  (``Scene.route``: what the planner knows of where the AV is going);
- the ``--neighbours`` nearest other vehicles within ``--radius`` metres: position and
  velocity in the AV's frame, relative heading, AV or human, crashed.

With ``--target values`` the network learns, instead of the planner's choice, what the
planner's lookahead scored each first action at against its choice (its
:class:`~latentdrive.evaluate.planner.Plan` values, divided by ``VALUE_SCALE``; Huber
regression), and drives by the best: a cost-sensitive copy (Ross and Bagnell's AggreVaTe,
2014) that knows which of its mistakes cost a crash and which cost nothing.

With ``--privileged`` each neighbour also carries what the simulator's driver holds and
nothing observable shows (:func:`hidden_features`: its target speed, whether it is yielding
at a regulated junction, whether it is steering to another lane, its lane-change timer and
its IDM exponent), read from the fast backend's own state: a diagnostic of whether that
hidden state is what a copy lacks, never a policy's input.

Neither the map nor this vector holds where each human driver will turn or its exact
driving parameters, which the planner simulates. If this copy comes near the planner, the
map's picture (its raster, noise, reach) is what the map copy lacks; if it fails as the map
copy does, the planner's decisions rest on what neither reads.

Training episodes come from the training seed range; the copy, the rule driver and (with
``--compare RUN``) a map-reading run are then played on the first evaluation set, the
episodes of ``latentdrive evaluate --episodes N --envs 16``, and compared pairwise
(McNemar). Usage::

    python scripts/state_copy.py [--scenarios roundabout,intersection] [--decisions 20000]
        [--seed 0] [--episodes 200] [--compare RUN] [--no-route] [--target labels|values]
        [--privileged] [--audit] [--holdout F] [--ensemble K] [--arch mlp|attention]
        [--set planner.KEY=VALUE ...]

With ``--audit`` the planner also labels and scores every state each policy acts in on the
test episodes, so the copy's agreement where it drives stands beside that on its training
decisions (and the rule driver's and the map run's beside both), with the share of choices
the planner scores below its own and by about a crash's cost (severe).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F
from numpy.typing import NDArray
from torch import nn
from tqdm import tqdm

from latentdrive.actions import N_ACTIONS
from latentdrive.config import ConfigError
from latentdrive.evaluate.planner import (
    Plan,
    PlannerConfig,
    planner_config_from_args,
    planner_policy,
)
from latentdrive.evaluate.policies import reference_policy
from latentdrive.evaluate.report import compare, format_compare, format_table, policy_report
from latentdrive.evaluate.run import evaluate_policy, quotas
from latentdrive.observe.state import PER_NEIGHBOUR, nearest, state_features, state_size
from latentdrive.rl.imitate import (
    ExpertLabels,
    ImitationConfig,
    dagger_policy,
    expert_share,
    label_weights,
)
from latentdrive.rl.policy import greedy_policy, load_policy_network
from latentdrive.rollout import Policy, PolicyInput, rollout
from latentdrive.scenarios import ScenarioSpec, get_spec
from latentdrive.seeds import train_reset_seed
from latentdrive.sim.fast import FastBatch
from latentdrive.sim.fast.state import DELTA, LANE, TARGET, TARGET_SPEED, TIMER, YIELDING
from latentdrive.vec import make_vec

#: Hidden driver values per neighbour (:func:`hidden_features`).
PRIVILEGED = 5
#: Planning returns are divided by this before regression (a crash costs 20 of them).
VALUE_SCALE = 10.0


def hidden_features(inp: PolicyInput, env: int, agent: int, k: int, radius: float) -> NDArray[np.float32]:
    """What the simulator's drivers carry and no observation shows, for the neighbours of
    :func:`~latentdrive.observe.state.state_features` in its order: target speed / 20,
    yielding at a regulated junction, steering to another lane, seconds since the last
    lane-change decision / 5, IDM exponent δ − 4. ``(k * PRIVILEGED,)``. Reads the fast
    backend's private state: a diagnostic, never a policy's input."""
    sim = inp.simulator
    assert isinstance(sim, FastBatch)
    g, r = sim._where[env]
    st = sim._groups[g].state
    scene = inp.scenes[env]
    near = nearest(scene, int(scene.agents[agent]), k, radius)
    rows = np.zeros((k, PRIVILEGED))
    rows[: near.size] = np.stack([
        st.f[TARGET_SPEED, r, near] / 20.0, st.flag[YIELDING, r, near], st.i[TARGET, r, near] != st.i[LANE, r, near],
        st.f[TIMER, r, near] / 5.0, st.f[DELTA, r, near] - 4.0], axis=1)
    return rows.reshape(-1).astype(np.float32)


def batch_features(inp: PolicyInput, specs: list[ScenarioSpec], k: int, radius: float, route: bool,
                   privileged: bool = False) -> NDArray[np.float32]:
    """:func:`~latentdrive.observe.state.state_features` of every env and agent of ``inp``
    (and, with ``privileged``, :func:`hidden_features`): ``(num_envs, n_av, F)``."""
    def one(e: int, a: int) -> NDArray[np.float32]:
        x = state_features(inp.scenes[e], a, specs[e].duration, k, radius, route)
        return np.concatenate([x, hidden_features(inp, e, a, k, radius)]) if privileged else x

    return np.stack([np.stack([one(e, a) for a in range(scene.n_agents)]) for e, scene in enumerate(inp.scenes)])


def mlp(n_in: int, hidden: int) -> nn.Module:
    return nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                         nn.Linear(hidden, N_ACTIONS))


class EgoAttention(nn.Module):
    """Ego-attention over the neighbours (``--arch attention``; Leurent and Mercat, "Social
    attention for autonomous decision-making in dense traffic", 2019): the AV's own features
    and each neighbour's row (with ``--privileged``, its hidden driver state beside it) are
    embedded by layers shared across vehicles; the AV's embedding queries every present
    vehicle's, its own included, with ``heads`` heads; the logits come from the AV's
    embedding and what it attended to. Unlike the MLP, which gives each rank of the
    nearest-first order its own weights, it reads the neighbours as a set."""

    def __init__(self, ego: int, per: int, k: int, hidden: int, width: int = 64, heads: int = 4) -> None:
        super().__init__()
        self.ego, self.per, self.k = ego, per, k
        self.embed_ego = nn.Sequential(nn.Linear(ego, width), nn.ReLU(), nn.Linear(width, width))
        self.embed_other = nn.Sequential(nn.Linear(per, width), nn.ReLU(), nn.Linear(width, width))
        self.attend = nn.MultiheadAttention(width, heads, batch_first=True)
        self.head = nn.Sequential(nn.Linear(2 * width, hidden), nn.ReLU(), nn.Linear(hidden, N_ACTIONS))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, seen = x.shape[0], self.ego + self.k * PER_NEIGHBOUR
        others = x[:, self.ego: seen].reshape(b, self.k, PER_NEIGHBOUR)
        if self.per > PER_NEIGHBOUR:  # --privileged: the hidden rows follow the observed ones
            others = torch.cat([others, x[:, seen:].reshape(b, self.k, self.per - PER_NEIGHBOUR)], dim=2)
        # A row's last observed feature is 1 for a vehicle and 0 for padding.
        absent = torch.cat([torch.zeros(b, 1, dtype=torch.bool, device=x.device), others[:, :, PER_NEIGHBOUR - 1] < 0.5],
                           dim=1)
        me = self.embed_ego(x[:, : self.ego])
        tokens = torch.cat([me[:, None], self.embed_other(others)], dim=1)
        mixed, _ = self.attend(me[:, None], tokens, tokens, key_padding_mask=absent, need_weights=False)
        return self.head(torch.cat([me, mixed[:, 0]], dim=1))


class Ensemble(nn.Module):
    """``k`` networks of different initial weights trained on the same batches
    (``--ensemble``); the policy reads the mean of their outputs."""

    def __init__(self, make: Callable[[], nn.Module], k: int) -> None:
        super().__init__()
        self.nets = nn.ModuleList(make() for _ in range(k))

    def members(self, x: torch.Tensor) -> torch.Tensor:
        """``(k, B, N_ACTIONS)`` each member's output for ``x`` ``(B, F)``."""
        return torch.stack([net(x) for net in self.nets])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.members(x).mean(0)


class StateCopy:
    """The MLP's greedy policy over :func:`batch_features`; keeps the latest step's features."""

    def __init__(self, net: nn.Module, k: int, radius: float, route: bool, privileged: bool = False) -> None:
        self.net, self.k, self.radius, self.route, self.privileged = net, k, radius, route, privileged
        self.latest: NDArray[np.float32] | None = None

    def __call__(self, inp: PolicyInput) -> NDArray[np.int64]:
        specs = inp.simulator.specs if inp.simulator is not None else [get_spec(n) for n in inp.scenarios]
        x = batch_features(inp, list(specs), self.k, self.radius, self.route, self.privileged)
        self.latest = x
        with torch.no_grad():
            logits = self.net(torch.from_numpy(x.reshape(-1, x.shape[-1])))
        return logits.argmax(-1).numpy().reshape(x.shape[:2]).astype(np.int64)


def audit_line(where: str, chosen: NDArray[np.int64], expert: NDArray[np.int64],
               values: NDArray[np.float64], severe_gap: float) -> str:
    """How a policy's ``chosen`` actions ``(N,)`` stand against the planner's choices
    ``expert`` ``(N,)`` and its values ``(N, N_ACTIONS)`` of each first action on the same
    states: exact agreement, choices the planner scores below its best, and those by at least
    ``severe_gap`` (about a crash's cost), of all decisions and of the critical ones, where
    some action costs that much. Each value assumes the other AVs follow the planner's plans,
    not what the judged policy made them do."""
    best = values.max(axis=1)
    gap = best - values[np.arange(chosen.size), chosen]
    critical = best - values.min(axis=1) >= severe_gap
    severe = gap >= severe_gap
    return (f"{where}: {chosen.size} decisions; agreement {float((chosen == expert).mean()):.3f}; "
            f"choices the planner scores below its best {float((gap > 1e-9).mean()):.3f}; "
            f"by at least {severe_gap:g} (about a crash's cost) {float(severe.mean()):.4f} of all, "
            f"{float(severe[critical].mean()) if critical.any() else float('nan'):.3f} of the "
            f"{float(critical.mean()):.3f} where some action costs that much")


def severe_gap(cfg: PlannerConfig) -> float:
    """Half the planner's crash penalty: what a crash a few steps into its horizon costs
    after discounting, the gap in planning return that :func:`audit_line` calls severe."""
    return -cfg.crash_penalty / 2


class Audit:
    """Asks the planner (settings ``cfg``) about every decision a policy takes on its
    ``episodes`` test episodes per scenario (``--audit``): agreement with it, and the choices
    it scores below its own, where the policy drives."""

    def __init__(self, cfg: PlannerConfig, episodes: int) -> None:
        self.cfg, self.episodes = cfg, episodes
        self.chosen: list[NDArray[np.int64]] = []
        self.expert: list[NDArray[np.int64]] = []
        self.values: list[NDArray[np.float64]] = []

    def factory(self, make: Callable[[], Policy]) -> Callable[[], Policy]:
        """``make`` (a policy factory, as :func:`evaluate_policy` takes, called once per
        scenario) with every decision of its policies judged. The evaluation steps every
        environment until the last has played its quota and drops the outcomes beyond it;
        the decisions of those extra episodes are dropped here too."""
        def audited_factory() -> Policy:
            policy = make()
            plans: list[Plan] = []
            expert = planner_policy(self.cfg, record=plans.append)
            # Per environment: episodes begun, episodes counted, last step's time (sized on
            # the first step).
            episode = quota = np.zeros(0, dtype=np.int64)
            last_time = np.zeros(0)

            def audited(inp: PolicyInput) -> NDArray[np.int64]:
                nonlocal episode, quota, last_time
                act = policy(inp)
                expert(inp)
                p = plans.pop()
                now = np.asarray([scene.time for scene in inp.scenes])
                if episode.size == 0:
                    episode, quota = np.zeros(now.size, dtype=np.int64), np.asarray(quotas(self.episodes, now.size))
                else:
                    # Time rises every step of an episode: where it does not, a new one began.
                    episode = episode + (now <= last_time)
                last_time = now
                counted = inp.active & (episode < quota)[:, None]
                self.chosen.append(act[counted])
                self.expert.append(p.actions[counted])
                self.values.append(p.values[counted])
                return act
            return audited
        return audited_factory

    def summary(self, where: str) -> str:
        return audit_line(where, np.concatenate(self.chosen), np.concatenate(self.expert),
                          np.concatenate(self.values), severe_gap(self.cfg))


def target_loss(out: torch.Tensor, y: torch.Tensor, v: torch.Tensor, w: torch.Tensor, target: str) -> torch.Tensor:
    """The loss of outputs ``out`` ``(B, N_ACTIONS)`` against labels ``y`` ``(B,)`` (class
    weights ``w``) or the planner's scaled values ``v`` ``(B, N_ACTIONS)``, per ``--target``."""
    if target == "values":
        return F.smooth_l1_loss(out, v)
    if target == "weighted":
        # Each label weighs what its worst alternative would cost (in VALUE_SCALE units),
        # plus a floor so that ties still teach the planner's order.
        stake = 0.1 - v.min(dim=1).values
        per = F.cross_entropy(out, y, weight=w, reduction="none")
        return (per * stake).sum() / (w[y] * stake).sum()
    return F.cross_entropy(out, y, weight=w)


def train(args: argparse.Namespace, scenarios: list[str]) -> StateCopy:
    torch.manual_seed(args.seed)
    rng = np.random.default_rng(args.seed)
    imitation = ImitationConfig()
    vec = make_vec(scenarios, args.envs, backend="fast")
    n_in = state_size(args.neighbours, not args.no_route) + (args.neighbours * PRIVILEGED if args.privileged else 0)

    def make() -> nn.Module:
        if args.arch == "attention":
            per = PER_NEIGHBOUR + (PRIVILEGED if args.privileged else 0)
            return EgoAttention(state_size(0, not args.no_route), per, args.neighbours, args.hidden)
        return mlp(n_in, args.hidden)

    net = make() if args.ensemble == 1 else Ensemble(make, args.ensemble)
    print(f"state copy: {n_in} inputs, {sum(p.numel() for p in net.parameters()):,} parameters")
    copy = StateCopy(net, args.neighbours, args.radius, not args.no_route, args.privileged)
    opt = (torch.optim.AdamW(net.parameters(), lr=args.lr, weight_decay=args.weight_decay) if args.weight_decay
           else torch.optim.Adam(net.parameters(), lr=args.lr))
    xs = np.zeros((args.decisions, n_in), dtype=np.float32)
    ys = np.zeros(args.decisions, dtype=np.int64)
    vs = np.zeros((args.decisions, N_ACTIONS), dtype=np.float32)
    plans: list[Plan] = []
    # --holdout: every decision whose index falls on the held-out stride is labelled and kept
    # but never trained on, so the copy can be judged on unseen states of its own distribution.
    held = np.zeros(args.decisions, dtype=bool)
    if args.holdout:
        held[:: round(1 / args.holdout)] = True
    n = updates = 0
    labels = ExpertLabels()
    behaviour = dagger_policy(planner_policy(planner_config_from_args(args.set), record=plans.append), copy, rng, lambda: expert_share(imitation, n, args.decisions), labels)
    acted: list[NDArray[np.bool_]] = []

    def policy(inp: PolicyInput) -> NDArray[np.int64]:
        acted.append(inp.active.copy())
        return behaviour(inp)

    loss = float("nan")
    bar = tqdm(total=args.decisions, desc="decisions", unit="dec")
    for _ in rollout(vec, policy, seed=train_reset_seed(args.seed, 0)):
        active = acted.pop()
        assert copy.latest is not None and labels.latest is not None
        new_x, new_y = copy.latest[active], labels.latest[active]
        # Advantages under the planner's own scores: 0 for its choice, below for the others.
        worth = plans.pop().values[active]
        new_v = (worth - worth.max(axis=-1, keepdims=True)) / VALUE_SCALE
        take = min(len(new_y), args.decisions - n)
        xs[n: n + take], ys[n: n + take], vs[n: n + take] = new_x[:take], new_y[:take], new_v[:take]
        n += take
        bar.update(take)
        due = int(n * args.updates_per_decision) - updates
        if n >= args.learning_starts and due > 0:
            w = torch.from_numpy(label_weights(ys[:n]))
            pool = np.flatnonzero(~held[:n]) if args.holdout else None
            for _ in range(due):
                idx = rng.integers(0, n, size=args.batch_size) if pool is None else rng.choice(pool, size=args.batch_size)
                x, y, v = torch.from_numpy(xs[idx]), torch.from_numpy(ys[idx]), torch.from_numpy(vs[idx])
                # An ensemble's members each learn the targets; their mean is only the policy.
                outs = net.members(x) if isinstance(net, Ensemble) else net(x)[None]
                loss_t = torch.stack([target_loss(out, y, v, w, args.target) for out in outs]).mean()
                opt.zero_grad(set_to_none=True)
                loss_t.backward()
                nn.utils.clip_grad_norm_(net.parameters(), 10.0)
                opt.step()
                loss = float(loss_t.detach())
            updates += due
            bar.set_postfix(loss=f"{loss:.3f}", beta=f"{expert_share(imitation, n, args.decisions):.2f}")
        if n >= args.decisions:
            break
    bar.close()
    vec.close()
    with torch.no_grad():
        pred_all = net(torch.from_numpy(xs[:n])).argmax(-1).numpy()
    fit = ~held[:n]
    pred, ys_fit, vs_fit = pred_all[fit], ys[:n][fit], vs[:n][fit]
    acc = float((pred == ys_fit).mean())
    ties = float(((vs_fit == 0).sum(axis=1) > 1).mean())
    print(f"trained on {int(fit.sum())} labelled decisions, {updates} updates; last batch loss {loss:.3f}; "
          f"agreement with the labels it trained on {acc:.3f}; decisions whose best value the planner's "
          f"choice shares with another first action {ties:.3f}")
    if args.audit:
        gap = severe_gap(planner_config_from_args(args.set))
        print(audit_line("on the decisions it trained on", pred, ys_fit, vs_fit.astype(np.float64) * VALUE_SCALE, gap))
        if args.holdout:
            print(audit_line("on the decisions held out of training", pred_all[~fit], ys[:n][~fit],
                             vs[:n][~fit].astype(np.float64) * VALUE_SCALE, gap))
    return copy


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenarios", default="roundabout,intersection")
    ap.add_argument("--decisions", type=int, default=20_000, help="labelled decisions (default 20000)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--envs", type=int, default=16)
    ap.add_argument("--neighbours", type=int, default=12)
    ap.add_argument("--radius", type=float, default=80.0, help="metres")
    ap.add_argument("--privileged", action="store_true",
                    help="also feed each neighbour's hidden driver state (hidden_features): a diagnostic")
    ap.add_argument("--no-route", action="store_true", help="leave the AV's planned route out of its features")
    ap.add_argument("--target", choices=["labels", "values", "weighted"], default="labels",
                    help="labels: the planner's action (class-weighted cross-entropy); values: the planner's "
                         "score of each first action against its choice (Huber regression; the policy takes the best); "
                         "weighted: labels, each weighted by what its worst alternative would cost")
    ap.add_argument("--hidden", type=int, default=256)
    ap.add_argument("--arch", choices=("mlp", "attention"), default="mlp",
                    help="mlp: two hidden layers over the whole vector; attention: the AV's features "
                    "attend over its neighbours' rows, read as a set (EgoAttention)")
    ap.add_argument("--holdout", type=float, default=0.0,
                    help="share of the labelled decisions (every 1/F-th) kept out of training and judged "
                         "with --audit: unseen states of the copy's own distribution (default 0)")
    ap.add_argument("--ensemble", type=int, default=1,
                    help="MLPs of different initial weights, each trained on the labels; the policy reads "
                         "their mean output (default 1)")
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--weight-decay", type=float, default=0.0,
                    help="decoupled weight decay (AdamW) when above 0; default 0 (Adam)")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--updates-per-decision", type=float, default=0.5)
    ap.add_argument("--learning-starts", type=int, default=1000)
    ap.add_argument("--episodes", type=int, default=200, help="test episodes per scenario (default 200)")
    ap.add_argument("--audit", action="store_true",
                    help="also ask the planner about every test state each policy acts in: agreement and "
                         "how often the planner scores its choice below its own there, beside the copy's on its training decisions (slower)")
    ap.add_argument("--compare", metavar="RUN", help="a map-reading policy run to pair against")
    ap.add_argument("-s", "--set", action="append", default=[], metavar="planner.KEY=VALUE",
                    help="the expert planner's settings, as for latentdrive evaluate (planner.depth=1)")
    args = ap.parse_args()
    for name in ("decisions", "envs", "neighbours", "hidden", "ensemble", "batch_size", "episodes"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be at least 1")
    if args.weight_decay < 0:
        ap.error("--weight-decay must be at least 0")
    if not 0.0 <= args.holdout <= 0.5:
        ap.error("--holdout must lie in [0, 0.5]")
    try:
        planner_config_from_args(args.set)
    except ConfigError as err:
        ap.error(str(err))
    torch.set_num_threads(1)
    scenarios = args.scenarios.split(",")
    t0 = time.perf_counter()
    copy = train(args, scenarios)
    print(f"training took {time.perf_counter() - t0:.0f} s")

    def copy_policy() -> Policy:
        return copy

    policies: dict[str, Callable[[], Policy]] = {"state copy": copy_policy, "rule": reference_policy("rule")}
    overrides: dict[str, dict[str, object]] = {}
    if args.compare:
        net, cfg = load_policy_network(args.compare)
        policies["map run"] = greedy_policy(net, torch.device("cpu"))
        overrides["map run"] = {"observation": cfg.observation.model_dump(), "reward": cfg.reward.model_dump()}
    audits = {name: Audit(planner_config_from_args(args.set), args.episodes) for name in policies} if args.audit else {}
    for name, audit in audits.items():
        policies[name] = audit.factory(policies[name])
    outcomes = {name: evaluate_policy(make, scenarios, args.episodes, envs=16, **overrides.get(name, {}))  # type: ignore[arg-type]
                for name, make in policies.items()}
    print(f"test set: the first {args.episodes} evaluation episodes per scenario (envs 16)")
    print(format_table({name: policy_report(o) for name, o in outcomes.items()}))
    for other in [name for name in outcomes if name != "state copy"]:
        print(format_compare(compare(outcomes["state copy"], outcomes[other]), ("state copy", other)))
    for name, audit in audits.items():
        print(audit.summary(f"{name} on the test episodes"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
