"""The ego-attention map reader (``vfan.reader: attention``)."""

import pytest
import torch

from latentdrive.config import ConfigError, validate
from latentdrive.models.attention import MapAttentionBody, token_grid, token_shape
from latentdrive.models.vfan import QNetwork, VFANConfig
from latentdrive.rl.config import PolicyTrainConfig

SHAPE = (4, 4, 32, 64)


def test_the_token_grid_lies_where_the_map_draws_its_cells():
    # Default map: 32 x 64 cells of 1.5 m, 32 m behind the observer. Token j stands for the
    # block of cells 4j..4j+3, a 6 m square, and sits at its centre.
    grid, me = token_grid(32, 64, 1.5, 32.0)
    assert grid.shape == (8 * 16, 2)
    # First token: centre 3 m into the map, i.e. 29 m behind and 21 m to the left, / 50.
    assert grid[0].tolist() == pytest.approx([-0.58, -0.42])
    # Row-major: the second token is 6 m further ahead, the 17th 6 m further right.
    assert grid[1].tolist() == pytest.approx([-0.46, -0.42])
    assert grid[16].tolist() == pytest.approx([-0.58, -0.30])
    # The observer (32 m from the back edge, on the middle line) is in row 4, column 5:
    # column 5's block spans 30-36 m from the back edge, row 4's the first 6 m to its right.
    assert me == (4, 5)
    assert grid[4 * 16 + 5].tolist() == pytest.approx([0.02, 0.06])


def test_odd_sized_maps_get_as_many_positions_as_the_stem_gives():
    body = MapAttentionBody((4, 2, 30, 45), 1.5, 10.0)
    assert body(torch.rand(3, 4, 2, 30, 45)).shape == (3, 5)
    # 30 x 45 cells: the overlapping stem gives ceil(floor(n/2)/2) = 8 x 11 tokens, the
    # patch stem the 7 x 11 whole 4 x 4 blocks.
    assert token_shape(30, 45) == (8, 11)
    assert token_shape(30, 45, "patch") == (7, 11)
    patch = MapAttentionBody((4, 2, 30, 45), 1.5, 10.0, stem="patch")
    assert (patch.rows, patch.cols) == (7, 11)
    assert patch(torch.rand(3, 4, 2, 30, 45)).shape == (3, 5)


def test_the_patch_stem_puts_its_tokens_where_the_conv_stem_does():
    # On the default map both stems make the 8 x 16 tokens of 4 x 4-cell blocks.
    assert torch.equal(token_grid(32, 64, 1.5, 32.0, "patch")[0], token_grid(32, 64, 1.5, 32.0)[0])
    assert token_grid(32, 64, 1.5, 32.0, "patch")[1] == (4, 5)
    with pytest.raises(ValueError, match="unknown stem 'pixel'"):
        MapAttentionBody(SHAPE, 1.5, 32.0, stem="pixel")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="attention_stem"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "attention", "attention_stem": "pixel"}})


@pytest.mark.parametrize("stem", ["conv", "patch"])
def test_the_token_shape_is_what_the_stem_makes(stem):
    for h in range(4, 41, 3):
        for w in range(4, 41, 5):
            body = MapAttentionBody((2, 1, h, w), 1.5, 0.0, width=8, heads=2, hidden=8, stem=stem)
            with torch.no_grad():
                f = body.stem(torch.zeros(1, 2, h, w))
            assert (f.shape[2], f.shape[3]) == token_shape(h, w, stem) == (body.rows, body.cols)


def test_the_other_cells_are_read_as_a_set():
    torch.manual_seed(0)
    body = MapAttentionBody(SHAPE, 1.5, 32.0).eval()
    tokens = body.tokens(torch.rand(2, *SHAPE))
    me = 4 * 16 + 5
    perm = torch.randperm(tokens.shape[1])
    moved = tokens[:, perm]
    new_me = int((perm == me).nonzero())
    with torch.no_grad():
        assert torch.allclose(body.read(tokens, me), body.read(moved, new_me), atol=1e-5)
        # ...while what a cell holds does matter.
        changed = tokens.clone()
        changed[:, 0] += 5.0
        assert not torch.allclose(body.read(tokens, me), body.read(changed, me), atol=1e-4)
        # ...and so does where it is: the same maps read with the cells' positions swapped.
        x = torch.rand(2, *SHAPE)
        before = body(x)
        body.grid = body.grid.flip(0)
        assert not torch.allclose(before, body(x), atol=1e-4)


