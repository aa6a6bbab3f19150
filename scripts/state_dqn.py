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

With ``--reader map`` the network reads the VelocityMap instead, through the attention
reader of ``vfan.reader=attention`` (:class:`~latentdrive.models.attention.MapAttentionBody`,
the default map and its sensor noise), and gets the AV's place in the world, :data:`POSE`,
added to its own token through a small MLP (:class:`MapPoseNet`); ``--no-pose`` zeroes the
place, leaving the map alone. The pair asks whether the place that the ego-centred map does
not show is what separates the map's policies from the exact-state learner inside the map's
view (``--no-route --view-box``). The place is in world coordinates: a policy that leans on
it has learned the preset layouts, not roads it has not seen. ``--aux SCALE`` (map reader
only) asks whether the reader can learn to see the vehicles from a better signal than the
rewards: after each Q update, an Adam step at ``SCALE`` × ``dqn.lr`` trains the reader and a
head of its own to predict, from the map, the AV's speeds and its 12 nearest vehicles inside
the map's view as the exact-state vector holds them (:func:`aux_targets`). The targets are
used in training only; the policy reads the map.

With ``--reader blobs`` the network reads the map through rules instead of a learned stem:
the vehicles that the fixed detector and tracker of ``scripts/map_blobs.py`` finds in the
default map's two newest frames (place, motion over the last step, value, size), its
``--neighbours`` nearest, and the road channel averaged over ``--road-pool`` cells, in the
exact-state vector's layout, through the same :class:`EgoAttention`. It asks whether the
learned stem or what the map shows holds the map's policies back. ``--exact-vehicles``
replaces the vehicles found by the exact-state rows of the nearest inside the map's view
(:func:`exact_in_view`; headings, signed velocities, no noise), keeping the map's speed and road:
what a perfect detector would give this reader. ``--ego-motion`` measures the detector's
motion after carrying the older frame into the newest frame's axes by the AV's own turn and
step (``scripts/map_blobs.py``); ``--track-frames F`` follows each vehicle through the F
newest frames and fits its motion; ``--fill`` (with ``--track-frames`` 3 or 4) puts a vehicle
the newest frame lost (the sensor drops each from a frame with probability 0.1) back one step
on along its track, where that place is clear of the newest frame's vehicles and the newest
frame holds fewer vehicles than the one before. ``--sensor-noise [PARTS]`` (with ``--exact-vehicles``) gives the exact
rows the map's sensor noise (:func:`sensor_noise`): what a perfect detector of the sensor's
noisy vehicles would give, one frame at a time; ``--sensor-frames F`` that noise as a
tracker that followed each vehicle without error through F frames would read it. ``--smooth`` (with ``--track-frames`` 3 or 4) places
each tracked vehicle on its fitted line. ``--drop velocity,heading,crashed`` zeroes
those columns of every vehicle row (:data:`DROPPABLE`) to ask which of them matters.

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
        [--reader state|map|blobs] [--road-pool CELLS] [--ego-motion] [--track-frames F] [--fill] [--smooth]
        [--exact-vehicles [--sensor-noise [PARTS] [--sensor-frames F]]] [--drop NAMES] [--aux SCALE] [--precision auto|fp32|bf16] [--compare RUN] [--outcomes FILE.json]
        [--set dqn.KEY=VALUE ...] [--set reward.KEY=VALUE ...] [--out FILE.csv]
    python scripts/state_dqn.py --pair A.json B.json

``--compare RUN`` also plays a ``train-policy`` run's greedy policy (on its own map) on the
test set and pairs it with this one. ``--outcomes`` writes the test episodes' outcomes;
``--pair A.json B.json`` trains nothing and pairs two such files (McNemar), which must hold
the same episodes.

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
import hashlib
import json
import runpy
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from numpy.typing import NDArray
from torch import nn
from tqdm import tqdm

