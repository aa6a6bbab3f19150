"""The objects reader (``vfan.reader: objects``): shapes, what it reads, and refusals."""

import pytest
import torch

from latentdrive.config import ConfigError, validate
from latentdrive.models.objects import ObjectsBody
from latentdrive.models.vfan import QNetwork, VFANConfig
from latentdrive.observe.velocitymap import AV, HV, MV, RL
from latentdrive.rl.config import PolicyTrainConfig

SHAPE = (4, 2, 16, 32)
GEOMETRY = (1.5, 12.0)


def _net() -> QNetwork:
    torch.manual_seed(0)
    return QNetwork(VFANConfig(reader="objects", hidden=32, attention_width=16, objects_k=4), "raw", SHAPE,
                    geometry=GEOMETRY)


@pytest.mark.parametrize("vfan", [{}, {"objects_frames": 2, "objects_layers": 2}])
def test_q_values_and_gradients_reach_every_layer(vfan: dict) -> None:
    torch.manual_seed(0)
    net = QNetwork(VFANConfig(reader="objects", hidden=32, attention_width=16, objects_k=4, **vfan), "raw", SHAPE,
                   geometry=GEOMETRY)
    x = torch.zeros(5, *SHAPE)
    x[:, HV, -1, 3:5, 20:23] = 0.7
    x[:, AV, 0, 10:12, 5:8] = 0.5  # an older frame's vehicle: the age embedding's second row reads it
    x[:, RL, -1] = 1.0
    x[:, MV, :, 7:9, 7:10] = 0.3
    q = net(net.features(x))
    assert q.shape == (5, 5)
    q.sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())


def test_it_reads_the_newest_vehicles_the_two_newest_speeds_and_the_newest_road() -> None:
    shape = (4, 3, 16, 32)
    torch.manual_seed(0)
    net = QNetwork(VFANConfig(reader="objects", hidden=32, attention_width=16, objects_k=4), "raw", shape,
                   geometry=GEOMETRY).eval()
    x = torch.zeros(1, *shape)
    x[0, RL, :, 6:10] = 1.0
    base = net(net.features(x))

    def changed(frame: int, channel: int, rows: slice, cols: slice, value: float) -> torch.Tensor:
        y = x.clone()
        y[0, channel, frame, rows, cols] = value
        return net(net.features(y))

    assert not torch.allclose(changed(-1, HV, slice(7, 9), slice(10, 13), 0.9), base)  # a vehicle
    assert not torch.allclose(changed(-1, MV, slice(7, 9), slice(7, 10), 0.5), base)  # speed now
    assert not torch.allclose(changed(-2, MV, slice(7, 9), slice(7, 10), 0.5), base)  # speed a step ago
    assert not torch.allclose(changed(-1, RL, slice(0, 4), slice(0, 32), 1.0), base)  # more road
    # Not read: an older frame's vehicle, the speed two steps ago, an older frame's road.
    assert torch.equal(changed(0, HV, slice(7, 9), slice(10, 13), 0.9), base)
    assert torch.equal(changed(0, MV, slice(7, 9), slice(7, 10), 0.5), base)
    assert torch.equal(changed(0, RL, slice(0, 4), slice(0, 32), 1.0), base)


def test_features_are_the_speeds_the_pooled_road_and_the_vehicle_rows() -> None:
    net = _net()
    x = torch.zeros(2, *SHAPE)
    x[:, RL, -1, 4:8] = 1.0
    x[0, MV, -1, 7:9, 7:10] = 0.3
    x[0, MV, -2, 7:9, 7:10] = 0.25
    x[1, AV, -1, 3:5, 20:23] = 0.7
    f = net.features(x)
    assert f.dtype == torch.float32 and f.shape == (2, net.stored_shape[0]) == (2, 2 + 4 * 8 + 4 * 6)
    torch.testing.assert_close(f[0, :2], torch.tensor([0.25, 0.3]))
    # 4 × 4 blocks: rows 4-7 of the road are the second row of blocks, all road.
    torch.testing.assert_close(f[:, 2:34].reshape(2, 4, 8)[:, 1], torch.ones(2, 8))
    assert f[:, 2:34].reshape(2, 4, 8)[:, [0, 2, 3]].sum() == 0
    rows = f[:, 34:].reshape(2, 4, 6)
    assert rows[0, :, -1].sum() == 0 and rows[1, :, -1].tolist() == [1.0, 0.0, 0.0, 0.0]
    torch.testing.assert_close(rows[1, 0, 2:5], torch.tensor([0.7, 1.0, 0.6]))


