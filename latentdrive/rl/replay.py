"""Experience replay that stores each agent-observation once.

Transitions refer to observations by id. An observation store keeps them in a ring:

- :class:`LatentStore` (latent modes, and the objects reader of raw maps): the frozen
  encoder's latents ``(3, d)`` float32, or the vehicles and road the objects reader finds
  in the map ``(F,)``, computed once when the observation is collected. Both are fixed
  functions of the observation, so this is exactly what computing them at sampling time
  would give, at a fraction of the cost.
- :class:`FrameStore` (raw and end-to-end modes but for the objects reader): only the
  newest VelocityMap frame ``(4, H, W)`` of each observation, as uint8 (``round(255·x)``), with the id of the same
  agent's previous frame. Sampling rebuilds the stack ``(4, T, H, W)`` by following those
  links, repeating the first frame of an episode as the env does. A stack shares T-1
  frames with its predecessor, so this takes about 1/T of the memory of storing stacks,
  and 1/(2T) of storing obs and next obs: 100k transitions at 4×32×64 cells take about
200k frames of 8 KiB, 1.6 GB (tests/rl/test_replay.py checks the arrays stay under 2 GiB).

Ids count every observation ever added; slot ``id % capacity`` holds it while
``id >= added - capacity``.

A transition may span ``k`` policy steps (n-step returns, :mod:`latentdrive.rl.nstep`):
its reward is then the discounted sum of ``k`` rewards and its bootstrap is discounted by
``γ^k``. With ``prioritized`` the replay samples in proportion to priorities
(:mod:`latentdrive.rl.priority`) and gives each sample its importance weight.
"""

from __future__ import annotations

from typing import ClassVar, NamedTuple, Protocol

import numpy as np
import torch
from numpy.typing import NDArray

from latentdrive.data.shards import dequantize, quantize
from latentdrive.rl.priority import SumTree

__all__ = ["Batch", "FrameStore", "LatentStore", "ObservationStore", "Replay"]

IntArray = NDArray[np.int64]


class Batch(NamedTuple):
    """A sampled minibatch of transitions (tensors on the learner's device)."""

    obs: torch.Tensor  # (B, *stored_shape)
    action: torch.Tensor  # (B,) int64
    reward: torch.Tensor  # (B,) float32
    next_obs: torch.Tensor  # (B, *stored_shape)
    #: (B,) float32: 0 where the agent terminated (crash or mission done), else 1.
    bootstrap: torch.Tensor
    #: (B,) float32: policy steps k the transition spans; its bootstrap is discounted by γ^k.
    steps: torch.Tensor | None = None
    #: (B,) float32 importance weights (prioritized replay), or None: all equal.
    weight: torch.Tensor | None = None
    #: (B,) the sampled replay slots (to update their priorities), or None.
    slots: NDArray[np.int64] | None = None


class ObservationStore(Protocol):
    capacity: int
    added: int
    #: Bytes of the store's arrays when full.
    nbytes: int

    def add(self, obs: NDArray[np.float32], prev: IntArray) -> IntArray: ...
    def get(self, ids: IntArray) -> NDArray[np.float32]: ...
    def state(self) -> dict[str, np.ndarray]: ...
    def load_state(self, arrays: dict[str, np.ndarray]) -> None: ...


class LatentStore:
    """Fixed features (latents) ``(*shape)`` float32 by id; ``prev`` is ignored (they are whole)."""

    def __init__(self, capacity: int, shape: tuple[int, ...]) -> None:
        self.capacity = int(capacity)
        self.added = 0
        self.data = np.zeros((self.capacity, *shape), dtype=np.float32)
        self.nbytes = self.data.nbytes

    def add(self, obs: NDArray[np.float32], prev: IntArray) -> IntArray:
        ids = self.added + np.arange(len(obs), dtype=np.int64)
        self.data[ids % self.capacity] = obs
        self.added += len(obs)
        return ids

    def get(self, ids: IntArray) -> NDArray[np.float32]:
        if len(ids) and ids.min() < self.added - self.capacity:
            raise IndexError("observation evicted from the store")
        return self.data[ids % self.capacity]

    def state(self) -> dict[str, np.ndarray]:
        """The filled slots only (see :func:`_check`)."""
        n = min(self.added, self.capacity)
        return {"data": self.data[:n], "added": np.array([self.added], dtype=np.int64)}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        _same_kind(arrays, frames=False)
        added = _added(arrays)
        _check(arrays["data"], self.data, added, "stored features")
        _restore(self.data, arrays["data"], self.added, added, 0)
        self.added = added