from latentdrive.config import (
    ConfigError,
    NoiseConfig,
    ObservationConfig,
    parse_override_args,
    validate,
)
from latentdrive.errors import LatentDriveError
from latentdrive.evaluate.policies import reference_policy
from latentdrive.evaluate.report import compare, format_compare, format_table, policy_report
from latentdrive.evaluate.run import evaluate_policy
from latentdrive.fileio import atomic_write_text
from latentdrive.models.attention import MapAttentionBody
from latentdrive.observe.state import PER_NEIGHBOUR, state_size
from latentdrive.outcome import EpisodeOutcome, outcomes_from_json, outcomes_to_json
from latentdrive.rl.auxiliary import aux_step
from latentdrive.rl.dqn import DQNConfig, epsilon, target_step, update, updates_owed
from latentdrive.rl.nstep import NStepWindow
from latentdrive.rl.policy import greedy_policy, load_policy_network
from latentdrive.rl.replay import FrameStore, LatentStore, Replay
from latentdrive.rollout import Policy, PolicyInput, StepRecord, rollout
from latentdrive.runtime import PRECISIONS, autocast, resolve_precision
from latentdrive.scenarios import get_spec
from latentdrive.scenarios.spec import RewardConfig
from latentdrive.seeds import train_reset_seed, validation_reset_seed
from latentdrive.vec import make_vec

_COPY = runpy.run_path(str(Path(__file__).resolve().parent / "state_copy.py"), run_name="state_copy")
EgoAttention: type[nn.Module] = _COPY["EgoAttention"]
batch_features: Callable[..., NDArray[np.float32]] = _COPY["batch_features"]
mlp: Callable[[int, int], nn.Module] = _COPY["mlp"]
_BLOBS = runpy.run_path(str(Path(__file__).resolve().parent / "map_blobs.py"), run_name="map_blobs")
blob_features: Callable[..., NDArray[np.float32]] = _BLOBS["blob_features"]
blob_ego_size: Callable[[ObservationConfig, int], int] = _BLOBS["ego_size"]

#: The map the env renders is not read here: the smallest one keeps rendering cheap.
TINY_MAP = {"height": 4, "width": 4, "frames": 1, "behind": 0.0}
REFUSED = ("augment_shift", "explore_rule", "dueling", "prioritized", "priority_alpha", "priority_beta",
           "priority_eps")
#: The AV's own features that place it in the world (cos and sin of its heading, world x and
#: y, the share of the episode gone): ``--no-pose`` zeroes them.
POSE = slice(2, 7)
#: The share of the episode gone, within :data:`POSE`: ``--no-time`` zeroes it alone.
TIME = 6
N_POSE = POSE.stop - POSE.start
#: ``--reader map`` reads the default VelocityMap (``observation`` overrides: none).
MAP: dict[str, Any] = {}
#: That map's geometry.
GRID = ObservationConfig()
CPU = torch.device("cpu")


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
        rows = outside_zeroed(x[..., start:].reshape(*x.shape[:2], k, PER_NEIGHBOUR), view_box)
        x[..., start:] = rows.reshape(*x.shape[:2], -1)
    return x


def outside_zeroed(rows: NDArray[np.float32], view_box: tuple[float, float, float]) -> NDArray[np.float32]:
    """Vehicle rows ``(..., PER_NEIGHBOUR)`` with those whose place lies outside ``view_box``
    (metres behind, ahead, to each side) made absent (zero rows); a new array."""
    behind, front, side = view_box
    ahead, right = rows[..., 0] * 50.0, rows[..., 1] * 50.0
    return np.where(((ahead < -behind) | (ahead > front) | (np.abs(right) > side))[..., None], 0.0, rows)


#: ``--aux``'s targets: the AV's speed and lane speed and its :data:`AUX_NEIGHBOURS` nearest
#: vehicles inside the default map's view, as the exact-state vector holds them.
AUX_NEIGHBOURS = 12
N_AUX = 2 + AUX_NEIGHBOURS * PER_NEIGHBOUR


def aux_targets(state: NDArray[np.float32]) -> NDArray[np.float32]:
    """``--aux``'s targets ``(..., N_AUX)`` from :func:`features` of :data:`AUX_NEIGHBOURS`
    neighbours without the route, inside :data:`MAP_VIEW`: what the map draws."""
    return np.concatenate([state[..., :2], state[..., POSE.stop:]], axis=-1)


def map_features(inp: PolicyInput, specs: list[Any], pose: bool = True, show_time: bool = True,
                 aux: bool = False) -> NDArray[np.float32]:
    """``--reader map``'s input ``(num_envs, n_av, 4·T·H·W + N_POSE)``: each agent's stacked
    VelocityMap, flattened, then :data:`POSE` (zeroed without ``pose``; its time alone zeroed
    without ``show_time``); with ``aux``, :func:`aux_targets` after them (``N_AUX`` more),
    which the replay keeps for ``--aux`` and the network does not read."""
    e, a = inp.obs.shape[:2]
    # One pass over the Scenes gives the place and, with aux, the targets. 80 m reaches every
    # corner of MAP_VIEW's box (at most 68 m away).
    state = features(inp, specs, AUX_NEIGHBOURS if aux else 0, 80.0, False, pose, MAP_VIEW, show_time)
    parts = [inp.obs.reshape(e, a, -1), state[..., POSE]] + ([aux_targets(state)] if aux else [])
    return np.concatenate(parts, axis=-1, dtype=np.float32)


