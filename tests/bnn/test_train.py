"""Bottleneck-network training on small synthetic VelocityMaps (4 × T=2 × 16 × 32)."""

from __future__ import annotations

import csv
import itertools
import json
import math
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import torch

from latentdrive.bnn import train as train_mod
from latentdrive.bnn.batch import BNNBatch, array_batches_fn, iterate_batches, synthetic_dataset
from latentdrive.bnn.checkpoint import CheckpointError, read_checkpoint
from latentdrive.bnn.losses import (
    PAPER_WEIGHTS,
    CellWeights,
    LossKind,
    cell_weights,
    reconstruction_error,
    reconstruction_loss,
    step_losses,
    vehicle_cells_l2,
)
from latentdrive.bnn.resume import check_resumable
from latentdrive.bnn.train import BNNTrainConfig, load_trained_bottleneck, train_bnn
from latentdrive.config import ConfigError, validate
from latentdrive.fileio import FileFormatError
from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork, channel_pairs
from latentdrive.runtime import resolve_device

SHAPE = (4, 2, 16, 32)
MODEL = BottleneckConfig(input_shape=SHAPE[1:], latent_dim=16, channels=(8, 16, 16))


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def data() -> dict[str, np.ndarray]:
    clean, noisy, scenario = synthetic_dataset(320, SHAPE, 3, seed=0)
    vclean, vnoisy, vscenario = synthetic_dataset(96, SHAPE, 3, seed=1)
    return {
        "clean": clean, "noisy": noisy, "scenario": scenario,
        "vclean": vclean, "vnoisy": vnoisy, "vscenario": vscenario,
    }


def _fns(data: dict[str, np.ndarray], n: int, batch_size: int, stratify_from: int):
    train_fn = array_batches_fn(
        data["clean"][:n], data["noisy"][:n], data["scenario"][:n],
        batch_size=batch_size, seed=0, stratify_from_epoch=stratify_from,
    )

    def val_fn() -> Iterator[BNNBatch]:
        return iterate_batches(
            data["vclean"], data["vnoisy"], data["vscenario"], 48, np.random.default_rng(0)
        )

    return train_fn, val_fn


def _small_cfg(**fields: object) -> BNNTrainConfig:
    base = {"pretrain_epochs": 1, "mixed_epochs": 2, "batch_size": 16, "lr": 3e-3,
            "lambda_distance": 0.01, "log_every": 2, "val_mmd_samples": 8, "num_threads": 1}
    return BNNTrainConfig.model_validate({**base, **fields})


def _rows(run: Path) -> list[dict[str, str]]:
    with (run / "metrics.csv").open(newline="") as f:
        return list(csv.DictReader(f))


def _losses(run: Path) -> list[tuple[str, ...]]:
    # Everything but timings and memory, which legitimately vary between runs.
    keys = ("kind", "step", "loss", "recon", "reg", "val_loss")
    return [tuple(r[k] for k in keys) for r in _rows(run)]


def _model_tensors(run: Path) -> dict[str, torch.Tensor]:
    tensors, _ = read_checkpoint(run / "checkpoint.safetensors")
    return {k: v for k, v in tensors.items() if not k.startswith("rng/")}


# ---------------------------------------------------------------------------------------
# The loss


def test_loss_targets_the_clean_pairs(data: dict[str, np.ndarray]) -> None:
    torch.manual_seed(0)
    model = BottleneckNetwork(MODEL)
    noisy = torch.from_numpy(data["noisy"][:8])
    clean = torch.from_numpy(data["clean"][:8])
    batch = BNNBatch(noisy, clean, torch.from_numpy(data["scenario"][:8]))
    with torch.no_grad():
        recon, _ = model(noisy)
        expected = torch.mean((recon - channel_pairs(clean)) ** 2)
        against_noisy = torch.mean((recon - channel_pairs(noisy)) ** 2)
        loss = reconstruction_loss(model, batch)
        total, recon_part, reg = step_losses(model, batch, 0.0)
    assert torch.equal(loss, expected)
    assert not torch.allclose(loss, against_noisy)
    assert torch.equal(total, expected) and torch.equal(recon_part, expected) and float(reg) == 0.0
    # With λ > 0 the total adds λ times the scenario distance of the latents.
    with torch.no_grad():
        total, recon_part, reg = step_losses(model, batch, 0.5)
    assert float(reg) > 0.0
    torch.testing.assert_close(total, recon_part + 0.5 * reg)


