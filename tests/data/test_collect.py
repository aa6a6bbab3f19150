from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest
from helpers import held_by_another_process

from latentdrive.config import ConfigError, LatentDriveError
from latentdrive.data.cli import add_collect_parser
from latentdrive.data.collect import (
    collect,
    dataset_hash,
    episode_seeds,
    plan_units,
    resolve_env_configs,
)
from latentdrive.data.policies import episode_policy
from latentdrive.data.shards import (
    MANIFEST,
    QUANT_MAX_ERROR,
    SHARD_KEYS,
    SHARD_WALL,
    DatasetError,
    array_digest,
    dequantize,
    quantize,
)
from latentdrive.env import DrivingEnv
from latentdrive.runlock import DirectoryInUse

from .conftest import tiny_config


def manifest(root: Path) -> dict:
    return json.loads((root / MANIFEST).read_text())


def content(root: Path) -> dict[str, str]:
    return {name: e["content_sha256"] for name, e in manifest(root)["shards"].items()}


def test_quantization_error_is_at_most_half_a_step() -> None:
    x = np.linspace(0.0, 1.0, 100_001, dtype=np.float32)
    q = quantize(x)
    assert q.dtype == np.uint8 and q[0] == 0 and q[-1] == 255
    assert np.abs(dequantize(q) - x).max() <= QUANT_MAX_ERROR + 1e-6
    assert QUANT_MAX_ERROR == pytest.approx(1 / 510)