class MapAndPose:
    """The replay's observation store for ``--reader map``: each observation is a
    :func:`map_features` row; its map goes to a :class:`~latentdrive.rl.replay.FrameStore`
    (the newest frame, uint8, linked to the agent's previous one), its place to a
    :class:`~latentdrive.rl.replay.LatentStore`. Both are filled together, so their ids agree.
    The script keeps no checkpoint, so the store has no ``state``/``load_state``."""

    def __init__(self, capacity: int, shape: tuple[int, int, int, int], extra: int = N_POSE) -> None:
        self.capacity, self.added, self.shape = int(capacity), 0, shape
        self.n_map = int(np.prod(shape))
        self.maps = FrameStore(capacity, shape)
        self.place = LatentStore(capacity, (extra,))  # the place, and --aux's targets

    def add(self, obs: NDArray[np.float32], prev: NDArray[np.int64]) -> NDArray[np.int64]:
        ids = self.maps.add(obs[:, : self.n_map].reshape(-1, *self.shape), prev)
        self.place.add(obs[:, self.n_map:], prev)
        self.added = self.maps.added
        return ids

    def get(self, ids: NDArray[np.int64]) -> NDArray[np.float32]:
        maps = self.maps.get(ids).reshape(len(ids), -1)
        return np.concatenate([maps, self.place.get(ids)], axis=1)


class MapPoseNet(nn.Module):
    """``--reader map``'s network: :class:`~latentdrive.models.attention.MapAttentionBody` (the
    ``vfan.reader=attention`` reader at its default width and heads) over the map part of a
    :func:`map_features` row, with an MLP's embedding of the place added to the observer's
    own token before it queries the others. A zero place adds a constant, so ``--no-pose``
    reads the map alone with the same parameters."""

    def __init__(self, obs: ObservationConfig, hidden: int, width: int = 64, heads: int = 4, aux: int = 0) -> None:
        super().__init__()
        self.shape = obs.shape
        self.n_map = int(np.prod(self.shape))
        self.body = MapAttentionBody(self.shape, obs.resolution, obs.behind, width=width, heads=heads, hidden=hidden)
        self.place = nn.Sequential(nn.Linear(N_POSE, width), nn.ReLU(), nn.Linear(width, width))
        self.me = self.body.me[0] * self.body.cols + self.body.me[1]
        #: ``--aux``: predicts :func:`aux_targets` from what the Q head reads.
        self.aux = nn.Sequential(nn.Linear(2 * width, hidden), nn.ReLU(), nn.Linear(hidden, aux)) if aux else None

    def summary(self, x: torch.Tensor) -> torch.Tensor:
        """What the heads read, ``(B, 2·width)``, from :func:`map_features` rows ``(B, ≥ n_map + N_POSE)``."""
        tokens = self.body.tokens(x[:, : self.n_map].reshape(-1, *self.shape))
        mine = tokens[:, self.me] + self.place(x[:, self.n_map: self.n_map + N_POSE])
        tokens = torch.cat([tokens[:, : self.me], mine[:, None], tokens[:, self.me + 1:]], dim=1)
        return self.body.summary(tokens, self.me)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.body.head(self.summary(x))


def map_aux_step(net: MapPoseNet, opt: torch.optim.Optimizer, obs: torch.Tensor, dtype: torch.dtype) -> float:
    """One step of ``--aux`` (:func:`latentdrive.rl.auxiliary.aux_step`, the loss of
    ``train-policy``'s ``dqn.aux_scale``): ``net.aux``'s prediction of the
    :func:`aux_targets` that ``obs``'s rows end with; the loss."""
    assert net.aux is not None
    return aux_step(net.summary, net.aux, opt, obs, obs[:, net.n_map + N_POSE:], dtype)


class BlobReading(NamedTuple):
    """``--reader blobs``'s options (module docstring), as :func:`blob_reading` reads them."""

    road_pool: int = 4
    exact_vehicles: bool = False
    drop: tuple[int, ...] = ()  #: columns of every vehicle row zeroed (:func:`drop_columns`)
    ego_motion: bool = False
    frames: int = 2
    noise: NoiseConfig | None = None  #: with ``exact_vehicles``, the sensor noise its rows carry
    fill: bool = False  #: vehicles the newest frame lost put back along their tracks
    smooth: bool = False  #: tracked vehicles placed on their fitted lines