class FrameStore:
    """Newest frames ``(4, H, W)`` uint8 with links to the previous frame; stacks of ``frames``.

    ``add(obs, prev)`` takes stacked observations ``(k, 4, T, H, W)`` and stores their last
    frame; ``prev[i]`` is the id of the same agent's previous observation in the episode,
    or -1 at the episode's first observation.
    """

    def __init__(self, capacity: int, shape: tuple[int, int, int, int]) -> None:
        c, t, h, w = shape
        self.capacity = int(capacity)
        self.frames = t
        self.added = 0
        self.data = np.zeros((self.capacity, c, h, w), dtype=np.uint8)
        self.prev = np.full(self.capacity, -1, dtype=np.int64)
        self.nbytes = self.data.nbytes + self.prev.nbytes

    def add(self, obs: NDArray[np.float32], prev: IntArray) -> IntArray:
        ids = self.added + np.arange(len(obs), dtype=np.int64)
        self.data[ids % self.capacity] = quantize(obs[:, :, -1])
        self.prev[ids % self.capacity] = prev
        self.added += len(obs)
        return ids

    def get(self, ids: IntArray) -> NDArray[np.float32]:
        """Stacks ``(k, 4, T, H, W)`` float32 of the observations ``ids``."""
        oldest = self.added - self.capacity
        chain = np.empty((len(ids), self.frames), dtype=np.int64)
        chain[:, -1] = ids
        for j in range(self.frames - 2, -1, -1):
            later = chain[:, j + 1]
            p = self.prev[later % self.capacity]
            # The first frame of an episode fills the older slots, as FrameStack.reset does.
            chain[:, j] = np.where(p >= 0, p, later)
        if len(ids) and chain.min() < oldest:
            raise IndexError("frame evicted from the store")
        frames = self.data[chain % self.capacity]  # (k, T, 4, H, W)
        # Laid out channels-last, (k, T, H, W, 4) in memory, indexed (k, 4, T, H, W): the
        # VFAN's CPU convolutions take that layout as it is (QNetwork's body), where any
        # other one costs them a copy per forward pass. The dequantizing copy lays it out.
        return dequantize(frames.transpose(0, 1, 3, 4, 2)).transpose(0, 4, 1, 2, 3)

    def state(self) -> dict[str, np.ndarray]:
        """The filled slots only (see :func:`_check`)."""
        n = min(self.added, self.capacity)
        return {"data": self.data[:n], "prev": self.prev[:n], "added": np.array([self.added], dtype=np.int64)}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        _same_kind(arrays, frames=True)
        added = _added(arrays)
        _check(arrays["data"], self.data, added, "stored frames")
        _check(arrays["prev"], self.prev, added, "frame links")
        _restore(self.data, arrays["data"], self.added, added, 0)
        _restore(self.prev, arrays["prev"], self.added, added, -1)
        self.added = added


def _on(stored: np.ndarray, device: torch.device | str) -> torch.Tensor:
    """Stored observations as a tensor on ``device``: as laid out on the CPU (raw stacks
    come channels-last for its convolutions), contiguous elsewhere, where that layout's
    speed is not measured."""
    t = torch.from_numpy(stored).to(device)
    return t if t.device.type == "cpu" else t.contiguous()


