"""Replay stores each observation once: stacks rebuilt from uint8 frames, latents encoded once."""

import numpy as np
import pytest
import torch

import latentdrive
from latentdrive.data.shards import QUANT_MAX_ERROR
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.learner import Learner, make_store
from latentdrive.rl.policy import FeatureCache, build_network
from latentdrive.rl.replay import FrameStore, LatentStore, Replay
from latentdrive.rollout import rollout

OBS = {"height": 16, "width": 32, "frames": 3}


def _random_policy(rng):
    return lambda inp: rng.integers(0, 5, size=inp.active.shape)


def _record(mode: str, steps: int = 30, vfan: dict | None = None):
    """Drive a learner's replay writing through real rollouts; keep every stored observation."""
    cfg = PolicyTrainConfig(mode=mode, scenarios=("intersection", "merge"), envs=4, observation=OBS,
                            dqn={"buffer_size": 1000}, vfan=vfan or {})
    net = build_network(cfg, None if mode == "raw" else BottleneckConfig.for_observation(cfg.observation))
    vec = latentdrive.make_vec(list(cfg.scenarios), cfg.envs, observation=OBS)
    learner = Learner(cfg, net, torch.device("cpu"), cfg.envs * vec.n_av)
    cache = FeatureCache(net, torch.device("cpu"))
    seen: dict[int, np.ndarray] = {}
    cur = None
    for t, rec in enumerate(rollout(vec, _random_policy(np.random.default_rng(0)), seed=1)):
        if cur is None:
            cur = learner.start_segment(cache(rec.obs))
            for (e, a), i in np.ndenumerate(cur):
                seen[int(i)] = rec.obs[e, a]
        ei, ai = np.nonzero(rec.agents.acting)
        start = learner.replay.added
        cur = learner.record(rec, cur, cache)
        for j, (e, a) in enumerate(zip(ei, ai, strict=True)):
            seen[int(learner.replay.next_id[start + j])] = rec.next_obs[e, a]
        for e in np.flatnonzero(rec.ended):
            for a in range(vec.n_av):
                seen[int(cur[e, a])] = rec.obs_after[e, a]
        if t == steps:
            break
    return learner, net, seen


def test_sampled_raw_stacks_equal_the_env_observations_within_quantization():
    learner, _, seen = _record("raw")
    assert any(learner.replay.terminated[: len(learner.replay)])  # episodes ended in there
    ids = np.array(sorted(seen))
    got = learner.replay.store.get(ids)
    want = np.stack([seen[int(i)] for i in ids])
    assert got.shape == want.shape
    assert np.abs(got - want).max() <= QUANT_MAX_ERROR + 1e-7
    # Sampling goes through the same path.
    batch = learner.replay.sample(np.random.default_rng(0), 16)
    assert batch.obs.shape == (16, 4, 3, 16, 32) and batch.next_obs.shape == batch.obs.shape
    # Laid out channels-last, as the VFAN's CPU convolutions take them without a copy.
    assert batch.obs.is_contiguous(memory_format=torch.channels_last_3d)


def test_batches_keep_the_channels_last_layout_on_the_cpu_only():
    from latentdrive.rl.replay import _on

    learner, _, _ = _record("raw", steps=10)
    stored = learner.replay.store.get(np.arange(4))
    assert _on(stored, "cpu").is_contiguous(memory_format=torch.channels_last_3d)
    # Any other device gets the plain layout (a device that holds no data stands in for CUDA).
    elsewhere = _on(stored, "meta")
    assert elsewhere.is_contiguous() and elsewhere.shape == stored.shape


def test_the_vfan_gives_the_same_q_values_whatever_its_inputs_layout():
    learner, net, _ = _record("raw", steps=10)
    batch = learner.replay.sample(np.random.default_rng(0), 8)
    plain = batch.obs.contiguous()
    assert not plain.is_contiguous(memory_format=torch.channels_last_3d)
    with torch.no_grad():
        # The body's layers on the plain layout (forward would convert it) against forward.
        assert torch.allclose(net(batch.obs), net.body.net(plain), rtol=1e-5, atol=1e-6)


def test_latent_replay_is_exactly_encoding_at_sampling_time():
    learner, net, seen = _record("latent-random")
    ids = np.array(sorted(seen))
    stored = torch.from_numpy(learner.replay.store.get(ids))
    with torch.no_grad():
        fresh = net.encoder.encode(torch.from_numpy(np.stack([seen[int(i)] for i in ids])))
    # Frozen encoder: the stored latents are what sampling-time encoding would give.
    torch.testing.assert_close(stored, fresh, atol=1e-6, rtol=1e-5)