def test_shards_and_manifest_are_written(collected: Path) -> None:
    cfg = tiny_config()
    m = manifest(collected)
    units = plan_units(cfg, resolve_env_configs(cfg))
    assert sorted(p.name for p in collected.glob("*.npz")) == sorted(u.name for u in units)
    assert [u["name"] for u in m["units"]] == [u.name for u in units]
    assert set(m["shards"]) == {u.name for u in units}
    assert m["config_hash"] == dataset_hash(cfg)
    assert m["config"] == cfg.model_dump(mode="json")
    assert m["scenarios"] == ["merge", "highway"]
    assert [e["scenario"]["name"] for e in m["env_configs"]] == ["merge", "highway"]
    assert all(e["clean_observation"] for e in m["env_configs"])
    assert m["sample_shape"] == [4, 2, 16, 32]
    assert not [p for p in collected.iterdir() if p.name.endswith(".tmp")]
    episodes: list[int] = []
    for u in m["units"]:
        entry = m["shards"][u["name"]]
        with np.load(collected / u["name"], allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
        assert set(arrays) == SHARD_KEYS
        n = entry["samples"]
        assert arrays["noisy"].shape == arrays["clean"].shape == (n, 4, 2, 16, 32)
        assert arrays["noisy"].dtype == np.uint8
        assert (arrays["scenario"] == u["scenario"]).all()
        assert array_digest(arrays) == entry["content_sha256"]
        ids = np.unique(arrays["episode"])
        assert ids.tolist() == list(range(u["first_episode"], u["first_episode"] + u["episodes"]))
        episodes += ids.tolist()
        assert entry["episode_samples"] == np.bincount(arrays["episode"] - u["first_episode"]).tolist()
        # Every episode starts at the reset observation and records both AVs every step.
        for e in ids:
            steps = arrays["step"][arrays["episode"] == e]
            assert steps.min() == 0 and np.array_equal(np.bincount(steps), np.full(steps.max() + 1, 2))
        assert set(arrays["agent"].tolist()) == {0, 1}
        assert not np.array_equal(arrays["noisy"], arrays["clean"])  # sensor noise is on
    assert sorted(episodes) == list(range(12))  # global ids, unique across scenarios


def test_samples_reproduce_from_the_stored_seed(collected: Path) -> None:
    # Replay the first episode of the first highway shard from its stored seed.
    cfg = tiny_config()
    env_cfg = resolve_env_configs(cfg)[1]
    name = next(u["name"] for u in manifest(collected)["units"] if u["scenario"] == 1)
    with np.load(collected / name, allow_pickle=False) as npz:
        a = {k: npz[k] for k in npz.files}
    first = a["episode"] == a["episode"].min()
    env_seed, rng = episode_seeds(cfg.seed, "highway", int(a["episode"].min()) - cfg.episodes)
    assert (a["seed"][first] == env_seed).all()
    env = DrivingEnv(config=env_cfg)
    _, policy = episode_policy(cfg.behaviour, rng, rule_fraction=cfg.rule_fraction,
                               cruise_speeds=env_cfg.scenario.av_target_speeds)
    obs, info = env.reset(seed=env_seed)
    last = int(a["step"][first].max())
    for step in range(last + 1):
        at = first & (a["step"] == step)
        assert np.array_equal(a["noisy"][at], quantize(obs))
        assert np.array_equal(a["clean"][at], quantize(info["clean_observation"]))
        if step < last:  # the last recorded observation may be the episode's final one
            obs, _, _, _, info = env.step(policy(info["scene"], rng))


def test_rerun_with_the_same_config_skips_every_shard(dataset_copy: Path) -> None:
    before = content(dataset_copy)
    summary = collect(tiny_config(), dataset_copy, progress=False)
    assert summary.shards_written == 0 and summary.shards_skipped == len(before)
    assert content(dataset_copy) == before


def test_resume_redoes_only_a_deleted_shard(dataset_copy: Path) -> None:
    before = content(dataset_copy)
    victim = sorted(before)[1]
    (dataset_copy / victim).unlink()
    summary = collect(tiny_config(), dataset_copy, progress=False)
    assert summary.shards_written == 1 and summary.shards_skipped == len(before) - 1
    assert content(dataset_copy) == before


def test_resume_after_an_interrupted_write(dataset_copy: Path) -> None:
    # As if the process died while writing a shard: its temporary file is half written and
    # the manifest does not list it yet (the manifest is updated after the rename).
    before = content(dataset_copy)
    victim = sorted(before)[-1]
    m = manifest(dataset_copy)
    del m["shards"][victim]
    (dataset_copy / MANIFEST).write_text(json.dumps(m))
    (dataset_copy / victim).unlink()
    partial = dataset_copy / f".{victim}.4242.tmp"
    partial.write_bytes(b"PK\x03\x04 half a zip")
    summary = collect(tiny_config(), dataset_copy, progress=False)
    assert summary.shards_written == 1
    assert not partial.exists()
    assert content(dataset_copy) == before


def test_a_dataset_collected_before_later_settings_existed_still_resumes(dataset_copy: Path) -> None:
    # Regression: a manifest written before observation.route and reward.failure existed
    # lacks them; their defaults change no data, so the collection resumes.
    before = content(dataset_copy)
    m = manifest(dataset_copy)
    for env in m["env_configs"]:
        del env["observation"]["route"], env["reward"]["failure"]
    (dataset_copy / MANIFEST).write_text(json.dumps(m))
    summary = collect(tiny_config(), dataset_copy, progress=False)
    assert summary.shards_written == 0 and summary.shards_skipped == len(before)
    # A setting that does change the data still refuses the folder.
    m["env_configs"][0]["observation"]["route"] = 1.0
    (dataset_copy / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(DatasetError, match="different env_configs"):
        collect(tiny_config(), dataset_copy, progress=False)


def _recorded(root: Path) -> dict[str, float]:
    return {name: e[SHARD_WALL] for name, e in manifest(root)["shards"].items()}


def test_a_resumed_collection_reports_what_earlier_runs_spent_on_what_it_kept(dataset_copy: Path) -> None:
    before = _recorded(dataset_copy)
    assert all(s > 0 for s in before.values())  # the fixture's collection kept each shard's share
    victim = sorted(before)[1]
    (dataset_copy / victim).unlink()
    summary = collect(tiny_config(), dataset_copy, progress=False)
    # The deleted shard's earlier time is not counted: it was redone, and its new share replaces it.
    assert summary.shards_written == 1
    assert summary.resumed_s == pytest.approx(sum(s for name, s in before.items() if name != victim))
    after = _recorded(dataset_copy)
    assert {n: s for n, s in after.items() if n != victim} == {n: s for n, s in before.items() if n != victim}
    assert 0 < after[victim] <= summary.seconds + 1e-3
    # A rerun of a complete dataset reports all of it and changes no record.
    again = collect(tiny_config(), dataset_copy, progress=False)
    assert again.shards_written == 0 and again.resumed_s == pytest.approx(sum(after.values()))
    assert _recorded(dataset_copy) == after
    # A manifest written before the times were kept resumes as if nothing had been spent.
    m = manifest(dataset_copy)
    for entry in m["shards"].values():
        del entry[SHARD_WALL]
    (dataset_copy / MANIFEST).write_text(json.dumps(m))
    assert collect(tiny_config(), dataset_copy, progress=False).resumed_s == 0


@pytest.mark.parametrize("bad", [-1.0, "12", True, None, float("nan"), float("inf"), 10**400])
def test_a_manifest_whose_shard_time_is_not_seconds_is_refused(dataset_copy: Path, bad: object) -> None:
    m = manifest(dataset_copy)
    name = sorted(m["shards"])[0]
    m["shards"][name][SHARD_WALL] = bad
    (dataset_copy / MANIFEST).write_text(json.dumps(m))
    before = (dataset_copy / MANIFEST).read_bytes()
    with pytest.raises(DatasetError, match=f"manifest is corrupt \\(shard {name}: {SHARD_WALL} .* is not a number of "
                                           "seconds\\)$"):
        collect(tiny_config(), dataset_copy, progress=False)
    assert (dataset_copy / MANIFEST).read_bytes() == before


def test_resume_redoes_a_shard_whose_file_changed(dataset_copy: Path) -> None:
    before = content(dataset_copy)
    victim = sorted(before)[0]
    data = bytearray((dataset_copy / victim).read_bytes())
    data[len(data) // 2] ^= 0xFF
    (dataset_copy / victim).write_bytes(bytes(data))
    assert collect(tiny_config(), dataset_copy, progress=False).shards_written == 1
    assert content(dataset_copy) == before


def test_a_different_config_is_refused(dataset_copy: Path) -> None:
    other = tiny_config(seed=1)
    with pytest.raises(DatasetError) as err:
        collect(other, dataset_copy, progress=False)
    msg = str(err.value)
    assert "\n" not in msg
    assert str(dataset_copy) in msg and dataset_hash(other) in msg and dataset_hash(tiny_config()) in msg
    assert isinstance(err.value, LatentDriveError)


def test_a_non_empty_directory_without_manifest_is_refused(tmp_path: Path) -> None:
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(DatasetError, match="not empty"):
        collect(tiny_config(), tmp_path, progress=False)


def test_same_config_gives_identical_shards_with_one_or_two_workers(collected: Path, tmp_path: Path) -> None:
    summary = collect(tiny_config(workers=2), tmp_path / "w2", progress=False)
    assert summary.shards_written == len(content(collected))
    assert content(tmp_path / "w2") == content(collected)
    # A new dataset resumed nothing; each shard's share is the main process's wall time
    # since the previous shard arrived, so they add up to at most the run's.
    assert summary.resumed_s == 0
    assert 0 < sum(_recorded(tmp_path / "w2").values()) <= summary.seconds + 1e-3
    collect(tiny_config(), tmp_path / "w1", progress=False)
    assert content(tmp_path / "w1") == content(collected)


def test_workers_are_not_part_of_the_dataset_identity() -> None:
    assert dataset_hash(tiny_config()) == dataset_hash(tiny_config(workers=3))
    assert dataset_hash(tiny_config()) != dataset_hash(tiny_config(seed=1))


def test_units_and_seeds_follow_from_the_config() -> None:
    cfg = tiny_config()
    units = plan_units(cfg, resolve_env_configs(cfg))
    # duration 4 s at 1 Hz: at most 2 AVs × 5 recorded steps = 10 samples per episode.
    assert [(u.scenario, u.first_episode, u.episodes) for u in units] == [(0, 0, 4), (0, 4, 2), (1, 6, 4), (1, 10, 2)]
    a, _ = episode_seeds(0, "merge", 3)
    assert a == episode_seeds(0, "merge", 3)[0] != episode_seeds(0, "highway", 3)[0]
    assert a != episode_seeds(1, "merge", 3)[0]


def test_config_validation_names_the_field() -> None:
    with pytest.raises(ConfigError, match=r"scenarios: .*unknown scenario 'parking'"):
        tiny_config(scenarios=["parking"])
    with pytest.raises(ConfigError, match=r"scenarios: .*duplicate"):
        tiny_config(scenarios=["merge", "merge"])
    with pytest.raises(ConfigError, match=r"env: .*observation\.frames"):
        tiny_config(env={"observation": {"frames": 0}})
    with pytest.raises(ConfigError, match="episodes"):
        tiny_config(episodes=0)
    with pytest.raises(ConfigError, match="behaviour"):
        tiny_config(behaviour="greedy")
    dotted = tiny_config(env={"observation.height": 16, "observation.width": 32, "observation.frames": 2, "duration": 4})
    assert dotted == tiny_config() and dataset_hash(dotted) == dataset_hash(tiny_config())


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="latentdrive")
    add_collect_parser(p.add_subparsers(dest="command", required=True))
    return p


def test_cli_collects_and_refuses_another_config(collected: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cli"
    argv = ["collect", str(out), "--scenarios", "merge,highway", "--episodes", "6", "--shard-size", "40",
            "--set", "observation.height=16", "--set", "observation.width=32",
            "--set", "observation.frames=2", "--set", "duration=4", "-q"]
    args = _parser().parse_args(argv)
    assert args.func(args) == 0
    assert capsys.readouterr().err == ""  # quiet: no progress lines
    assert content(out) == content(collected)
    args = _parser().parse_args([*argv, "--seed", "5"])
    with pytest.raises(DatasetError, match="not this config's"):
        args.func(args)
    args = _parser().parse_args(["collect", str(tmp_path / "x"), "--scenarios", "nowhere"])
    with pytest.raises(ConfigError, match="scenarios"):
        args.func(args)


def test_a_second_collect_into_a_directory_in_use_is_refused(tmp_path: Path) -> None:
    out = tmp_path / "ds"
    with held_by_another_process(out, "collect"):
        with pytest.raises(DirectoryInUse, match="collect"):
            collect(tiny_config(), out, progress=False)
    assert not (out / MANIFEST).exists()
    # The lock file alone does not make the directory "not empty".
    assert collect(tiny_config(), out, progress=False).shards_written > 0
