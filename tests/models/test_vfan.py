"""The VFAN: one body definition for every input mode; latents enter as 1×1×1 channels."""

import pytest
import torch

from latentdrive.models.bottleneck import BottleneckConfig, BottleneckNetwork
from latentdrive.models.vfan import MODES, QNetwork, VFANBody, VFANConfig

OBS = (4, 4, 32, 64)


def _net(mode, cfg=None):
    enc = None if mode == "raw" else BottleneckNetwork(BottleneckConfig(latent_dim=16))
    return QNetwork(cfg or VFANConfig(), mode, OBS, enc)


@pytest.mark.parametrize("mode", MODES)
def test_every_mode_maps_its_stored_input_to_five_q_values(mode):
    net = _net(mode)
    obs = torch.rand(3, *OBS)
    stored = net.features(obs)
    assert tuple(stored.shape[1:]) == net.stored_shape
    assert net(stored).shape == (3, 5)
    expected = (3, 16) if mode in ("latent", "latent-random") else OBS
    assert net.stored_shape == expected


def test_the_body_is_the_same_definition_with_clipped_kernels():
    raw, latent = _net("raw"), _net("latent")
    raw_convs = [m for m in raw.body.modules() if isinstance(m, torch.nn.Conv3d)]
    lat_convs = [m for m in latent.body.modules() if isinstance(m, torch.nn.Conv3d)]
    assert [c.out_channels for c in raw_convs] == [c.out_channels for c in lat_convs] == [32, 64, 64]
    # Raw: the authors' kernels (the third clipped to the 2×2×4 map left by the first two).
    assert [c.kernel_size for c in raw_convs] == [(1, 8, 8), (3, 4, 4), (2, 2, 3)]
    # Latent: 3·d channels of a 1×1×1 volume, every kernel 1×1×1 (a dense layer).
    assert lat_convs[0].in_channels == 3 * 16 and all(c.kernel_size == (1, 1, 1) for c in lat_convs)
    assert raw.body.net[-1].out_features == latent.body.net[-1].out_features == 5
    assert raw.body.net[-3].out_features == latent.body.net[-3].out_features == 512


def test_a_1x1x1_body_is_exactly_a_dense_network_of_the_latents():
    body = VFANBody(VFANConfig(hidden=8), (6, 1, 1, 1))
    z = torch.rand(4, 6)
    convs = [m for m in body.net if isinstance(m, torch.nn.Conv3d)]
    h = z
    for c in convs:
        assert c.bias is not None
        h = torch.relu(h @ c.weight.flatten(1).T + c.bias)
    lin = [m for m in body.net if isinstance(m, torch.nn.Linear)]
    q = lin[1](torch.relu(lin[0](h)))
    torch.testing.assert_close(body(z.view(4, 6, 1, 1, 1)), q)
    # The dense shortcut the body takes at 1×1×1 is the convolution path's math.
    assert body.pointwise
    body.pointwise = False
    torch.testing.assert_close(body(z.view(4, 6, 1, 1, 1)), q)


def test_encoders_are_frozen_in_latent_modes_and_trained_end_to_end():
    for mode in ("latent", "latent-random"):
        net = _net(mode)
        assert not any(p.requires_grad for p in net.encoder.parameters())
        net.train()
        assert not net.encoder.training
        assert net.parameter_count()["trainable"] == net.parameter_count()["body"]
    e2e = _net("end-to-end")
    trainable = {id(p) for p in e2e.trainable_parameters()}
    ae = e2e.encoder.autoencoder
    assert all(id(p) in trainable for p in ae.encoder_convs.parameters())
    assert not any(id(p) in trainable for p in ae.decoder_convs.parameters())


def test_bad_modes_and_mismatched_encoders_are_refused():
    with pytest.raises(ValueError, match="unknown mode"):
        QNetwork(VFANConfig(), "pixels", OBS)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="needs an encoder"):
        QNetwork(VFANConfig(), "latent", OBS)
    with pytest.raises(ValueError, match="takes no encoder"):
        QNetwork(VFANConfig(), "raw", OBS, BottleneckNetwork(BottleneckConfig()))
    with pytest.raises(ValueError, match="encoder takes observations"):
        QNetwork(VFANConfig(), "latent", (4, 2, 32, 64), BottleneckNetwork(BottleneckConfig()))



@pytest.mark.parametrize("mode", MODES)
def test_the_dueling_head_combines_value_and_mean_centred_advantages(mode):
    enc = None if mode == "raw" else BottleneckNetwork(BottleneckConfig(latent_dim=16))
    net = QNetwork(VFANConfig(hidden=16), mode, OBS, enc, dueling=True)
    stored = net.features(torch.rand(3, *OBS))
    q = net(stored)
    assert q.shape == (3, 5)
    body = net.body
    assert isinstance(body, VFANBody)
    if mode == "end-to-end":
        assert net.encoder is not None
        x = net.encoder.encode(stored)
    else:
        x = stored
    h = body.net(x.reshape(3, -1, 1, 1, 1) if mode != "raw" else x)
    adv = body.advantage(h)
    torch.testing.assert_close(q, body.value(h) + adv - adv.mean(dim=1, keepdim=True))
    # Without the option the parameter names are those of older checkpoints.
    plain = QNetwork(VFANConfig(hidden=16), mode, OBS, enc)
    assert not any(k.startswith(("body.value", "body.advantage")) for k in plain.state_dict())
    assert "body.net.9.weight" in plain.state_dict() and "body.net.9.weight" not in net.state_dict()