def test_the_objects_reader_stores_the_vehicles_it_finds_once_and_reads_them_back():
    learner, net, seen = _record("raw", vfan={"reader": "objects", "objects_k": 6})
    ids = np.array(sorted(seen))
    store = learner.replay.store
    assert isinstance(store, LatentStore) and net.stored_shape == (2 + 4 * 8 + 6 * 6,)
    maps = torch.from_numpy(np.stack([seen[int(i)] for i in ids]))
    stored = torch.from_numpy(store.get(ids))
    torch.testing.assert_close(stored, net.features(maps), atol=0, rtol=0)
    assert stored[:, -6 * 6:].reshape(len(ids), 6, 6)[:, 0, -1].sum() > 0  # vehicles were found
    with torch.no_grad():
        torch.testing.assert_close(net(stored), net(net.features(maps)))


@pytest.mark.parametrize("frames_into_features", [True, False])
def test_a_replay_of_the_other_store_kind_is_refused_and_changes_nothing(frames_into_features):
    # An objects-reader run saved while its replay held map frames cannot resume on rows,
    # nor a replay of rows into a network that stores frames.
    frames = _filled_replay(FrameStore(16, (4, 2, 4, 4)), 5)
    rows = _filled_replay(LatentStore(16, (3,)), 4, seed=1)
    source, target = (frames, rows) if frames_into_features else (rows, frames)
    before = target.state()
    with pytest.raises(ValueError, match="holds map frames" if frames_into_features else "holds fixed features"):
        target.load_state(source.state())
    after = target.state()
    assert after.keys() == before.keys() and all(np.array_equal(after[k], before[k]) for k in before)


def test_features_of_several_frames_are_each_observations_own():
    # Rows of a batch are the rows each observation gives alone (frames stacked along the
    # batch inside features() must come back to their own observation).
    torch.manual_seed(0)
    cfg = PolicyTrainConfig(mode="raw", observation=OBS, vfan={"reader": "objects", "objects_frames": 3})
    net = build_network(cfg, None)
    maps = torch.from_numpy(_record("raw", steps=3)[2][5]).expand(1, -1, -1, -1, -1)
    batch = torch.cat([maps, torch.flip(maps, dims=[-1]), torch.zeros_like(maps)])
    together = net.features(batch)
    assert together[:2, -3 * 16 * 6:].reshape(2, 3, 16, 6)[..., -1].sum() > 0
    for i in range(len(batch)):
        torch.testing.assert_close(together[i:i + 1], net.features(batch[i:i + 1]), atol=0, rtol=0)


def test_transitions_of_an_ended_episode_lead_to_its_final_observation():
    learner, _, seen = _record("raw", steps=40)
    r = learner.replay
    n = len(r)
    # Every transition's next observation continues the same agent's stack: its older
    # frames are the newer frames of the observation it came from.
    for k in range(n):
        a, b = seen[int(r.obs_id[k])], seen[int(r.next_id[k])]
        np.testing.assert_array_equal(a[:, 1:], b[:, :-1])


def test_evicted_observations_are_refused():
    store = FrameStore(4, (4, 2, 8, 8))
    ids = store.add(np.zeros((6, 4, 2, 8, 8), np.float32), np.full(6, -1))
    with pytest.raises(IndexError, match="evicted"):
        store.get(ids[:1])
    latents = LatentStore(2, (3,))
    ids = latents.add(np.zeros((3, 3), np.float32), np.full(3, -1))
    with pytest.raises(IndexError):
        latents.get(ids[:1])


@pytest.mark.parametrize("dqn", [{}, {"n_step": 20, "prioritized": True}])
def test_raw_replay_of_100k_transitions_fits_in_2_gib(dqn):
    cfg = PolicyTrainConfig(mode="raw", dqn={"buffer_size": 100_000, **dqn})
    net = build_network(cfg, None)
    d = cfg.dqn
    replay = Replay(d.buffer_size, make_store(net, cfg, n_slots=16 * 2), prioritized=d.prioritized)
    store = replay.store
    assert isinstance(store, FrameStore)
    arrays: list[np.ndarray] = [replay.obs_id, replay.next_id, replay.action, replay.reward, replay.terminated,
                                replay.steps, store.data, store.prev]
    if replay.tree is not None:
        arrays.append(replay.tree.tree)
    total = sum(a.nbytes for a in arrays)
    assert total <= 2 * 2**30, f"{total / 2**30:.2f} GiB"


def _filled_replay(store, n: int, seed: int = 0) -> Replay:
    rng = np.random.default_rng(seed)
    replay = Replay(8, store)
    shape = (n, 4, 2, 4, 4) if isinstance(store, FrameStore) else (n, 3)
    ids = store.add(rng.random(shape, dtype=np.float32), np.full(n, -1))
    replay.add(ids, rng.integers(0, 5, n), rng.random(n, dtype=np.float32), ids, rng.random(n) < 0.5)
    return replay