def test_with_objects_frames_it_reads_each_newer_frames_vehicles_marked_by_age() -> None:
    shape = (4, 3, 16, 32)
    torch.manual_seed(0)
    net = QNetwork(VFANConfig(reader="objects", hidden=32, attention_width=16, objects_k=4, objects_frames=2), "raw",
                   shape, geometry=GEOMETRY).eval()
    torch.nn.init.normal_(net.body.age)  # trained ages differ; zeros would hide the frame
    x = torch.zeros(1, *shape)
    x[0, RL, :, 6:10] = 1.0
    x[0, HV, -1, 2:4, 3:6] = 0.7  # in the newest frame
    x[0, AV, -2, 12:14, 20:23] = 0.4  # a frame older
    f = net.features(x)
    assert f.shape == (1, 2 + 4 * 8 + 2 * 4 * 6)
    rows = f[0, 34:].reshape(2, 4, 6)  # newest frame's rows first
    assert rows[:, :, -1].tolist() == [[1, 0, 0, 0], [1, 0, 0, 0]]
    assert rows[0, 0, 3] == 0 and rows[1, 0, 3] == 1  # the HV now, the AV a frame ago
    base = net(f)

    def changed(frame: int) -> torch.Tensor:
        y = x.clone()
        y[0, HV, frame, 9:11, 25:28] = 0.9
        return net(net.features(y))

    assert not torch.allclose(changed(-1), base) and not torch.allclose(changed(-2), base)
    assert torch.equal(changed(0), base)  # the oldest frame is not read
    # The same vehicle read as one frame old rather than new: its age changes the Q-values.
    older = torch.cat([f[:, :34], rows.flip(0).reshape(1, -1)], dim=1)
    assert not torch.allclose(net(older), base)


@pytest.mark.parametrize("layers", [0, 1])
def test_padding_rows_are_not_read(layers: int) -> None:
    # The weights do not depend on k: with at most four vehicles in view, reading four or
    # nine rows must give the same Q-values (the five extra rows are padding), with or
    # without self-attention among the rows.
    torch.manual_seed(0)
    four = ObjectsBody(SHAPE, *GEOMETRY, k=4, width=16, hidden=32, layers=layers).eval()
    nine = ObjectsBody(SHAPE, *GEOMETRY, k=9, width=16, hidden=32, layers=layers).eval()
    nine.load_state_dict(four.state_dict())
    x = torch.zeros(3, *SHAPE)
    x[:, RL, -1, 6:10] = 1.0
    x[0, HV, -1, 2:4, 3:6] = 0.7
    x[1, HV, -1, 2:4, 3:6] = 0.7
    x[1, AV, -1, 12:14, 20:23] = 0.4
    torch.testing.assert_close(four(four.features(x)), nine(nine.features(x)))


def test_the_reader_is_refused_where_it_cannot_read() -> None:
    with pytest.raises(ValueError, match="needs the map's geometry"):
        QNetwork(VFANConfig(reader="objects"), "raw", SHAPE)
    with pytest.raises(ValueError, match="no dueling head"):
        QNetwork(VFANConfig(reader="objects"), "raw", SHAPE, dueling=True, geometry=GEOMETRY)
    with pytest.raises(ValueError, match="at least 2 frames"):
        ObjectsBody((4, 1, 16, 32), *GEOMETRY)
    with pytest.raises(ValueError, match="multiples of 4"):
        ObjectsBody((4, 2, 18, 32), *GEOMETRY)
    with pytest.raises(ValueError, match="1 to 2 frames"):
        ObjectsBody((4, 2, 16, 32), *GEOMETRY, frames=3)
    with pytest.raises(ConfigError, match="objects_frames=5 reads more frames"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "objects", "objects_frames": 5}})
    with pytest.raises(ConfigError, match="reads raw maps"):
        validate(PolicyTrainConfig, {"mode": "end-to-end", "vfan": {"reader": "objects"}})
    with pytest.raises(ConfigError, match="augment_shift"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "objects"}, "dqn": {"augment_shift": 2}})
    with pytest.raises(ConfigError, match="dueling"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "objects"}, "dqn": {"dueling": True}})
    with pytest.raises(ConfigError, match="route"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "objects"}, "observation": {"route": 0.8}})
    with pytest.raises(ConfigError, match=r"observation\.frames"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "objects"}, "observation": {"frames": 1}})
    with pytest.raises(ConfigError, match="multiples of 4"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "objects"}, "observation": {"height": 18}})
    with pytest.raises(ConfigError, match="objects_layers"):
        validate(VFANConfig, {"reader": "objects", "objects_layers": -1})
    with pytest.raises(ConfigError, match="objects_k"):
        validate(VFANConfig, {"reader": "objects", "objects_k": 0})