def _logit(p: torch.Tensor) -> torch.Tensor:
    return torch.log(p / (1 - p))


def test_foreground_weight_weighs_vehicle_cells_not_the_road() -> None:
    target = torch.zeros(1, 3, 2, 1, 1, 2)
    recon = torch.full_like(target, 1e-6)
    target[0, 0, 0, 0, 0, 0] = 1.0  # an HV cell, missed
    recon[0, 0, 0, 0, 0, 1] = 0.5   # a false HV cell
    target[0, 1, 0, 0, 0, 0] = 1.0  # a road cell, missed: weighs 1 whatever the weight
    # 12 cells: plain MSE (1 + 0.25 + 1) / 12; weight 9 on the one vehicle cell:
    # (9 + 0.25 + 1) / (12 + 8).
    logits = _logit(recon)
    assert float(reconstruction_error(logits, target)) == pytest.approx(2.25 / 12, rel=1e-5)
    assert float(reconstruction_error(logits, target, CellWeights(9.0))) == pytest.approx(10.25 / 20, rel=1e-5)


def test_channel_weights_scale_the_road_and_each_av_copy() -> None:
    target = torch.zeros(1, 3, 2, 1, 1, 1)
    target[0, 0, 1] = 1.0  # the AV cell, seen in all three pairs
    target[0, 1, 1] = 1.0
    target[0, 2, 1] = 1.0
    target[0, 1, 0] = 1.0  # the road
    w = cell_weights(target, CellWeights(foreground=4.0, road=0.3, av_share=1 / 3))
    expected = torch.tensor([[1.0, 4 / 3], [0.3, 4 / 3], [1.0, 4 / 3]]).view(1, 3, 2, 1, 1, 1)
    torch.testing.assert_close(w, expected)
    # Empty cells keep their channel weight; the road is never a vehicle cell.
    empty = cell_weights(torch.zeros_like(target), CellWeights(foreground=4.0, road=0.3, av_share=0.5))
    torch.testing.assert_close(empty.flatten(), torch.tensor([1.0, 0.5, 0.3, 0.5, 1.0, 0.5]))


def test_bce_is_the_weighted_cross_entropy_of_the_cells() -> None:
    target = torch.zeros(1, 3, 2, 1, 1, 2)
    target[0, 0, 0, 0, 0, 0] = 0.8  # an HV cell
    recon = torch.full_like(target, 0.1)
    recon[0, 0, 0, 0, 0, 0] = 0.6
    logits = _logit(recon)
    # The HV cell: -(0.8 ln 0.6 + 0.2 ln 0.4); each of the 11 empty cells: -ln 0.9.
    hv = -(0.8 * math.log(0.6) + 0.2 * math.log(0.4))
    empty = -math.log(0.9)
    assert float(reconstruction_error(logits, target, loss="bce")) == pytest.approx((hv + 11 * empty) / 12, rel=1e-5)
    assert float(reconstruction_error(logits, target, CellWeights(5.0), "bce")) == pytest.approx(
        (5 * hv + 11 * empty) / 16, rel=1e-5)
    # Saturated logits stay finite.
    assert torch.isfinite(reconstruction_error(torch.full_like(target, -200.0), target, loss="bce"))
    with pytest.raises(ValueError, match="loss"):
        reconstruction_error(logits, target, loss="l1")  # type: ignore[arg-type]


