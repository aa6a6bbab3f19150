"""The objects reader (``vfan.reader: objects``): shapes, what it reads, and refusals."""

import pytest
import torch

from latentdrive.config import ConfigError, validate
from latentdrive.models.objects import ObjectsBody
from latentdrive.models.vfan import QNetwork, VFANConfig
from latentdrive.observe.velocitymap import HV, MV, RL
from latentdrive.rl.config import PolicyTrainConfig

SHAPE = (4, 2, 16, 32)
GEOMETRY = (1.5, 12.0)


def _net() -> QNetwork:
    torch.manual_seed(0)
    return QNetwork(VFANConfig(reader="objects", hidden=32, attention_width=16, objects_k=4), "raw", SHAPE,
                    geometry=GEOMETRY)


def test_q_values_and_gradients_reach_every_layer() -> None:
    net = _net()
    x = torch.zeros(5, *SHAPE)
    x[:, HV, -1, 3:5, 20:23] = 0.7
    x[:, RL, -1] = 1.0
    x[:, MV, :, 7:9, 7:10] = 0.3
    q = net(x)
    assert q.shape == (5, 5)
    q.sum().backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in net.parameters())


def test_it_reads_the_vehicles_speed_and_road_and_nothing_else() -> None:
    net = _net().eval()
    x = torch.zeros(1, *SHAPE)
    x[0, RL, -1, 6:10] = 1.0
    base = net(x)
    car = x.clone()
    car[0, HV, -1, 7:9, 10:13] = 0.9
    fast = x.clone()
    fast[0, MV, -1, 7:9, 7:10] = 0.5
    older = x.clone()
    older[0, HV, 0, 7:9, 10:13] = 0.9  # an older frame's vehicle: not read
    assert not torch.allclose(net(car), base)
    assert not torch.allclose(net(fast), base)
    assert torch.equal(net(older), base)


def test_the_reader_is_refused_where_it_cannot_read() -> None:
    with pytest.raises(ValueError, match="needs the map's geometry"):
        QNetwork(VFANConfig(reader="objects"), "raw", SHAPE)
    with pytest.raises(ValueError, match="no dueling head"):
        QNetwork(VFANConfig(reader="objects"), "raw", SHAPE, dueling=True, geometry=GEOMETRY)
    with pytest.raises(ValueError, match="at least 2 frames"):
        ObjectsBody((4, 1, 16, 32), *GEOMETRY)
    with pytest.raises(ValueError, match="multiples of 4"):
        ObjectsBody((4, 2, 18, 32), *GEOMETRY)
    with pytest.raises(ConfigError, match="reads raw maps"):
        validate(PolicyTrainConfig, {"mode": "end-to-end", "vfan": {"reader": "objects"}})
    with pytest.raises(ConfigError, match="augment_shift"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "objects"}, "dqn": {"augment_shift": 2}})
    with pytest.raises(ConfigError, match="dueling"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "objects"}, "dqn": {"dueling": True}})
    with pytest.raises(ConfigError, match="objects_k"):
        validate(VFANConfig, {"reader": "objects", "objects_k": 0})