def _whole_rings(replay: Replay) -> dict[str, np.ndarray]:
    """``replay.state()`` as checkpoints saved it before they kept the filled slots only."""
    out = replay.state()
    for key in out:
        owner, name = key.split("/")
        if name != "added":
            out[key] = getattr(replay if owner == "replay" else replay.store, name)
    return out


@pytest.mark.parametrize("make", [lambda: FrameStore(12, (4, 2, 4, 4)), lambda: LatentStore(12, (3,))])
@pytest.mark.parametrize("n", [0, 5, 8, 30])
def test_a_replay_saves_its_filled_slots_and_restores_exactly(make, n):
    replay = _filled_replay(make(), n)
    state = replay.state()
    assert len(state["replay/obs_id"]) == min(n, 8) and len(state["store/data"]) == min(n, 12)
    # Into a new replay, into one holding more, and from a whole ring as older checkpoints saved it.
    for target, arrays in [(_filled_replay(make(), 0), state), (_filled_replay(make(), 40, seed=1), state),
                           (_filled_replay(make(), 0), _whole_rings(replay))]:
        target.load_state({k: v.copy() for k, v in arrays.items()})
        assert target.added == replay.added and target.store.added == replay.store.added
        for name in ("obs_id", "next_id", "action", "reward", "terminated"):
            np.testing.assert_array_equal(getattr(target, name), getattr(replay, name))
        for name in ("data", "prev"):
            if hasattr(replay.store, name):
                np.testing.assert_array_equal(getattr(target.store, name), getattr(replay.store, name))


def test_sampled_observations_are_the_stored_transitions_first_ones():
    store = LatentStore(20, (3,))
    replay = Replay(8, store)
    with pytest.raises(ValueError, match="empty"):
        replay.sample_observations(np.random.default_rng(0), 4)
    ids = store.add(np.arange(30, dtype=np.float32).reshape(10, 3), np.full(10, -1))
    # Five transitions, 0..4 → 5..9: their next observations and the unfilled slots are never drawn.
    replay.add(ids[:5], np.zeros(5, np.int64), np.zeros(5, np.float32), ids[5:], np.zeros(5, bool))
    obs, drawn = replay.sample_observations(np.random.default_rng(0), 200)
    assert obs.shape == (200, 3) and set(drawn.tolist()) == set(ids[:5].tolist())
    np.testing.assert_array_equal(obs.numpy(), store.get(drawn))


def test_a_replay_that_does_not_fit_is_refused_and_changes_nothing():
    replay = _filled_replay(FrameStore(12, (4, 2, 4, 4)), 5)
    target = _filled_replay(FrameStore(12, (4, 2, 4, 4)), 3, seed=1)
    before = {k: v.copy() for k, v in target.state().items()}
    bad: list[tuple[str, np.ndarray]] = [
        ("replay/obs_id", np.zeros(4, np.int64)), ("replay/reward", np.zeros(5, np.float64)),
        ("store/data", np.zeros((5, 4, 3, 3), np.uint8)), ("store/prev", np.zeros(6, np.int64)),
        ("replay/added", np.array([-1])),
    ]
    for key, value in bad:
        with pytest.raises(ValueError):
            target.load_state({**replay.state(), key: value})
        after = target.state()
        assert after.keys() == before.keys() and all(np.array_equal(after[k], before[k]) for k in before)


def test_latent_network_stores_latents():
    enc = BottleneckNetwork(BottleneckConfig(latent_dim=16))
    cfg = PolicyTrainConfig(mode="latent-random")
    net = build_network(cfg, enc.cfg)
    assert net.stored_shape == (3, 16)
    assert net(torch.zeros(2, 3, 16)).shape == (2, 5)