#: The detector's defaults.
BLOBS = BlobReading()


def blob_reading(args: argparse.Namespace) -> BlobReading:
    return BlobReading(args.road_pool, args.exact_vehicles, drop_columns(args.drop), args.ego_motion, args.track_frames,
                       sensor_config(args.sensor_noise, args.sensor_frames), args.fill, args.smooth)


#: ``--sensor-noise``'s names for the parts of :class:`~latentdrive.config.NoiseConfig`.
NOISE_PARTS = {"position": "position_std", "speed": "speed_std", "heading": "heading_std", "miss": "miss_prob"}


def sensor_config(names: str | None, frames: int = 1) -> NoiseConfig | None:
    """The map's default sensor noise restricted to ``names`` (comma-separated
    :data:`NOISE_PARTS` keys, or ``all``), the other parts zero; ``None`` for ``None``. With
    ``frames`` F > 1, what a tracker that followed every vehicle without error through F
    frames of independent noise would read: each standard deviation divided by √F (the mean
    of F draws) and the miss probability raised to the power F (missed in every frame)."""
    if names is None:
        return None
    parts = list(NOISE_PARTS) if names == "all" else [n for n in names.split(",") if n]
    default = NoiseConfig.model_validate({})
    scaled = {"position_std": default.position_std / frames**0.5, "speed_std": default.speed_std / frames**0.5,
              "heading_std": default.heading_std / frames**0.5, "miss_prob": default.miss_prob**frames}
    return NoiseConfig.model_validate({field: scaled[field] if part in parts else 0.0
                                       for part, field in NOISE_PARTS.items()})


class StatePolicy:
    """ε-greedy (``eps() > 0``) or greedy actions of ``net`` over :func:`batch_features`
    (``reader`` "state"), :func:`map_features` ("map") or :func:`read_blobs` ("blobs"), its
    forward pass in ``dtype``;
    keeps the latest step's input ``(num_envs, n_av, F)`` in :attr:`latest`."""

    def __init__(self, net: nn.Module, k: int, radius: float, route: bool,
                 rng: np.random.Generator | None = None, eps: Callable[[], float] = lambda: 0.0,
                 pose: bool = True, view_box: tuple[float, float, float] | None = None, show_time: bool = True,
                 reader: str = "state", dtype: torch.dtype = torch.float32, aux: bool = False,
                 blobs: BlobReading = BLOBS) -> None:
        self.net, self.k, self.radius, self.route, self.rng, self.eps = net, k, radius, route, rng, eps
        self.pose, self.view_box, self.show_time, self.reader, self.dtype = pose, view_box, show_time, reader, dtype
        self.aux, self.blobs = aux, blobs
        self.latest: NDArray[np.float32] | None = None

    def read(self, inp: PolicyInput) -> NDArray[np.float32]:
        """This policy's input ``(num_envs, n_av, F)`` for ``inp``."""
        specs = list(inp.simulator.specs if inp.simulator is not None else [get_spec(n) for n in inp.scenarios])
        if self.reader == "map":
            return map_features(inp, specs, self.pose, self.show_time, self.aux)
        if self.reader == "blobs":
            return read_blobs(inp, specs, self.k, self.blobs)
        return features(inp, specs, self.k, self.radius, self.route, self.pose, self.view_box, self.show_time)

    def __call__(self, inp: PolicyInput) -> NDArray[np.int64]:
        x = self.read(inp)
        self.latest = x
        with torch.no_grad(), autocast(self.dtype, CPU):
            q = self.net(torch.from_numpy(x.reshape(-1, x.shape[-1]))).float()
        act = q.argmax(-1).numpy().reshape(x.shape[:2]).astype(np.int64)
        e = self.eps()
        if self.rng is not None and e > 0:
            explore = self.rng.random(act.shape) < e
            act = np.where(explore, self.rng.integers(0, q.shape[-1], size=act.shape), act)
        return act


def next_input(rec: StepRecord, names: NDArray[np.object_], simulator: Any) -> PolicyInput:
    """Where each transition of ``rec`` leads, as a policy reads it: the Scene the step led
    to and the maps drawn there. Where an episode ended, both are its last ones
    (``rec.scenes``, ``rec.next_obs``), not the next episode's first (``rec.obs_after``)."""
    return PolicyInput(rec.next_obs, rec.scenes, rec.agents.active, names, simulator)