class Replay:
    """A ring of ``capacity`` transitions over an observation store.

    Args:
        capacity: transitions kept.
        prioritized: sample in proportion to ``priority^alpha`` (proportional prioritized
            replay); otherwise uniformly.
        alpha: the priority exponent (0: uniform).
        priority_eps: added to |TD error| so that no transition's priority is 0.
        store: where the observations live. Every transition adds one observation (its
            next) and every ended episode ``n_av`` more (the new episode's first), at most
            one per transition over the replay's span plus one step's worth, and a stack
            reaches ``T-1`` frames back: give a :class:`FrameStore` at least
            ``2·capacity + (2T + 1)·agents`` frames (``agents`` = envs × AVs).
    """

    def __init__(self, capacity: int, store: ObservationStore, *, prioritized: bool = False, alpha: float = 0.6,
                 priority_eps: float = 1e-6) -> None:
        self.capacity = int(capacity)
        self.store = store
        self.added = 0
        self.obs_id = np.zeros(self.capacity, dtype=np.int64)
        self.next_id = np.zeros(self.capacity, dtype=np.int64)
        self.action = np.zeros(self.capacity, dtype=np.int64)
        self.reward = np.zeros(self.capacity, dtype=np.float32)
        self.terminated = np.zeros(self.capacity, dtype=bool)
        self.steps = np.ones(self.capacity, dtype=np.int64)
        self.alpha, self.priority_eps = float(alpha), float(priority_eps)
        self.tree = SumTree(self.capacity) if prioritized else None
        self.max_priority = 1.0  # of priority^alpha: what a new transition gets

    def __len__(self) -> int:
        return min(self.added, self.capacity)

    def nbytes_at(self, transitions: int) -> int:
        """Bytes the replay and its observation store occupy once they hold ``transitions``
        (their arrays are reserved whole but take memory as they fill; the store holds about
        two observations per transition)."""
        share = min(1.0, transitions / self.capacity)
        own = sum(getattr(self, name).nbytes for name in self._ARRAYS)
        tree = self.tree.tree.nbytes if self.tree is not None else 0
        return int(share * (own + tree + self.store.nbytes))

    def add(self, obs_id: IntArray, action: IntArray, reward: NDArray[np.floating], next_id: IntArray,
            terminated: NDArray[np.bool_], steps: IntArray | None = None) -> None:
        """Store ``k`` transitions (every argument ``(k,)``); ``steps``: policy steps each spans (1 when None)."""
        k = len(obs_id)
        slots = (self.added + np.arange(k)) % self.capacity
        self.obs_id[slots] = obs_id
        self.next_id[slots] = next_id
        self.action[slots] = action
        self.reward[slots] = reward
        self.terminated[slots] = terminated
        self.steps[slots] = 1 if steps is None else steps
        if self.tree is not None and k:
            self.tree.set(slots, np.full(k, self.max_priority))
        self.added += k

    def sample(self, rng: np.random.Generator, batch_size: int, device: torch.device | str = "cpu",
               beta: float = 1.0) -> Batch:
        """``batch_size`` transitions drawn with replacement: uniformly, or (prioritized) in
        proportion to their priority, with importance weights ``(N·P(i))^-beta`` divided by
        the batch's largest."""
        if len(self) == 0:
            raise ValueError("cannot sample from an empty replay")
        weight = None
        if self.tree is None:
            idx = rng.integers(0, len(self), size=batch_size)
        else:
            idx = self.tree.sample(rng, batch_size, len(self))
            p = self.tree.leaves(len(self))[idx] / self.tree.total
            w = (len(self) * p) ** -beta
            weight = torch.from_numpy((w / w.max()).astype(np.float32)).to(device)
        obs = _on(self.store.get(self.obs_id[idx]), device)
        nxt = _on(self.store.get(self.next_id[idx]), device)
        return Batch(
            obs, torch.from_numpy(self.action[idx]).to(device),
            torch.from_numpy(self.reward[idx]).to(device), nxt,
            torch.from_numpy((~self.terminated[idx]).astype(np.float32)).to(device),
            torch.from_numpy(self.steps[idx].astype(np.float32)).to(device), weight, idx,
        )

    def sample_observations(self, rng: np.random.Generator, batch_size: int,
                            device: torch.device | str = "cpu") -> tuple[torch.Tensor, NDArray[np.int64]]:
        """The first observations of ``batch_size`` transitions drawn uniformly with
        replacement, and their store ids ``(batch_size,)``; nothing else is read."""
        if len(self) == 0:
            raise ValueError("cannot sample from an empty replay")
        ids = self.obs_id[rng.integers(0, len(self), size=batch_size)]
        return _on(self.store.get(ids), device), ids

    def update_priorities(self, index: IntArray, td_error: NDArray[np.floating]) -> None:
        """New priorities ``(|td_error| + eps)^alpha`` of sampled slots ``index`` ``(B,)``."""
        if self.tree is None:
            return
        p = (np.abs(np.asarray(td_error, dtype=np.float64)) + self.priority_eps) ** self.alpha
        self.tree.set(index, p)
        self.max_priority = max(self.max_priority, float(p.max()))

    _ARRAYS = ("obs_id", "next_id", "action", "reward", "terminated", "steps")
    #: Arrays older checkpoints lack, and the value every one of their transitions had.
    _OPTIONAL: ClassVar[dict[str, int]] = {"steps": 1}

    def state(self) -> dict[str, np.ndarray]:
        """Every array needed to continue exactly (for checkpoints): the filled slots only,
        so that a short run's replay takes the space of its transitions, not of its capacity."""
        n = len(self)
        own: dict[str, np.ndarray] = {name: getattr(self, name)[:n] for name in self._ARRAYS}
        own["added"] = np.array([self.added], dtype=np.int64)
        if self.tree is not None:
            own["priority"] = self.tree.leaves(n).copy()
            own["max_priority"] = np.array([self.max_priority], dtype=np.float64)
        return {**{f"replay/{k}": v for k, v in own.items()},
                **{f"store/{k}": v for k, v in self.store.state().items()}}

    def load_state(self, arrays: dict[str, np.ndarray]) -> None:
        """Restore :meth:`state` (or the whole arrays, as older checkpoints hold them).

        Raises ``KeyError`` or ``ValueError`` when ``arrays`` do not fit this replay;
        nothing is changed then.
        """
        own = {k.removeprefix("replay/"): v for k, v in arrays.items() if k.startswith("replay/")}
        added = _added(own)
        n = min(added, self.capacity)
        for name, value in self._OPTIONAL.items():
            if name not in own:
                own[name] = np.full(n, value, dtype=getattr(self, name).dtype)
        for name in self._ARRAYS:
            _check(own[name], getattr(self, name), added, f"replay {name}")
        if self.tree is not None:
            prio, top = own["priority"], own["max_priority"]
            if prio.dtype != np.float64 or prio.shape[0] < n or top.shape != (1,) or not np.isfinite(prio[:n]).all():
                raise ValueError(f"replay priorities are {prio.dtype} {prio.shape}, expected float64 ({n},)")
        store = {k.removeprefix("store/"): v for k, v in arrays.items() if k.startswith("store/")}
        # The store checks its arrays before it changes anything; the replay's are checked.
        self.store.load_state(store)
        for name in self._ARRAYS:
            blank = self._OPTIONAL.get(name, 0)
            _restore(getattr(self, name), own[name], self.added, added, blank)
        if self.tree is not None:
            self.tree.rebuild(own["priority"][:n])
            self.max_priority = float(own["max_priority"][0])
        self.added = added


