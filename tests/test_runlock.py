"""One writer per output directory: the lock, and collect / train-bnn refusing a held one."""

from __future__ import annotations

import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from helpers import held_by_another_process

from latentdrive.bnn.batch import array_batches_fn, synthetic_dataset
from latentdrive.bnn.train import BNNTrainConfig, train_bnn
from latentdrive.config import LatentDriveError
from latentdrive.models.bottleneck import BottleneckConfig
from latentdrive.runlock import LOCK_NAME, UNKNOWN, DirectoryInUse, dir_lock, holder


def test_a_held_directory_is_refused_with_the_holder(tmp_path: Path) -> None:
    d = tmp_path / "d"
    with held_by_another_process(d, "train-bnn") as holder:
        with pytest.raises(DirectoryInUse) as err:
            with dir_lock(d, "collect"):
                pass
    msg = str(err.value)
    assert msg.startswith(str(d)) and f"train-bnn (pid {holder.pid})" in msg and "\n" not in msg
    # The holder was killed: no stale lock is left behind.
    with dir_lock(d, "collect"):
        assert (d / LOCK_NAME).read_text().startswith("collect (pid ")


def test_the_holder_is_read_without_taking_or_writing_the_lock(tmp_path: Path) -> None:
    assert holder(tmp_path) is None and not (tmp_path / LOCK_NAME).exists()  # never locked, and still not
    with held_by_another_process(tmp_path, "reproduce") as child:
        before = (tmp_path / LOCK_NAME).read_bytes()
        assert holder(tmp_path) == f"reproduce (pid {child.pid})"
        assert (tmp_path / LOCK_NAME).read_bytes() == before
    assert holder(tmp_path) is None  # released when its holder ended
    with dir_lock(tmp_path, "collect"):  # the probe left it free to take
        pass
    weird = tmp_path / "weird"
    (weird / LOCK_NAME).mkdir(parents=True)
    assert holder(weird) == UNKNOWN


def test_a_probe_of_the_lock_does_not_refuse_a_run_starting_at_that_instant(tmp_path: Path) -> None:
    import fcntl

    with dir_lock(tmp_path, "collect"):
        pass
    with (tmp_path / LOCK_NAME).open() as probe:  # as holder() holds it for an instant
        fcntl.flock(probe.fileno(), fcntl.LOCK_SH | fcntl.LOCK_NB)
        timer = threading.Timer(0.1, lambda: fcntl.flock(probe.fileno(), fcntl.LOCK_UN))
        timer.start()
        with dir_lock(tmp_path, "reproduce"):  # waits the probe out
            pass
        timer.join()


def test_the_lock_is_reentrant_within_a_process(tmp_path: Path) -> None:
    d = tmp_path / "d"
    with dir_lock(d, "bnn-study"), dir_lock(d, "train-bnn"):
        pass
    with held_by_another_process(d):  # fully released after the outer block
        with pytest.raises(DirectoryInUse):
            with dir_lock(d, "collect"):
                pass


def test_a_file_is_not_a_directory(tmp_path: Path) -> None:
    (tmp_path / "f").write_text("x")
    with pytest.raises(LatentDriveError, match="not a directory"):
        with dir_lock(tmp_path / "f", "collect"):
            pass


def test_training_refuses_a_run_directory_in_use(tmp_path: Path) -> None:
    clean, noisy, scenario = synthetic_dataset(8, (4, 1, 8, 8), 2, seed=0)
    fn = array_batches_fn(clean, noisy, scenario, batch_size=4, seed=0)
    cfg = BNNTrainConfig(pretrain_epochs=1, mixed_epochs=0, num_threads=1)
    model = BottleneckConfig(input_shape=(1, 8, 8), latent_dim=2, channels=(2,))
    run = tmp_path / "run"
    with held_by_another_process(run, "train-bnn"):
        with pytest.raises(DirectoryInUse, match="train-bnn"):
            train_bnn(cfg, model, fn, None, run, progress=False)
    assert sorted(p.name for p in run.iterdir()) == [LOCK_NAME]
    assert np.isfinite(train_bnn(cfg, model, fn, None, run, progress=False)["train_loss"])


@pytest.mark.skipif(sys.platform == "win32", reason="turns are flock, POSIX only")
def test_a_turn_is_taken_by_one_holder_at_a_time(tmp_path):
    """``Turn``: the second taker waits until the first passes it on, wherever it does."""
    import threading
    import time

    from latentdrive.runlock import Turn

    first, second = Turn(tmp_path / "turn.lock"), Turn(tmp_path / "turn.lock")
    order: list[str] = []
    first.acquire()

    def take() -> None:
        with second:
            order.append("second")

    t = threading.Thread(target=take)
    t.start()
    time.sleep(0.3)
    order.append("first releases")
    first.release()
    t.join(10)
    assert order == ["first releases", "second"]
    first.release()  # releasing what is not held does nothing
