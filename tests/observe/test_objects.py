"""The vehicles a map shows, found by rule (``latentdrive.observe.objects``): literal cases."""

import pytest
import torch
import torch.nn.functional as F

from latentdrive.observe.objects import PER_OBJECT, _max3x3, label_blobs, map_objects
from latentdrive.observe.velocitymap import AV, HV, MV, RL

# A 16 × 32 grid of 1.5 m cells seeing 12 m behind: cell (i, j) is centred
# (j + ½)·1.5 − 12 m ahead of the observer and (i + ½)·1.5 − 12 m to its right.
RES, BEHIND, H, W = 1.5, 12.0, 16, 32


def _maps(n: int = 1, t: int = 2) -> torch.Tensor:
    return torch.zeros(n, 4, t, H, W)


def test_a_vehicle_is_its_blobs_place_value_kind_and_size() -> None:
    x = _maps()
    x[0, HV, -1, 8:10, 10:13] = 0.6  # rows 8-9, columns 10-12: centre row 8.5, column 11
    x[0, AV, -1, 2, 20:22] = 0.4  # row 2, columns 20-21: centre row 2, column 20.5
    rows = map_objects(x, RES, BEHIND, 3)
    assert rows.shape == (1, 3, PER_OBJECT)
    hv = [(11.5 * 1.5 - 12.0) / 50, (9.0 * 1.5 - 12.0) / 50, 0.6, 0.0, 0.6, 1.0]  # 5.25 m ahead, 1.5 m right
    av = [(21.0 * 1.5 - 12.0) / 50, (2.5 * 1.5 - 12.0) / 50, 0.4, 1.0, 0.2, 1.0]  # 19.5 m ahead, 8.25 m left
    torch.testing.assert_close(rows[0], torch.tensor([hv, av, [0.0] * PER_OBJECT]))


def test_nearest_first_and_only_k_of_them() -> None:
    x = _maps()
    for col in (30, 9, 20):  # 33.75, 2.25 and 18.75 m ahead, on the observer's line
        x[0, HV, -1, 7:9, col] = 1.0
    rows = map_objects(x, RES, BEHIND, 2)
    torch.testing.assert_close(rows[0, :, 0] * 50, torch.tensor([2.25, 18.75]))
    assert map_objects(x, RES, BEHIND, 5)[0, :, -1].tolist() == [1.0, 1.0, 1.0, 0.0, 0.0]


def test_only_the_newest_frame_and_no_blob_across_channels_or_observations() -> None:
    x = _maps(n=2, t=3)
    x[0, HV, -1, 4:6, 4:6] = 1.0
    x[0, AV, -1, 4:6, 6:8] = 1.0  # touches the HV car, in another channel: two vehicles
    x[0, HV, -2, 10:12, 20:22] = 1.0  # an older frame: not read
    x[0, RL] = 1.0  # the road and the observer's own channel hold no vehicles
    x[0, MV, -1, 7:9, 7:10] = 1.0
    x[1, HV, -1, 0, 0] = 1.0
    x[1, HV, -1, 1, 1] = 1.0  # diagonal neighbours: one blob of two cells
    rows = map_objects(x, RES, BEHIND, 4)
    assert rows[0, :, -1].tolist() == [1.0, 1.0, 0.0, 0.0]
    assert sorted(rows[0, :2, 3].tolist()) == [0.0, 1.0]
    assert rows[1, :, -1].tolist() == [1.0, 0.0, 0.0, 0.0]
    assert rows[1, 0, 4].item() == pytest.approx(0.2)


def test_an_empty_map_reads_no_vehicle() -> None:
    assert torch.equal(map_objects(_maps(n=3), RES, BEHIND, 4), torch.zeros(3, 4, PER_OBJECT))


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="expected maps"):
        map_objects(torch.zeros(1, 3, 2, H, W), RES, BEHIND, 4)
    with pytest.raises(ValueError, match="k must be"):
        map_objects(_maps(), RES, BEHIND, 0)
    with pytest.raises(ValueError, match="expected masks"):
        label_blobs(torch.zeros(H, W, dtype=torch.bool))


def test_the_3x3_maximum_is_max_pooling() -> None:
    x = torch.rand(6, 1, 9, 13, generator=torch.Generator().manual_seed(0))
    assert torch.equal(_max3x3(x), F.max_pool2d(x, 3, stride=1, padding=1))