def test_the_feature_cache_encodes_each_needed_observation_once_and_no_other(monkeypatch):
    cfg = PolicyTrainConfig(mode="latent-random", observation=OBS)
    net = build_network(cfg, BottleneckConfig.for_observation(cfg.observation))
    encoded: list[int] = []
    features = net.features

    def counting(x: torch.Tensor) -> torch.Tensor:
        encoded.append(len(x))
        return features(x)

    monkeypatch.setattr(net, "features", counting)
    cache = FeatureCache(net, torch.device("cpu"))
    obs = np.random.default_rng(0).random((3, 2, *cfg.observation.shape), dtype=np.float32)
    need = np.array([[True, False], [True, True], [False, False]])
    got = cache(obs, need)
    assert encoded == [3] and not got[~torch.from_numpy(need)].any()
    with torch.no_grad():
        want = features(torch.from_numpy(obs.reshape(-1, *obs.shape[2:]))).reshape(3, 2, *net.stored_shape)
    torch.testing.assert_close(got[torch.from_numpy(need)], want[torch.from_numpy(need)], atol=1e-6, rtol=1e-5)
    cache(obs, need)  # the same array again: nothing to do
    cache(obs)  # now every row: only the three missing ones are encoded
    assert encoded == [3, 3]
    torch.testing.assert_close(cache(obs), want, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize(("mode", "reader"), [("raw", "conv"), ("latent-random", "conv"), ("raw", "objects")])
def test_n_step_entries_never_refer_to_evicted_observations(mode, reader):
    # A small ring that wraps many times: every stored entry's observations must still be
    # in the store while the entry is in the replay, although n-step entries arrive late.
    cfg = PolicyTrainConfig(mode=mode, scenarios=("intersection", "merge"), envs=4, observation=OBS,
                            dqn={"buffer_size": 100, "n_step": 6}, vfan={"reader": reader})
    net = build_network(cfg, None if mode == "raw" else BottleneckConfig.for_observation(cfg.observation))
    vec = latentdrive.make_vec(list(cfg.scenarios), cfg.envs, observation=OBS)
    learner = Learner(cfg, net, torch.device("cpu"), cfg.envs * vec.n_av)
    cache = FeatureCache(net, torch.device("cpu"))
    cur = None
    r = learner.replay
    for t, rec in enumerate(rollout(vec, _random_policy(np.random.default_rng(0)), seed=2)):
        if cur is None:
            cur = learner.start_segment(cache(rec.obs))
        cur = learner.record(rec, cur, cache)
        n = len(r)
        r.store.get(r.obs_id[:n])  # raises IndexError on an evicted observation
        r.store.get(r.next_id[:n])
        if t == 80:
            break
    learner.end_segment()
    vec.close()
    assert r.added > 3 * r.capacity and set(np.unique(r.steps)) == set(range(1, 7))
    r.store.get(r.obs_id)
    r.store.get(r.next_id)


def test_the_replays_memory_grows_with_what_it_holds():
    replay = Replay(1000, FrameStore(2000, (4, 4, 16, 32)))
    full = replay.nbytes_at(1000)
    # Six per-transition arrays, and per stored frame 4×16×32 uint8 cells plus its link.
    assert full == 1000 * (8 + 8 + 8 + 4 + 1 + 8) + 2000 * (4 * 16 * 32 + 8)
    assert replay.nbytes_at(500) == full // 2 and replay.nbytes_at(10**6) == full
    features = Replay(100, LatentStore(200, (3, 16)))
    assert features.nbytes_at(100) == 100 * 37 + 200 * 3 * 16 * 4


def test_a_replay_larger_than_the_memory_available_is_refused_before_training(tmp_path, monkeypatch):
    import latentdrive.rl.learner as learner_module
    from latentdrive.config import ConfigError
    from latentdrive.rl.train import train_policy

    from .conftest import TINY

    monkeypatch.setattr(learner_module, "available_memory", lambda: 2**20)
    cfg = PolicyTrainConfig.model_validate({**TINY, "mode": "raw"})
    with pytest.raises(ConfigError) as info:
        train_policy(cfg, tmp_path / "run", progress=False, say=lambda _l: None)
    msg = str(info.value)
    assert "\n" not in msg and "GiB of memory is available" in msg and "dqn.buffer_size" in msg
    from latentdrive.runlock import LOCK_NAME

    # Nothing written but the folder and its lock.
    assert [p.name for p in (tmp_path / "run").iterdir()] == [LOCK_NAME]
    # A finished run loads no replay: it resumes to nothing whatever memory is left; one
    # with training left checks before it loads its replay.
    monkeypatch.setattr(learner_module, "available_memory", lambda: None)
    train_policy(cfg, tmp_path / "done", progress=False, say=lambda _l: None)
    monkeypatch.setattr(learner_module, "available_memory", lambda: 2**20)
    assert train_policy(cfg, tmp_path / "done", resume=True, progress=False, say=lambda _l: None)["transitions"] >= 300
    longer = PolicyTrainConfig.model_validate({**TINY, "mode": "raw", "steps": 400})
    with pytest.raises(ConfigError, match="GiB of memory is available"):
        train_policy(longer, tmp_path / "done", resume=True, progress=False, say=lambda _l: None)


def test_the_memory_available_is_the_least_of_the_machines_and_the_cgroups(tmp_path, monkeypatch):
    import latentdrive.runtime as runtime

    limit, used = tmp_path / "memory.max", tmp_path / "memory.current"
    monkeypatch.setattr(runtime, "_cgroup_memory_files", lambda: [(limit, used)])
    limit.write_text("1000\n")
    used.write_text("400\n")
    assert runtime.available_memory() == 600
    for no_cap in ("max", str(2**63 - 4096)):  # v2 and v1 ways to say "no limit": the machine's figure
        limit.write_text(no_cap + "\n")
        have = runtime.available_memory()
        assert have is None or have > 2**20