def _added(arrays: dict[str, np.ndarray]) -> int:
    """The ``added`` counter of saved arrays."""
    a = arrays["added"]
    if a.shape != (1,) or a.dtype.kind not in "iu" or int(a[0]) < 0:
        raise ValueError(f"'added' is {a.dtype} {a.shape}, expected one count")
    return int(a[0])


def _same_kind(arrays: dict[str, np.ndarray], frames: bool) -> None:
    """Raise unless a store's saved ``arrays`` are of the kind that loads them: map frames
    (a :class:`FrameStore`'s, which carry the ``prev`` links) or fixed features. A run
    whose network changed what replay stores (an objects-reader run saved while its
    replay held frames) cannot resume; its checkpoint still evaluates."""
    if ("prev" in arrays) != frames:
        held, wanted = ("map frames", "fixed features") if not frames else ("fixed features", "map frames")
        raise ValueError(f"the replay holds {held}, this network stores {wanted}: the run cannot resume "
                         "(its checkpoint still evaluates)")


def _check(saved: np.ndarray, mine: np.ndarray, added: int, what: str) -> None:
    """Raise unless ``saved`` can restore the ring ``mine`` after ``added`` items.

    A ring saves only its filled slots, the first ``min(added, capacity)``: slot
    ``id % capacity`` of every id below ``added``. Older checkpoints saved all ``capacity``.
    """
    capacity = mine.shape[0]
    n = saved.shape[0] if saved.ndim else -1
    if saved.dtype != mine.dtype or saved.shape[1:] != mine.shape[1:] or n not in (min(added, capacity), capacity):
        want = (min(added, capacity), *mine.shape[1:])
        raise ValueError(f"{what} are {saved.dtype} {saved.shape}, expected {mine.dtype} {want}")


def _restore(mine: np.ndarray, saved: np.ndarray, added_before: int, added: int, blank: int) -> None:
    """Copy the filled slots of a checked ``saved`` into ``mine``; slots that were filled
    before and are not now get ``blank``, the value a new ring holds. Slots beyond both
    were never written, so a short run's replay restores without touching the rest of
    its (large, lazily allocated) arrays."""
    capacity = mine.shape[0]
    n, before = min(added, capacity), min(added_before, capacity)
    mine[:n] = saved[:n]
    if before > n:
        mine[n:before] = blank
