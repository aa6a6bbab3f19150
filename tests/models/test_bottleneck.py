"""The bottleneck network: shapes, channel pairs, shared weights, config validation."""

from __future__ import annotations

import pytest
import torch

from latentdrive.config import ConfigError, ObservationConfig, validate
from latentdrive.models.bottleneck import (
    PAIR_CHANNELS,
    BottleneckConfig,
    BottleneckNetwork,
    PairAutoencoder,
    SpatialBroadcast,
    channel_pairs,
)

SMALL = {"input_shape": (2, 16, 32), "channels": (8, 16, 16)}


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _net(**fields: object) -> BottleneckNetwork:
    torch.manual_seed(0)
    return BottleneckNetwork(BottleneckConfig.model_validate({**SMALL, **fields}))


@pytest.mark.parametrize("d", [16, 32, 64])
def test_shapes_for_each_latent_size(d: int) -> None:
    net = _net(latent_dim=d)
    x = torch.rand(5, 4, 2, 16, 32)
    z = net.encode(x)
    recon, latents = net(x)
    assert z.shape == (5, 3, d) == latents.shape
    assert net.latent_shape == (3, d) and net.latent_size == 3 * d
    assert recon.shape == (5, 3, 2, 2, 16, 32)
    assert net.pairs(x).shape == recon.shape
    assert recon.min() >= 0.0 and recon.max() <= 1.0
    # Default sigmoid latents lie in [0, 1].
    assert latents.min() >= 0.0 and latents.max() <= 1.0
    assert torch.equal(z, latents)


@pytest.mark.parametrize("shape", [(1, 8, 8), (3, 9, 13), (4, 32, 64), (5, 17, 40)])
def test_reconstruction_matches_any_input_shape(shape: tuple[int, int, int]) -> None:
    net = BottleneckNetwork(BottleneckConfig(input_shape=shape, latent_dim=16, channels=(4, 8, 8)))
    x = torch.rand(2, 4, *shape)
    recon, z = net(x)
    assert recon.shape == (2, 3, 2, *shape)
    assert z.shape == (2, 3, 16)


def test_pairs_are_hv_av_rl_av_mv_av() -> None:
    # Channel c holds the constant c, so each pair's values name its channels.
    x = torch.arange(4.0).view(1, 4, 1, 1, 1).expand(2, 4, 2, 8, 8).contiguous()
    p = channel_pairs(x)
    assert p.shape == (2, 3, 2, 2, 8, 8)
    for k, (a, b) in enumerate(PAIR_CHANNELS):
        assert torch.all(p[:, k, 0] == a)
        assert torch.all(p[:, k, 1] == b)
    assert [pair for pair in PAIR_CHANNELS] == [(0, 1), (2, 1), (3, 1)]


def test_weights_are_shared_between_pairs() -> None:
    net = _net(latent_dim=16)
    single = PairAutoencoder(net.cfg)
    net_params = dict(net.named_parameters())
    ae_params = dict(single.named_parameters())
    # Exactly one pair autoencoder's parameters, nothing per pair.
    assert sorted(net_params) == sorted(f"autoencoder.{n}" for n in ae_params)
    assert {n: p.shape for n, p in net_params.items()} == {
        f"autoencoder.{n}": p.shape for n, p in ae_params.items()
    }
    assert sum(p.numel() for p in net.parameters()) == sum(p.numel() for p in single.parameters())
    # And every pair really goes through that one autoencoder.
    x = torch.rand(3, 4, 2, 16, 32)
    z = net.encode(x)
    pairs = channel_pairs(x)
    for k in range(3):
        torch.testing.assert_close(z[:, k], net.autoencoder.encode(pairs[:, k]))


@pytest.mark.parametrize("decoder", ["linear", "broadcast"])
def test_gradients_reach_every_parameter(decoder: str) -> None:
    net = _net(latent_dim=16, decoder=decoder)
    recon, _ = net(torch.rand(2, 4, 2, 16, 32))
    recon.sum().backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


@pytest.mark.parametrize("shape", [(1, 8, 8), (3, 9, 13), (4, 32, 64)])
def test_broadcast_decoder_matches_any_input_shape(shape: tuple[int, int, int]) -> None:
    net = BottleneckNetwork(BottleneckConfig(input_shape=shape, latent_dim=16, channels=(4, 8), decoder="broadcast",
                                             broadcast_hidden=16))
    recon, z = net(torch.rand(2, 4, *shape))
    assert recon.shape == (2, 3, 2, *shape) and z.shape == (2, 3, 16)
    assert recon.min() >= 0.0 and recon.max() <= 1.0