def test_bce_pushes_a_missing_vehicle_harder_than_l2() -> None:
    # The reason the option exists: at a near-empty output the L2 gradient through the
    # sigmoid is damped by r(1 - r); the cross-entropy's is not.
    target = torch.zeros(1, 3, 2, 1, 1, 1)
    target[0, 0, 0] = 0.8
    grads = {}
    for kind in ("l2", "bce"):
        logit = torch.full_like(target, math.log(0.05 / 0.95), requires_grad=True)
        reconstruction_error(logit, target, loss=kind).backward()
        assert logit.grad is not None
        grads[kind] = float(logit.grad[0, 0, 0].abs().sum())
    assert grads["bce"] > 5 * grads["l2"]


def test_the_loss_of_bf16_logits_is_computed_in_float32() -> None:
    target = torch.zeros(2, 3, 2, 1, 2, 2)
    target[:, 0, 0, 0, 0, 0] = 0.7
    logits = torch.randn(target.shape, generator=torch.Generator().manual_seed(0))
    half = reconstruction_error(logits.bfloat16(), target, CellWeights(5.0, 0.3, 1 / 3), "bce")
    assert half.dtype == torch.float32
    torch.testing.assert_close(half, reconstruction_error(logits, target, CellWeights(5.0, 0.3, 1 / 3), "bce"),
                               rtol=2e-2, atol=1e-3)


def test_vehicle_cells_l2_reads_the_hv_av_pair_only() -> None:
    target = torch.zeros(1, 3, 2, 1, 2, 2)
    target[0, 0, 0, 0, 0, 0] = 1.0  # an HV cell
    target[0, 1, 0, 0, 1, 1] = 1.0  # road: not a vehicle cell
    total, count = vehicle_cells_l2(torch.zeros_like(target), target)
    assert int(count) == 1 and float(total) == pytest.approx(1.0)