@pytest.mark.parametrize("dueling", [False, True])
def test_q_values_from_the_summary_are_the_networks_own(dueling):
    # A loss on the summary shares the Q-loss's forward pass (dqn.aux_joint) only if the
    # Q-values read from it are those forward() gives.
    torch.manual_seed(0)
    net = QNetwork(VFANConfig(reader="attention", hidden=32, attention_width=16), "raw", (4, 2, 16, 32),
                   dueling=dueling, geometry=(1.5, 8.0))
    x = torch.rand(3, 4, 2, 16, 32)
    assert torch.equal(net.q_from_summary(net.summary(x)), net(x))
    with pytest.raises(ValueError, match="attention reader"):
        QNetwork(VFANConfig(), "raw", (4, 4, 32, 64)).q_from_summary(torch.rand(3, 128))


@pytest.mark.parametrize(("stem", "context", "sees"),
                         [("conv", 0, {0, 1}), ("conv", 1, {0, 1, 2, 3}), ("conv", 2, {0, 1, 2, 3, 4, 5}),
                          ("patch", 0, {0}), ("patch", 1, {0, 1}), ("patch", 2, {0, 1, 2})])
def test_context_layers_widen_what_the_observers_token_sees(stem, context, sees):
    # Cells changed in one token-sized block at a time, ``k`` tokens ahead of the
    # observer's (k = 0: its own block): its own token feels the blocks ``sees`` (the conv
    # stem's 8 cells reach one token on and each layer, dilated by 2, two more; the patch
    # stem's 4 cells none, and each of its undilated layers one more).
    torch.manual_seed(0)
    body = MapAttentionBody(SHAPE, 1.5, 32.0, context=context, stem=stem).eval()
    assert len(body.context) == context
    x = torch.rand(1, *SHAPE)
    me_row, me_col = 4, 5
    felt = []
    for k in range(0, 8):
        changed = x.clone()
        col = 4 * (me_col + k)
        changed[..., 4 * me_row: 4 * me_row + 4, col: col + 4] = 1.0 - changed[..., 4 * me_row: 4 * me_row + 4, col: col + 4]
        with torch.no_grad():
            moved = (body.tokens(changed)[0, me_row * 16 + me_col] - body.tokens(x)[0, me_row * 16 + me_col])
        felt.append(moved.abs().max().item() > 1e-6)
    assert felt == [k in sees for k in range(0, 8)]


@pytest.mark.parametrize(("dueling", "context", "stem"),
                         [(False, 0, "conv"), (True, 0, "conv"), (False, 2, "conv"), (True, 0, "patch"),
                          (False, 0, "patch")])
def test_a_raw_network_with_the_reader_gives_five_q_values(dueling, context, stem):
    net = QNetwork(VFANConfig(reader="attention", attention_context=context, attention_stem=stem), "raw", SHAPE,
                   dueling=dueling, geometry=(1.5, 32.0))
    # The setting reaches the network: the patch stem's first layer reads 4 x 4 blocks.
    assert isinstance(net.body, MapAttentionBody)
    assert net.body.stem[0].stride == {"conv": (2, 2), "patch": (4, 4)}[stem]
    if not dueling and not context:
        assert sum(p.numel() for p in net.parameters()) == {"conv": 120_485, "patch": 114_373}[stem]
    q = net(torch.rand(5, *SHAPE))
    assert q.shape == (5, 5)
    q.sum().backward()
    assert all(p.grad is not None for p in net.parameters())


def test_the_reader_is_refused_where_it_has_no_map_to_read():
    with pytest.raises(ValueError, match="needs the map's geometry"):
        QNetwork(VFANConfig(reader="attention"), "raw", SHAPE)
    with pytest.raises(ConfigError, match="reads raw maps"):
        validate(PolicyTrainConfig, {"mode": "end-to-end", "vfan": {"reader": "attention"}})
    with pytest.raises(ConfigError, match="augment_shift"):
        validate(PolicyTrainConfig, {"mode": "raw", "vfan": {"reader": "attention"}, "dqn": {"augment_shift": 2}})
    with pytest.raises(ValueError, match="not those this reader was built for"):
        MapAttentionBody(SHAPE, 1.5, 32.0)(torch.rand(1, 4, 4, 64, 32))
    with pytest.raises(ConfigError, match="does not divide"):
        validate(VFANConfig, {"attention_width": 64, "attention_heads": 5})