def read_blobs(inp: PolicyInput, specs: list[Any], k: int, opts: BlobReading) -> NDArray[np.float32]:
    """``--reader blobs``'s input ``(num_envs, n_av, F)``: :func:`blob_features` of the maps,
    with ``opts.exact_vehicles`` the rows of :func:`exact_in_view` in place of the vehicles
    found (the same layout), and ``opts.drop``'s columns zeroed."""
    x = blob_features(inp.obs, GRID, k, opts.road_pool, opts.ego_motion, opts.frames, opts.fill, opts.smooth)
    rows = x[..., -k * PER_NEIGHBOUR:].reshape(*x.shape[:-1], k, PER_NEIGHBOUR)  # a view into x
    if opts.exact_vehicles:
        rows[...] = exact_in_view(inp, specs, k, opts.noise)
    rows[..., list(opts.drop)] = 0.0
    return x


#: ``--drop``'s names for columns of a vehicle row (the exact-state layout). The detector's
#: rows hold its motion in the velocity's columns and other values in the others, so
#: ``heading`` and ``crashed`` need ``--exact-vehicles``.
DROPPABLE = {"velocity": (2, 3), "heading": (4, 5), "crashed": (7,)}
#: How many vehicles :func:`exact_in_view` looks through for those inside the view.
IN_VIEW_SEARCH = 64


def exact_in_view(inp: PolicyInput, specs: list[Any], k: int, noise: NoiseConfig | None = None) -> NDArray[np.float32]:
    """``(num_envs, n_av, k, PER_NEIGHBOUR)``: the exact-state rows of the ``k`` nearest
    vehicles inside :data:`MAP_VIEW` (of the :data:`IN_VIEW_SEARCH` nearest within 80 m,
    which reaches every corner of the view), nearest first, zero rows where fewer. With
    ``noise``, the rows first carry the map's sensor noise (:func:`sensor_noise`)."""
    x = features(inp, specs, IN_VIEW_SEARCH, 80.0, False, False)
    rows = x[..., -IN_VIEW_SEARCH * PER_NEIGHBOUR:].reshape(*x.shape[:2], IN_VIEW_SEARCH, PER_NEIGHBOUR)
    if noise is not None:
        rows = sensor_noise(rows, noise)
    rows = outside_zeroed(rows, MAP_VIEW)
    # A stable sort of "absent" keeps the present rows first and in their nearest-first order.
    order = np.argsort(rows[..., -1] < 0.5, axis=-1, kind="stable")[..., :k]
    return np.take_along_axis(rows, order[..., None], axis=2).astype(np.float32)


def sensor_noise(rows: NDArray[np.float32], noise: NoiseConfig) -> NDArray[np.float32]:
    """Exact-state vehicle rows ``(..., PER_NEIGHBOUR)`` as the map's sensor draws them
    (:class:`~latentdrive.config.NoiseConfig`, as :func:`~latentdrive.observe.draw_noise`):
    each present vehicle's place jittered by ``position_std`` metres on each axis, its speed
    along its heading by ``speed_std`` m/s, its heading by ``heading_std`` radians, and the
    vehicle dropped (a zero row) with ``miss_prob``. The draws come from a generator seeded
    by the rows themselves, so the same scene reads the same whenever it is read (the
    transition's next input and the next step's input agree, as the map's frames do)."""
    flat = np.ascontiguousarray(rows).reshape(-1, *rows.shape[-2:])  # one block per observer
    out = flat.astype(np.float64)
    for block, exact in zip(out, flat, strict=True):
        seed = np.frombuffer(hashlib.blake2b(exact.tobytes(), digest_size=16).digest(), np.uint32)
        rng = np.random.default_rng(seed.tolist())
        n = exact.shape[0]
        block[:, 0:2] += rng.standard_normal((n, 2)) * noise.position_std / 50.0
        c, s = block[:, 4].copy(), block[:, 5].copy()
        dv = rng.standard_normal(n) * noise.speed_std / 20.0
        block[:, 2] += dv * c
        block[:, 3] += dv * s
        turn = rng.standard_normal(n) * noise.heading_std
        block[:, 4], block[:, 5] = c * np.cos(turn) - s * np.sin(turn), s * np.cos(turn) + c * np.sin(turn)
        block[(rng.random(n) < noise.miss_prob) | (exact[:, -1] < 0.5)] = 0.0
    return out.reshape(rows.shape).astype(np.float32)


