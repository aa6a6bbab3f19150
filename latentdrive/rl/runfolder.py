"""A policy run folder's own files: config.json, the training and evaluation logs, and
the checks a resumption or an ``--init-from`` makes before anything is written.

:mod:`latentdrive.rl.train` trains into the folder; this module knows what the folder holds.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import torch

from latentdrive.bnn.checkpoint import read_checkpoint, section
from latentdrive.config import ConfigError, config_hash, validate
from latentdrive.fileio import atomic_write_text, read_log
from latentdrive.models.bottleneck import BottleneckConfig
from latentdrive.models.vfan import QNetwork
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.policy import (
    CHECKPOINT,
    CONFIG,
    build_network,
    changed_scenarios,
    encoder_config,
    load_policy_network,
    read_run_config,
    scenario_hashes,
)

__all__ = ["EVALS", "EVAL_COLUMNS", "LOGS", "METRICS", "METRIC_COLUMNS", "check_resume", "init_weights",
           "read_logs", "same_encoder", "stored_encoder", "write_config"]

METRICS = "metrics.csv"
EVALS = "eval.csv"
METRIC_COLUMNS = ("transitions", "updates", "episodes", "epsilon", "loss", "train_failure_rate",
                   "train_crash_rate", "transitions_per_s", "elapsed_s")
EVAL_COLUMNS = ("transitions", "scenario", "episodes", "failure_rate", "crash_rate", "success_rate", "mean_return")


def write_config(run_dir: Path, cfg: PolicyTrainConfig, net: QNetwork, enc: Any) -> None:
    data = {
        "kind": "policy",
        "train": cfg.model_dump(mode="json"),
        "encoder": None if enc is None else enc.model_dump(mode="json"),
        "parameters": net.parameter_count(),
        "config_hash": config_hash(cfg),
        # The specs themselves are in "train"; their hashes let a glance tell two runs' apart.
        "scenario_hashes": scenario_hashes(cfg.specs),
    }
    atomic_write_text(run_dir / CONFIG, json.dumps(data, indent=1) + "\n")


def check_resume(run_dir: Path, cfg: PolicyTrainConfig) -> None:
    data = read_run_config(run_dir)
    moved = changed_scenarios(data)
    if moved:
        raise ConfigError(f"{run_dir}: the scenario spec of {', '.join(moved)} changed since this run "
                          "was trained; train a new run")
    saved = data["train"]
    now = cfg.model_dump(mode="json")
    # The budget may grow on resumption; everything else must match. The BNN and init_from
    # are folders, which may have moved (a study folder finished elsewhere): the weights
    # come from the checkpoint, and only the encoder's are checked, by value.
    changed = sorted(k for k in now if k not in ("steps", "bnn", "init_from") and saved.get(k) != now[k])
    if changed:
        raise ConfigError(f"{run_dir}: --resume with a different config ({', '.join(changed)} changed)")
    if cfg.mode == "latent" and saved.get("bnn") != now["bnn"]:
        mine = build_network(cfg, encoder_config(cfg), load_bnn_weights=True).state_dict()
        # The last weights, not the policy's: a keep=best run may not have been evaluated
        # yet, and the frozen encoder is the same in both.
        tensors, _ = read_checkpoint(run_dir / CHECKPOINT)
        if not same_encoder(mine, section(tensors, "model/")):
            raise ConfigError(f"{run_dir}: --resume with another BNN ({cfg.bnn} holds other weights than the "
                              f"run's {saved.get('bnn')})")


def stored_encoder(run_dir: Path) -> BottleneckConfig | None:
    """The encoder architecture a run's config.json records (its weights are in the checkpoint)."""
    data = read_run_config(run_dir)
    return validate(BottleneckConfig, data["encoder"]) if data.get("encoder") else None


def same_encoder(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> bool:
    """The frozen encoder weights of two latent-mode networks are equal."""
    keys = [k for k in a if k.startswith("encoder.")]
    return all(k in b and torch.equal(a[k], b[k]) for k in keys)


LOGS = {METRICS: ("training log", METRIC_COLUMNS), EVALS: ("evaluation log", EVAL_COLUMNS)}


def read_logs(run_dir: Path) -> dict[str, list[dict[str, str]]]:
    """The rows of a run's metrics.csv and eval.csv, checked before anything is written."""
    logs: dict[str, list[dict[str, str]]] = {}
    for name, (what, cols) in LOGS.items():
        try:
            logs[name] = read_log(run_dir / name, columns=cols, key="transitions", what=what)
        except FileNotFoundError:
            logs[name] = []
    return logs


def init_weights(cfg: PolicyTrainConfig) -> dict[str, torch.Tensor]:
    """The weights ``--init-from`` names, checked before anything is written."""
    assert cfg.init_from is not None
    src, src_cfg = load_policy_network(cfg.init_from)
    if src_cfg.mode != cfg.mode:
        raise ConfigError(f"--init-from {cfg.init_from}: a {src_cfg.mode} run cannot initialize a {cfg.mode} run")
    mine = build_network(cfg, encoder_config(cfg), load_bnn_weights=cfg.mode == "latent").state_dict()
    theirs = src.state_dict()
    if mine.keys() != theirs.keys() or any(mine[k].shape != theirs[k].shape for k in mine):
        raise ConfigError(f"--init-from {cfg.init_from}: its network's architecture differs from this run's")
    # Its weights include the frozen encoder: the run would not use the BNN its config names.
    # Compared by weights, not by path, so a study folder can move or be mounted elsewhere.
    if cfg.mode == "latent" and not same_encoder(mine, theirs):
        raise ConfigError(f"--init-from {cfg.init_from}: it was trained on another BNN than {cfg.bnn} "
                          f"(its config names {src_cfg.bnn})")
    return theirs