def test_broadcast_decoder_coordinates_are_literal() -> None:
    # The coarsest stage of a (2, 16, 32) input through three stride-2 stages is (2, 2, 4):
    # frames at -1 and 1, rows at -1 and 1, columns at -1, -1/3, 1/3, 1, in (T, h, w) order.
    ae = _net(decoder="broadcast").autoencoder
    assert ae.code_shape[1:] == (2, 2, 4) and isinstance(ae.from_latent, SpatialBroadcast)
    coords = ae.from_latent.coords
    assert coords.shape == (16, 3)
    torch.testing.assert_close(coords[0], torch.tensor([-1.0, -1.0, -1.0]))
    torch.testing.assert_close(coords[1], torch.tensor([-1.0, -1.0, -1.0 / 3.0]))
    torch.testing.assert_close(coords[4], torch.tensor([-1.0, 1.0, -1.0]))
    torch.testing.assert_close(coords[15], torch.tensor([1.0, 1.0, 1.0]))
    # A single frame's axis sits at 0 rather than dividing by zero.
    one = BottleneckNetwork(BottleneckConfig(input_shape=(1, 8, 8), latent_dim=8, channels=(4,), decoder="broadcast"))
    assert isinstance(one.autoencoder.from_latent, SpatialBroadcast)
    assert torch.all(one.autoencoder.from_latent.coords[:, 0] == 0.0)


def test_broadcast_decoder_draws_every_cell_with_the_same_weights() -> None:
    # Without the coordinates' contribution, every coarse cell computes the same features
    # from the code: the cells differ only by where they are.
    ae = _net(latent_dim=16, decoder="broadcast").autoencoder
    head = ae.from_latent
    assert isinstance(head, SpatialBroadcast)
    with torch.no_grad():
        head.from_place.weight.zero_()
        feats = head(torch.rand(3, 16)).view(3, *ae.code_shape)
    c, t, h, w = ae.code_shape
    cells = feats.reshape(3, c, t * h * w)
    assert torch.equal(cells, cells[:, :, :1].expand_as(cells))
    assert not torch.equal(cells[0], cells[1])


def test_broadcast_decoder_puts_each_cells_features_at_that_cell() -> None:
    # Cell (t, i, j) of the coarse map holds the shared MLP of the code and coords[t·h·w + i·w + j].
    ae = _net(latent_dim=16, decoder="broadcast").autoencoder
    head = ae.from_latent
    assert isinstance(head, SpatialBroadcast)
    z = torch.rand(2, 16)
    with torch.no_grad():
        feats = head(z).view(2, *ae.code_shape)
        h, w = ae.code_shape[2:]
        for tt, i, j in [(0, 0, 0), (0, 1, 2), (1, 0, 3), (1, 1, 1)]:
            k = tt * h * w + i * w + j
            expected = head.cell(head.from_code(z) + head.from_place(head.coords[k]))
            torch.testing.assert_close(feats[:, :, tt, i, j], expected)


def test_initial_output_is_near_the_configured_value() -> None:
    net = _net(latent_dim=16, initial_output=0.05)
    with torch.no_grad():
        recon, _ = net(torch.zeros(4, 4, 2, 16, 32))
    assert abs(float(recon.mean()) - 0.05) < 0.05


def test_wrong_observation_shape_is_rejected() -> None:
    net = _net()
    with pytest.raises(ValueError, match=r"\(B, 4, 2, 16, 32\)"):
        net.encode(torch.rand(2, 4, 2, 16, 16))
    with pytest.raises(ValueError, match="B, 4, T, H, W"):
        channel_pairs(torch.rand(2, 3, 2, 16, 32))


@pytest.mark.parametrize(
    ("data", "field"),
    [
        ({"latent_dim": 1}, "latent_dim"),
        ({"latent_dim": 513}, "latent_dim"),
        ({"input_shape": (4, 7, 64)}, "input_shape"),
        ({"input_shape": (0, 32, 64)}, "input_shape"),
        ({"channels": ()}, "channels"),
        ({"spatial_kernel": 4}, "spatial_kernel"),
        ({"temporal_kernel": 2}, "temporal_kernel"),
        ({"latent_activation": "relu"}, "latent_activation"),
        ({"latent_size": 64}, "latent_size"),
        ({"decoder": "conv"}, "decoder"),
        ({"broadcast_hidden": 4}, "broadcast_hidden"),
    ],
)
def test_config_errors_name_the_field(data: dict[str, object], field: str) -> None:
    with pytest.raises(ConfigError, match=field):
        validate(BottleneckConfig, data)


def test_config_from_observation_config() -> None:
    obs = ObservationConfig(frames=3, height=24, width=48)
    cfg = BottleneckConfig.for_observation(obs, latent_dim=32)
    assert cfg.input_shape == (3, 24, 48)
    assert cfg.observation_shape == obs.shape
    assert cfg.latent_dim == 32
    assert BottleneckConfig().latent_dim == 64