def test_train_step_uses_step_losses(
    data: dict[str, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[tuple[torch.Tensor, float]] = []

    def spy(model: BottleneckNetwork, batch: BNNBatch, lam: float = 0.0, w: CellWeights = PAPER_WEIGHTS,
            loss: LossKind = "l2", dice: float = 0.0):
        seen.append((batch.clean, lam))
        return step_losses(model, batch, lam, w, loss, dice)

    monkeypatch.setattr(train_mod, "step_losses", spy)
    train_fn, _ = _fns(data, 32, 16, stratify_from=1)
    train_bnn(_small_cfg(), MODEL, train_fn, None, tmp_path / "run", progress=False)
    # Two batches per epoch; λ only in the mixed phase; the target is the clean batch.
    assert [lam for _, lam in seen] == [0.0, 0.0, 0.01, 0.01, 0.01, 0.01]
    first = next(iter(train_fn(0)))
    assert torch.equal(seen[0][0], first.clean)


# ---------------------------------------------------------------------------------------
# Training runs


#: The paper's objective: plain L2 of every cell (eq. 11), constant learning rate.
PAPER_OBJECTIVE = {"loss": "l2", "foreground_weight": 1.0, "foreground_weight_final": None, "road_weight": 1.0,
                   "av_weight": 1.0, "lr_schedule": "constant", "val_every": 1}


def test_tiny_run_learns_to_reconstruct(data: dict[str, np.ndarray], tmp_path: Path) -> None:
    cfg = _small_cfg(pretrain_epochs=6, mixed_epochs=4, batch_size=32, lambda_distance=0.0,
                     log_every=5, val_mmd_samples=32, **PAPER_OBJECTIVE)
    train_fn, val_fn = _fns(data, 320, 32, stratify_from=6)
    # The best constant guess, the mean training map, scores about 0.034.
    mean_map = channel_pairs(torch.from_numpy(data["clean"])).mean(0, keepdim=True)
    baseline = float(torch.mean((channel_pairs(torch.from_numpy(data["vclean"])) - mean_map) ** 2))
    run = tmp_path / "run"
    metrics = train_bnn(cfg, MODEL, train_fn, val_fn, run, progress=False)

    assert metrics["epoch"] == 10 and metrics["step"] == 100
    assert metrics["val_loss"] < 0.012 < baseline / 2.5
    epochs = [r for r in _rows(run) if r["kind"] == "epoch"]
    assert len(epochs) == 10
    assert [r["phase"] for r in epochs] == ["pretrain"] * 6 + ["mixed"] * 4
    assert float(epochs[0]["val_loss"]) > 2 * float(epochs[-1]["val_loss"])
    assert metrics["samples_per_s"] > 0 and metrics["peak_rss_mb"] > 0
    saved = json.loads((run / "config.json").read_text())
    assert saved["model"] == MODEL.model_dump(mode="json")
    assert saved["train"] == cfg.model_dump(mode="json")
    assert any((run / "tb").iterdir())
    # The trained encoder loads back frozen, for the Q-network.
    net = load_trained_bottleneck(run)
    assert not net.training and not any(p.requires_grad for p in net.parameters())
    z = net.encode(torch.from_numpy(data["vnoisy"][:4]))
    assert z.shape == (4, 3, 16)


@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_same_seed_same_run(data: dict[str, np.ndarray], tmp_path: Path, precision: str) -> None:
    train_fn, val_fn = _fns(data, 64, 16, stratify_from=1)
    train_bnn(_small_cfg(precision=precision), MODEL, train_fn, val_fn, tmp_path / "a", progress=False)
    train_bnn(_small_cfg(precision=precision), MODEL, train_fn, val_fn, tmp_path / "b", progress=False)
    train_bnn(_small_cfg(seed=1, precision=precision), MODEL, train_fn, val_fn, tmp_path / "c", progress=False)
    assert _losses(tmp_path / "a") == _losses(tmp_path / "b")
    a, b, c = (_model_tensors(tmp_path / x) for x in "abc")
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert _losses(tmp_path / "a") != _losses(tmp_path / "c")
    assert not all(torch.equal(a[k], c[k]) for k in a)


class _Interrupted(Exception):
    pass


@pytest.mark.parametrize(("schedule", "precision"), [
    ("constant", "fp32"), ("cosine", "fp32"), ("warmup_cosine", "fp32"), ("warmup_cosine", "bf16")])
def test_resume_continues_to_the_same_result(
    data: dict[str, np.ndarray], tmp_path: Path, schedule: str, precision: str
) -> None:
    train_fn, val_fn = _fns(data, 64, 16, stratify_from=1)
    cfg = _small_cfg(lr_schedule=schedule, precision=precision, val_every=1)
    full = train_bnn(cfg, MODEL, train_fn, val_fn, tmp_path / "full", progress=False)

    def interrupted_fn(epoch: int) -> Iterator[BNNBatch]:
        for i, batch in enumerate(train_fn(epoch)):
            if epoch == 2 and i == 2:
                raise _Interrupted  # mid-epoch, after the epoch-2 checkpoint's steps moved on
            yield batch

    run = tmp_path / "resumed"
    with pytest.raises(_Interrupted):
        train_bnn(cfg, MODEL, interrupted_fn, val_fn, run, progress=False)
    _, state = read_checkpoint(run / "checkpoint.safetensors")
    assert (state["epoch"], state["step"]) == (2, 8)
    # Rows logged after the checkpoint (steps 9, 10) exist until the resume drops them.
    assert max(int(r["step"]) for r in _rows(run)) == 10

    # What the interrupted session had done by its checkpoint is part of the run's cost.
    before = sum(float(r["elapsed_s"]) for r in _rows(run) if r["kind"] == "epoch" and int(r["step"]) <= 8)
    resumed = train_bnn(cfg, MODEL, train_fn, val_fn, run, resume=True, progress=False)
    assert resumed["resumed_s"] == round(before, 2) > 0 and full["resumed_s"] == 0
    for key in ("epoch", "step", "train_loss", "train_recon", "train_reg", "val_loss", "val_mmd",
                "val_vehicle_recall", "val_vehicle_precision"):
        assert resumed[key] == full[key] or (np.isnan(resumed[key]) and np.isnan(full[key])), key
    full_t, res_t = _model_tensors(tmp_path / "full"), _model_tensors(run)
    assert full_t.keys() == res_t.keys()
    assert all(torch.equal(full_t[k], res_t[k]) for k in full_t)
    assert _losses(run) == _losses(tmp_path / "full")
    best_full, _ = read_checkpoint(tmp_path / "full" / train_mod.BEST_NAME)
    best_res, _ = read_checkpoint(run / train_mod.BEST_NAME)
    assert all(torch.equal(best_full[k], best_res[k]) for k in best_full)

    # Resuming a finished run does no more work; extending the schedule continues it.
    again = train_bnn(cfg, MODEL, train_fn, val_fn, run, resume=True, progress=False)
    assert again["step"] == full["step"]
    longer = train_bnn(cfg.replace(mixed_epochs=3), MODEL, train_fn, val_fn, run,
                       resume=True, progress=False)
    assert longer["epoch"] == 4 and longer["step"] == full["step"] + 4


def test_reading_ahead_does_not_change_the_result(data: dict[str, np.ndarray], tmp_path: Path) -> None:
    train_fn, val_fn = _fns(data, 64, 16, stratify_from=1)
    for depth in (0, 3):
        train_bnn(_small_cfg(prefetch=depth), MODEL, train_fn, val_fn, tmp_path / f"p{depth}", progress=False)
    a, b = _model_tensors(tmp_path / "p0"), _model_tensors(tmp_path / "p3")
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    assert _losses(tmp_path / "p0") == _losses(tmp_path / "p3")


def test_run_dir_guards(data: dict[str, np.ndarray], tmp_path: Path) -> None:
    train_fn, _ = _fns(data, 32, 16, stratify_from=1)
    run = tmp_path / "run"
    cfg = _small_cfg(mixed_epochs=0)
    train_bnn(cfg, MODEL, train_fn, None, run, progress=False)
    with pytest.raises(CheckpointError, match="resume=True"):
        train_bnn(cfg, MODEL, train_fn, None, run, progress=False)
    with pytest.raises(CheckpointError, match=r"model config \(latent_dim \(16 → 32\)\)") as exc:
        train_bnn(cfg, MODEL.replace(latent_dim=32), train_fn, None, run, resume=True,
                  progress=False)
    assert str(exc.value).startswith(str(run / "checkpoint.safetensors"))
    with pytest.raises(CheckpointError, match=r"\(lr \(0.003 → 0.0001\)\)"):
        train_bnn(cfg.replace(lr=1e-4), MODEL, train_fn, None, run, resume=True, progress=False)


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.parametrize(("content", "needle"), [
    (b"kind,step\nstep,abc\n", "line 2 of the training log has step 'abc', not a count"),
    (bytes(range(256)) * 4, "not UTF-8"),
    (b"a,b,c\n1,2,3\n", "not a training log"),
])
def test_a_damaged_metrics_log_stops_a_resumption_before_anything_is_written(
    data: dict[str, np.ndarray], tmp_path: Path, content: bytes, needle: str
) -> None:
    train_fn, _ = _fns(data, 32, 16, stratify_from=1)
    run = tmp_path / "run"
    cfg = _small_cfg(mixed_epochs=0)
    train_bnn(cfg, MODEL, train_fn, None, run, progress=False)
    (run / "metrics.csv").write_bytes(content)
    before = _files(run)
    with pytest.raises(FileFormatError, match=re.escape(needle)) as exc:
        train_bnn(cfg.replace(mixed_epochs=1), MODEL, train_fn, None, run, resume=True, progress=False)
    msg = str(exc.value)
    assert msg.startswith(str(run / "metrics.csv")) and "\n" not in msg, msg
    assert _files(run) == before  # config.json and the log as they were


def test_a_resumption_keeps_the_rows_of_an_older_log(data: dict[str, np.ndarray], tmp_path: Path) -> None:
    # A log written before the vehicle metrics existed, cut off in its last row by a kill.
    train_fn, _ = _fns(data, 32, 16, stratify_from=1)
    run = tmp_path / "run"
    cfg = _small_cfg(mixed_epochs=0)
    train_bnn(cfg, MODEL, train_fn, None, run, progress=False)
    (run / "metrics.csv").write_text("kind,step,loss,val_loss\nstep,2,0.5,\nepoch,2,0.4,0.3\nstep,4,0.")
    train_bnn(cfg.replace(mixed_epochs=1), MODEL, train_fn, None, run, resume=True, progress=False)
    rows = _rows(run)
    assert [(r["kind"], r["step"], r["loss"], r["val_loss"]) for r in rows[:2]] == [
        ("step", "2", "0.5", ""), ("epoch", "2", "0.4", "0.3")]
    assert [r["step"] for r in rows[2:]] == ["4", "4"]


def test_a_checkpoint_from_before_a_field_existed_resumes(data: dict[str, np.ndarray], tmp_path: Path) -> None:
    # Regression: a checkpoint whose saved config lacks a field added later (here the LR
    # schedule and the loss) ran with that field's default and must stay resumable.
    train_fn, _ = _fns(data, 32, 16, stratify_from=1)
    run = tmp_path / "run"
    cfg = _small_cfg(mixed_epochs=0)
    train_bnn(cfg, MODEL, train_fn, None, run, progress=False)
    saved = read_checkpoint(run / "checkpoint.safetensors")[1]["config"]
    for key in ("lr_schedule", "lr_final_fraction", "loss"):
        del saved["train"][key]
    check_resumable(run / "checkpoint.safetensors", saved, cfg, MODEL)
    with pytest.raises(CheckpointError, match="lr_schedule"):
        check_resumable(run / "checkpoint.safetensors", saved, cfg.replace(lr_schedule="cosine"), MODEL)
    with pytest.raises(ValueError, match="no batches"):
        train_bnn(cfg, MODEL, lambda epoch: [], None, tmp_path / "empty", progress=False)


def test_train_config_validation() -> None:
    assert BNNTrainConfig().lambda_distance == 0.0
    assert BNNTrainConfig().device == "auto"
    cfg = BNNTrainConfig(pretrain_epochs=2, mixed_epochs=3)
    assert cfg.total_epochs == 5
    assert [cfg.phase(e) for e in range(5)] == ["pretrain"] * 2 + ["mixed"] * 3
    bad: list[tuple[dict[str, object], str]] = [
        ({"device": "gpu"}, "device"), ({"lr": 0}, "lr"),
        ({"lambda_distance": -1}, "lambda_distance"), ({"epochs": 3}, "epochs"),
    ]
    for data, field in bad:
        with pytest.raises(ConfigError, match=field):
            validate(BNNTrainConfig, data)
    assert resolve_device("cpu") == torch.device("cpu")


def test_cosine_schedule_runs_from_lr_down_to_its_final_fraction() -> None:
    cfg = BNNTrainConfig(pretrain_epochs=1, mixed_epochs=4, lr=1e-3, lr_schedule="cosine",
                         lr_final_fraction=0.1)
    lrs = [cfg.epoch_lr(e) for e in range(5)]
    assert lrs[0] == pytest.approx(1e-3) and lrs[-1] == pytest.approx(1e-4)
    assert lrs[2] == pytest.approx(0.55e-3)  # halfway: the mean of the two ends
    assert all(a > b for a, b in itertools.pairwise(lrs))
    assert BNNTrainConfig(lr=2e-3, lr_schedule="constant").epoch_lr(7) == 2e-3


def test_warmup_cosine_is_set_per_step() -> None:
    cfg = BNNTrainConfig(lr=1e-3, lr_schedule="warmup_cosine", warmup_fraction=0.1, lr_final_fraction=0.1)
    lrs = [cfg.step_lr(s, 100) for s in range(100)]
    # Ten warm-up steps up to lr, then down a half cosine to its final fraction.
    assert lrs[0] == pytest.approx(1e-4) and lrs[9] == pytest.approx(1e-3)
    assert all(a < b for a, b in itertools.pairwise(lrs[:10]))
    assert all(a >= b for a, b in itertools.pairwise(lrs[9:]))
    assert lrs[-1] == pytest.approx(1e-4)
    # Past the end it stays at the final rate (a run resumed with fewer epochs).
    assert cfg.step_lr(150, 100) == pytest.approx(1e-4)


def test_vehicle_weight_falls_linearly_over_the_run() -> None:
    cfg = BNNTrainConfig(foreground_weight=20.0, foreground_weight_final=5.0, road_weight=0.3, av_weight=0.5)
    assert cfg.cell_weights(0, 11) == CellWeights(20.0, 0.3, 0.5)
    assert cfg.cell_weights(5, 11).foreground == pytest.approx(12.5)
    assert cfg.cell_weights(10, 11).foreground == pytest.approx(5.0)
    assert BNNTrainConfig(foreground_weight=7.0, foreground_weight_final=None).cell_weights(10, 11).foreground == 7.0


def test_training_follows_the_step_schedules(
    data: dict[str, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    seen: list[float] = []

    def spy(model: BottleneckNetwork, batch: BNNBatch, lam: float, w: CellWeights, loss: LossKind, dice: float):
        seen.append(w.foreground)
        return step_losses(model, batch, lam, w, loss, dice)

    monkeypatch.setattr(train_mod, "step_losses", spy)
    train_fn, _ = _fns(data, 32, 16, stratify_from=1)  # two steps per epoch, six in all
    cfg = _small_cfg(lambda_distance=0.0, log_every=1, foreground_weight=11.0, foreground_weight_final=1.0)
    train_bnn(cfg, MODEL, train_fn, None, tmp_path / "run", progress=False)
    assert seen == pytest.approx([11.0, 9.0, 7.0, 5.0, 3.0, 1.0])
    logged = [float(r["lr"]) for r in _rows(tmp_path / "run") if r["kind"] == "step"]
    assert logged == pytest.approx([cfg.step_lr(s, 6) for s in range(6)])


def test_training_uses_the_scheduled_lr(data: dict[str, np.ndarray], tmp_path: Path) -> None:
    train_fn, _val_fn = _fns(data, 32, 16, stratify_from=1)
    cfg = _small_cfg(lr_schedule="cosine", lr_final_fraction=0.2, lambda_distance=0.0)
    train_bnn(cfg, MODEL, train_fn, None, tmp_path / "run", progress=False)
    logged = [float(r["lr"]) for r in _rows(tmp_path / "run") if r["kind"] == "epoch"]
    assert logged == pytest.approx([cfg.epoch_lr(e) for e in range(3)])
    assert logged[-1] == pytest.approx(0.2 * cfg.lr)


def test_run_restores_torch_settings(data: dict[str, np.ndarray], tmp_path: Path) -> None:
    threads = torch.get_num_threads()
    det = torch.are_deterministic_algorithms_enabled()
    train_fn, _ = _fns(data, 16, 16, stratify_from=1)
    cfg = _small_cfg(pretrain_epochs=1, mixed_epochs=0, num_threads=threads + 1)
    train_bnn(cfg, MODEL, train_fn, None, tmp_path / "run", progress=False)
    assert torch.get_num_threads() == threads
    assert torch.are_deterministic_algorithms_enabled() == det


# ---------------------------------------------------------------------------------------
# Batches


def test_stratified_batches_hold_every_scenario(data: dict[str, np.ndarray]) -> None:
    fn = array_batches_fn(data["clean"], data["noisy"], data["scenario"],
                          batch_size=16, seed=3, stratify_from_epoch=1)
    mixed = list(fn(1))
    assert sum(b.noisy.shape[0] for b in mixed) == 320
    assert all(len(torch.unique(b.scenario)) == 3 for b in mixed)
    seen = torch.cat([b.clean for b in mixed])
    assert seen.shape == (320, *SHAPE)
    # Each epoch's batches depend on (seed, epoch) only.
    again = list(fn(1))
    assert all(torch.equal(a.noisy, b.noisy) for a, b in zip(mixed, again, strict=True))
    assert not torch.equal(next(iter(fn(2))).noisy, mixed[0].noisy)
    first = next(iter(fn(0)))
    assert first.noisy.dtype == torch.float32 and first.scenario.dtype == torch.int64


def test_synthetic_dataset() -> None:
    clean, noisy, scenario = synthetic_dataset(12, SHAPE, 3, seed=5)
    assert clean.shape == noisy.shape == (12, *SHAPE) and scenario.shape == (12,)
    assert clean.dtype == noisy.dtype == np.float32
    assert 0.0 <= clean.min() and clean.max() <= 1.0 and 0.0 <= noisy.min() and noisy.max() <= 1.0
    assert not np.array_equal(clean, noisy)
    again = synthetic_dataset(12, SHAPE, 3, seed=5)
    assert np.array_equal(again[0], clean) and np.array_equal(again[1], noisy)


def test_the_best_validated_weights_are_the_ones_loaded(
    data: dict[str, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # Scores that fall after the first validation: the first validated epoch is the best.
    scores = iter([0.9, 0.5, 0.7])
    monkeypatch.setattr(train_mod, "validation_score", lambda m: next(scores))
    train_fn, val_fn = _fns(data, 32, 16, stratify_from=1)
    cfg = _small_cfg(pretrain_epochs=1, mixed_epochs=4, lambda_distance=0.0, val_every=2)
    run = tmp_path / "run"
    train_bnn(cfg, MODEL, train_fn, val_fn, run, progress=False)
    epochs = [r for r in _rows(run) if r["kind"] == "epoch"]
    # Validated after epochs 2 and 4 and after the last one (5).
    validated = [i + 1 for i, r in enumerate(epochs) if r["val_loss"] not in ("", "nan")]
    assert validated == [2, 4, 5]
    best, meta = read_checkpoint(run / train_mod.BEST_NAME)
    assert meta["epoch"] == 2
    last, _ = read_checkpoint(run / "checkpoint.safetensors")
    net = load_trained_bottleneck(run)
    for name, t in net.state_dict().items():
        assert torch.equal(t, best[f"model/{name}"])
    assert any(not torch.equal(best[k], last[k]) for k in best)


def test_validation_score_is_the_f1_of_recall_and_precision() -> None:
    assert train_mod.validation_score({"val_vehicle_recall": 0.9, "val_vehicle_precision": 0.6}) == pytest.approx(0.72)
    assert train_mod.validation_score({"val_vehicle_recall": float("nan"), "val_vehicle_precision": 0.6}) == -math.inf
    assert train_mod.validation_score({"val_vehicle_recall": 0.0, "val_vehicle_precision": 0.0}) == -math.inf


@pytest.mark.parametrize(("val_samples", "scored"), [(0, 96), (70, 70), (500, 96)])
def test_val_samples_caps_the_samples_each_validation_scores(
    data: dict[str, np.ndarray], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    val_samples: int, scored: int,
) -> None:
    seen: list[int] = []
    real = train_mod.evaluate_bnn

    def counting(model, batches, *args, **kwargs):
        batches = list(batches)
        seen.append(sum(int(b.noisy.shape[0]) for b in batches))
        return real(model, batches, *args, **kwargs)

    monkeypatch.setattr(train_mod, "evaluate_bnn", counting)
    train_fn, val_fn = _fns(data, 32, 16, stratify_from=1)
    # The validation batches are 48 samples each, 96 in all: a cap of 70 cuts the second.
    cfg = _small_cfg(pretrain_epochs=1, mixed_epochs=1, lambda_distance=0.0, val_every=1, val_samples=val_samples)
    train_bnn(cfg, MODEL, train_fn, val_fn, tmp_path / "run", progress=False)
    assert seen == [scored, scored]


def test_an_epoch_not_validated_says_so_rather_than_printing_nan(
    data: dict[str, np.ndarray], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Regression: epochs between validations printed ``val nan (... recall nan ...)``."""
    train_fn, val_fn = _fns(data, 32, 16, stratify_from=1)
    train_bnn(_small_cfg(val_every=2, precision="fp32"), MODEL, train_fn, val_fn, tmp_path / "run", progress=True)
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("epoch ")]
    assert len(lines) == 3
    assert "not validated (every 2 epochs and the last)" in lines[0]
    assert "recall" in lines[1] and "recall" in lines[2]
    assert "nan" not in lines[0]  # (a validated line may say precision nan: nothing drawn)
