"""One writer per output directory: the lock, and collect / train-bnn refusing a held one."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from latentdrive.bnn.batch import array_batches_fn, synthetic_dataset
from latentdrive.bnn.train import BNNTrainConfig, train_bnn
from latentdrive.config import LatentDriveError
from latentdrive.models.bottleneck import BottleneckConfig
from latentdrive.runlock import LOCK_NAME, DirectoryInUse, dir_lock


def test_a_held_directory_is_refused_with_the_holder(tmp_path: Path) -> None:
    with dir_lock(tmp_path / "d", "collect"):
        with pytest.raises(DirectoryInUse) as err:
            with dir_lock(tmp_path / "d", "collect"):
                pass
        msg = str(err.value)
        assert str(tmp_path / "d") in msg and "pid" in msg and "\n" not in msg
    with dir_lock(tmp_path / "d", "collect"):  # released: free again
        pass


def test_a_file_is_not_a_directory(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(LatentDriveError, match="not a directory"):
        with dir_lock(tmp_path / "f", "collect"):
            pass


def test_a_killed_holder_leaves_no_stale_lock(tmp_path: Path) -> None:
    d = tmp_path / "d"
    holder = subprocess.Popen(
        [sys.executable, "-c", textwrap.dedent(f"""
            import sys, time
            from latentdrive.runlock import dir_lock
            with dir_lock({str(d)!r}, "collect"):
                print("held", flush=True)
                time.sleep(60)
        """)],
        stdout=subprocess.PIPE, text=True,
    )
    try:
        assert holder.stdout is not None and holder.stdout.readline().strip() == "held"
        with pytest.raises(DirectoryInUse, match=f"pid {holder.pid}"):
            with dir_lock(d, "collect"):
                pass
    finally:
        holder.kill()
        holder.wait()
    with dir_lock(d, "collect"):
        assert (d / LOCK_NAME).exists()


def test_training_refuses_a_run_directory_in_use(tmp_path: Path) -> None:
    clean, noisy, scenario = synthetic_dataset(8, (4, 1, 8, 8), 2, seed=0)
    fn = array_batches_fn(clean, noisy, scenario, batch_size=4, seed=0)
    cfg = BNNTrainConfig(pretrain_epochs=1, mixed_epochs=0, num_threads=1)
    model = BottleneckConfig(input_shape=(1, 8, 8), latent_dim=2, channels=(2,))
    run = tmp_path / "run"
    with dir_lock(run, "train-bnn"):
        with pytest.raises(DirectoryInUse, match="train-bnn"):
            train_bnn(cfg, model, fn, None, run, progress=False)
    assert not (run / "checkpoint.safetensors").exists()
    assert np.isfinite(train_bnn(cfg, model, fn, None, run, progress=False)["train_loss"])