def drop_columns(names: str) -> tuple[int, ...]:
    """The vehicle-row columns that ``--drop`` (comma-separated :data:`DROPPABLE` names) zeroes."""
    return tuple(c for name in filter(None, names.split(",")) for c in DROPPABLE[name])


def env_map(args: argparse.Namespace) -> dict[str, Any]:
    """The ``observation`` overrides of the envs: the map is rendered only to be read."""
    return MAP if args.reader in ("map", "blobs") else TINY_MAP


def evaluate(net: nn.Module, args: argparse.Namespace, scenarios: list[str], episodes: int,
             reset_seed: int | None = None) -> list[Any]:
    def make() -> Policy:
        return StatePolicy(net, args.neighbours, args.radius, not args.no_route, pose=not args.no_pose,
                           view_box=args.view_box, show_time=not args.no_time, reader=args.reader,
                           dtype=resolve_precision(args.precision, CPU), blobs=blob_reading(args))

    net.eval()
    try:
        return evaluate_policy(make, scenarios, episodes, envs=16, reset_seed=reset_seed, observation=env_map(args))
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
    dtype = resolve_precision(args.precision, CPU)
    vec = make_vec(scenarios, args.envs, backend="fast", observation=env_map(args), reward=reward.model_dump())
    # Every step stores at most one next observation per agent and, for new episodes, one
    # first observation per agent; the replay's oldest entry reaches n-1 steps further back,
    # and a stored map's stack T-1 steps further still.
    capacity = 2 * cfg.buffer_size + (2 * cfg.n_step + 4 + 2 * GRID.frames) * args.envs * vec.n_av
    net: nn.Module
    store: Any
    aux = float(args.aux)
    if args.reader == "map":
        net = MapPoseNet(GRID, args.hidden, aux=N_AUX if aux else 0)
        n_in, what = net.n_map + N_POSE, "map reader and place" + (f", auxiliary targets at {aux:g} x lr" if aux else "")
        store = MapAndPose(capacity, net.shape, N_POSE + (N_AUX if aux else 0))
    elif args.reader == "blobs":
        ego = blob_ego_size(GRID, args.road_pool)
        found = "exact vehicles in the map's view" if args.exact_vehicles else "vehicles found in the map"
        if args.sensor_noise is not None:
            found += f" with the map's sensor noise ({args.sensor_noise})"
        if args.sensor_frames > 1:
            found += f" averaged over {args.sensor_frames} frames"
        if args.fill:
            found += ", the lost ones put back"
        if args.smooth:
            found += ", placed on their tracks"
        n_in, what = ego + args.neighbours * PER_NEIGHBOUR, f"{found}, road pooled {args.road_pool}"
        net = EgoAttention(ego, PER_NEIGHBOUR, args.neighbours, args.hidden)
        store = LatentStore(capacity, (n_in,))
    else:
        n_in, what = state_size(args.neighbours, route), args.arch
        net = (EgoAttention(state_size(0, route), PER_NEIGHBOUR, args.neighbours, args.hidden)
               if args.arch == "attention" else mlp(n_in, args.hidden))
        store = LatentStore(capacity, (n_in,))
    target = copy.deepcopy(net).requires_grad_(False)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr, eps=cfg.adam_eps)
    # --aux takes its own Adam steps on the same weights, so the Q-learner's update stays the
    # project's own (rl.dqn.update) and its moments are not mixed with the auxiliary loss's.
    # Adam's steps do not scale with the loss, so --aux scales their learning rate instead.
    aux_opt = torch.optim.Adam(net.parameters(), lr=aux * cfg.lr, eps=cfg.adam_eps) if aux else None
    print(f"state DQN: {n_in} inputs, {sum(p.numel() for p in net.parameters()):,} parameters, {what}, {dtype}")
    slots = (args.envs, vec.n_av)
    replay = Replay(cfg.buffer_size, store)
    window = NStepWindow(cfg.n_step, cfg.gamma, slots)
    transitions = updates = 0
    policy = StatePolicy(net, args.neighbours, args.radius, route, rng, lambda: epsilon(cfg, transitions, args.steps),
                         pose=not args.no_pose, view_box=args.view_box, show_time=not args.no_time,
                         reader=args.reader, dtype=dtype, aux=bool(aux), blobs=blob_reading(args))
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
    loss = aux_loss = float("nan")
    specs = list(vec.simulator.specs)
    names = np.asarray([s.name for s in specs], dtype=object)
    for rec in rollout(vec, act, seed=train_reset_seed(args.seed, 0)):
        ag = rec.agents
        ei, ai = np.nonzero(ag.acting)
        after = policy.read(next_input(rec, names, vec.simulator))
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
            batch = replay.sample(rng, cfg.batch_size)
            stats = update(net, target, opt, batch, cfg, dtype)
            loss = stats.loss
            if aux_opt is not None:
                assert isinstance(net, MapPoseNet)
                aux_loss = map_aux_step(net, aux_opt, batch.obs, dtype)
            updates += 1
            target_step(target, net, cfg, updates)
        bar.set_postfix(loss=f"{loss:.3f}", aux=f"{aux_loss:.3f}", eps=f"{epsilon(cfg, transitions, args.steps):.2f}", refresh=False)
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


