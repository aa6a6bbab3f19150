"""Random-shift augmentation (dqn.augment_shift): literal shifts, edges, config and runs."""

import numpy as np
import pytest
import torch
from safetensors.numpy import load_file

from latentdrive.config import ConfigError, validate
from latentdrive.rl.augment import random_shift
from latentdrive.rl.config import PolicyTrainConfig
from latentdrive.rl.policy import CHECKPOINT
from latentdrive.rl.train import train_policy


def _offsets(seed: int, b: int, pad: int) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2 * pad + 1, size=(b, 2))


def test_a_vehicle_cell_moves_by_the_drawn_shift_in_every_channel_and_frame():
    b, pad = 16, 2
    maps = torch.zeros(b, 4, 3, 12, 20)
    maps[:, :, :, 6, 9] = 1.0  # one bright cell, away from the edges
    out = random_shift(maps, pad, np.random.default_rng(5))
    for i, (oy, ox) in enumerate(_offsets(5, b, pad)):
        # The window starts oy rows into the padded map: the cell lands at 6 + pad - oy.
        want = torch.zeros(4, 3, 12, 20)
        want[:, :, 6 + pad - oy, 9 + pad - ox] = 1.0
        assert torch.equal(out[i], want), i
    assert len({tuple(o) for o in _offsets(5, b, pad)}) > 1  # the maps did not all move alike


def test_cells_shifted_in_from_outside_repeat_the_edge():
    maps = torch.arange(4 * 5, dtype=torch.float32).reshape(1, 1, 1, 4, 5)
    # A seed whose draw moves the map down and right by the full pad.
    seed = next(s for s in range(1000) if tuple(_offsets(s, 1, 1)[0]) == (0, 0))
    out = random_shift(maps, 1, np.random.default_rng(seed))[0, 0, 0]
    assert torch.equal(out[1:, 1:], maps[0, 0, 0, :-1, :-1])
    assert torch.equal(out[0, 1:], maps[0, 0, 0, 0, :-1])  # the top row repeated
    assert torch.equal(out[1:, 0], maps[0, 0, 0, :-1, 0])  # the left column repeated


def test_no_pad_returns_the_maps_and_draws_nothing():
    maps = torch.rand(3, 4, 2, 8, 8)
    rng = np.random.default_rng(1)
    assert random_shift(maps, 0, rng) is maps
    assert rng.integers(1 << 30) == np.random.default_rng(1).integers(1 << 30)


@pytest.mark.parametrize("mode", ["latent", "latent-random"])
def test_modes_that_learn_from_latents_refuse_it(mode):
    with pytest.raises(ConfigError, match="augment_shift shifts maps"):
        validate(PolicyTrainConfig, {"mode": mode, "bnn": "x" if mode == "latent" else None,
                                     "dqn": {"augment_shift": 2}})


def test_an_augmented_run_is_deterministic_and_differs_from_an_unaugmented_one(tmp_path, tiny):
    def weights(name, **dqn):
        cfg = tiny(mode="raw", steps=200, dqn={"augment_shift": 1, **dqn})
        train_policy(cfg, tmp_path / name, progress=False, say=lambda _line: None)
        return {k: v for k, v in load_file(str(tmp_path / name / CHECKPOINT)).items() if k.startswith("model/")}

    a, b, plain = weights("a"), weights("b"), weights("plain", augment_shift=0)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    assert not all(np.array_equal(a[k], plain[k]) for k in a)


def test_the_update_learns_from_shifted_observations_and_next_observations(tmp_path, tiny, monkeypatch):
    import latentdrive.rl.learner as learner_module

    real_update, seen = learner_module.update, []

    def marked_shift(maps, pad, rng):
        assert pad == 1
        return random_shift(maps, pad, rng) + 1000.0  # a mark no real map cell carries

    def spying_update(online, target, optimizer, batch, cfg, dtype, **kwargs):
        seen.append((float(batch.obs.min()), float(batch.next_obs.min())))
        return real_update(online, target, optimizer, batch, cfg, dtype, **kwargs)

    monkeypatch.setattr(learner_module, "random_shift", marked_shift)
    monkeypatch.setattr(learner_module, "update", spying_update)
    train_policy(tiny(mode="raw", steps=120, dqn={"augment_shift": 1, "learning_starts": 40}), tmp_path / "run",
                 progress=False, say=lambda _line: None)
    assert seen and all(obs >= 1000.0 and nxt >= 1000.0 for obs, nxt in seen)