def read_outcomes(path: str) -> list[EpisodeOutcome]:
    """The outcomes an ``--outcomes`` file holds; ``ValueError`` naming the file otherwise."""
    try:
        return outcomes_from_json(json.loads(Path(path).read_text()))
    except (OSError, ValueError) as err:  # JSONDecodeError is a ValueError
        raise ValueError(f"{path}: not an outcomes file ({err})") from None


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
    ap.add_argument("--reader", choices=("state", "map", "blobs"), default="state",
                    help="read exact states (default), the VelocityMap with the AV's place, or the vehicles a "
                         "fixed detector finds in the map (module docstring)")
    ap.add_argument("--road-pool", type=int, default=4, metavar="CELLS",
                    help="with --reader blobs: average the road channel over CELLS x CELLS blocks (default 4)")
    ap.add_argument("--drop", default="", metavar="NAMES",
                    help="with --reader blobs: zero these columns of every vehicle row, comma-separated: "
                         + ", ".join(DROPPABLE) + " (heading and crashed only with --exact-vehicles)")
    ap.add_argument("--ego-motion", action="store_true",
                    help="with --reader blobs: carry the older frame's vehicles into the newest frame's axes by "
                         "the AV's own turn (found by matching the road) and step before measuring their motion")
    ap.add_argument("--track-frames", type=int, default=2, metavar="F",
                    help="with --reader blobs: follow each vehicle back through the map's F newest frames and "
                         "take its motion as the slope of its places (default 2: the displacement between two)")
    ap.add_argument("--fill", action="store_true",
                    help="with --reader blobs and --track-frames 3 or 4: put a vehicle the newest frame lost back "
                         "one step on along its track (scripts/map_blobs.py)")
    ap.add_argument("--smooth", action="store_true",
                    help="with --reader blobs and --track-frames 3 or 4: place each tracked vehicle on its fitted "
                         "line instead of its newest blob (scripts/map_blobs.py)")
    ap.add_argument("--exact-vehicles", action="store_true",
                    help="with --reader blobs: the exact-state rows of the vehicles inside the map's view in place "
                         "of those the detector finds")
    ap.add_argument("--sensor-noise", nargs="?", const="all", metavar="PARTS",
                    help="with --exact-vehicles: the exact rows carry the map's sensor noise, all of it or the "
                         f"comma-separated parts named ({', '.join(NOISE_PARTS)})")
    ap.add_argument("--sensor-frames", type=int, default=1, metavar="F",
                    help="with --sensor-noise: the noise a perfect tracker through F frames would read (standard "
                         "deviations / sqrt(F), miss probability to the power F)")
    ap.add_argument("--aux", type=float, default=0.0, metavar="SCALE",
                    help="with --reader map: after each Q update, also train the reader to predict, from the map, "
                         "the AV's speeds and its 12 nearest vehicles inside the map's view (exact states), by "
                         "squared error, with Adam at SCALE times dqn.lr (default 0: off); the policy still reads "
                         "the map alone")
    ap.add_argument("--precision", choices=PRECISIONS, default="fp32",
                    help="the network's compute precision, as train-policy's precision (default fp32)")
    ap.add_argument("--hidden", type=int, default=256)
    ap.add_argument("--eval-every", type=int, default=25_000, help="agent-transitions between validations (0: at the end only)")
    ap.add_argument("--eval-episodes", type=int, default=40, help="validation episodes per scenario (default 40)")
    ap.add_argument("--episodes", type=int, default=200, help="test episodes per scenario (default 200)")
    ap.add_argument("--out", help="write the validation curve to this CSV file")
    ap.add_argument("--compare", metavar="RUN", help="a train-policy run to play on the test set and pair with")
    ap.add_argument("--outcomes", metavar="FILE.json", help="write the test episodes' outcomes to this file")
    ap.add_argument("--pair", nargs=2, metavar=("A.json", "B.json"),
                    help="train nothing: pair two --outcomes files (McNemar) and exit")
    ap.add_argument("-s", "--set", action="append", default=[], metavar="dqn.KEY=VALUE")
    args = ap.parse_args()
    if args.pair:
        try:
            a, b = (read_outcomes(f) for f in args.pair)
            print(format_compare(compare(a, b), (Path(args.pair[0]).stem, Path(args.pair[1]).stem)))
        except ValueError as err:
            ap.exit(1, f"error: {err}\n")
        return 0
    if args.compare:
        try:
            compared = load_policy_network(args.compare)
        except LatentDriveError as err:  # ConfigError, CheckpointError: they name the run and the problem
            ap.error(f"--compare {args.compare}: {err}")
    for name in ("steps", "envs", "neighbours", "hidden", "eval_episodes", "episodes"):
        if getattr(args, name) < 1:
            ap.error(f"--{name.replace('_', '-')} must be at least 1")
    if args.eval_every < 0:
        ap.error("--eval-every must be at least 0")
    if args.aux < 0 or (args.aux and args.reader != "map"):
        ap.error("--aux takes a scale of at least 0, and only with --reader map")
    grid = GRID
    if args.road_pool < 1 or grid.height % args.road_pool or grid.width % args.road_pool:
        ap.error(f"--road-pool must divide the map's {grid.height} x {grid.width} cells, got {args.road_pool}")
    if (args.exact_vehicles or args.ego_motion or args.track_frames != 2 or args.road_pool != 4) and args.reader != "blobs":
        ap.error("--exact-vehicles, --ego-motion, --track-frames and --road-pool only with --reader blobs")
    if not 2 <= args.track_frames <= grid.frames:
        ap.error(f"--track-frames must be 2 to the map's {grid.frames} frames, got {args.track_frames}")
    if (args.fill or args.smooth) and args.exact_vehicles:
        ap.error("--fill and --smooth act on the vehicles the detector finds, not on --exact-vehicles")
    if (args.fill or args.smooth) and (args.reader != "blobs" or args.track_frames < 3):
        ap.error("--fill and --smooth follow a vehicle through two older frames: they need --reader blobs and "
                 "--track-frames 3 or 4")
    if args.sensor_frames < 1 or (args.sensor_frames != 1 and args.sensor_noise is None):
        ap.error(f"--sensor-frames takes a count of at least 1, with --sensor-noise, got {args.sensor_frames}")
    names = list(filter(None, args.drop.split(",")))
    if any(n not in DROPPABLE for n in names) or (args.drop and args.reader != "blobs"):
        ap.error(f"--drop takes {', '.join(DROPPABLE)} with --reader blobs, got {args.drop!r}")
    if args.sensor_noise is not None and (not args.exact_vehicles or (args.sensor_noise != "all" and (
            not args.sensor_noise or any(n not in NOISE_PARTS for n in args.sensor_noise.split(","))))):
        ap.error(f"--sensor-noise takes all or {', '.join(NOISE_PARTS)}, with --exact-vehicles, got {args.sensor_noise!r}")
    if not args.exact_vehicles and any(n != "velocity" for n in names):
        ap.error("--drop heading or crashed only with --exact-vehicles: the detector's rows hold other values there")
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
    name = {"map": "map DQN", "blobs": "blob DQN"}.get(args.reader, "state DQN")
    outcomes = {name: evaluate(net, args, scenarios, args.episodes),
                "rule": evaluate_policy(reference_policy("rule"), scenarios, args.episodes, envs=16)}
    if args.compare:
        other, run_cfg = compared
        outcomes[Path(args.compare).name] = evaluate_policy(
            greedy_policy(other, CPU), scenarios, args.episodes, envs=16,
            observation=run_cfg.observation.model_dump(), reward=run_cfg.reward.model_dump())
    if args.outcomes:
        atomic_write_text(args.outcomes, json.dumps(outcomes_to_json(outcomes[name]), allow_nan=False) + "\n")
    print(f"test set: the first {args.episodes} evaluation episodes per scenario (envs 16)")
    print(format_table({k: policy_report(o) for k, o in outcomes.items()}))
    for k in [k for k in outcomes if k != name]:
        print(format_compare(compare(outcomes[name], outcomes[k]), (name, k)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
