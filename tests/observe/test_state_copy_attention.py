"""``scripts/state_copy.py --arch attention``: the ego-attention copy reads its neighbours as a set."""

import runpy
from pathlib import Path

import torch

from latentdrive.observe.state import PER_NEIGHBOUR, state_size

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "state_copy.py"
EgoAttention = runpy.run_path(str(SCRIPT), run_name="state_copy")["EgoAttention"]
K = 4
EGO = state_size(0, route=True)


def _vector(rows: torch.Tensor, hidden: torch.Tensor | None = None) -> torch.Tensor:
    ego = torch.linspace(-1, 1, EGO)
    parts = [ego, rows.reshape(-1)] + ([] if hidden is None else [hidden.reshape(-1)])
    return torch.cat(parts)[None]


def _rows(present: int) -> torch.Tensor:
    torch.manual_seed(1)
    rows = torch.zeros(K, PER_NEIGHBOUR)
    rows[:present] = torch.randn(present, PER_NEIGHBOUR)
    rows[:present, PER_NEIGHBOUR - 1] = 1.0  # the "a vehicle is here" flag
    return rows


def test_reordering_the_neighbours_leaves_the_logits_unchanged():
    torch.manual_seed(0)
    net = EgoAttention(EGO, PER_NEIGHBOUR, K, hidden=32).eval()
    rows = _rows(3)
    swapped = rows[[2, 0, 1, 3]]
    with torch.no_grad():
        assert torch.allclose(net(_vector(rows)), net(_vector(swapped)), atol=1e-5)
        # while what a row holds does matter.
        moved = rows.clone()
        moved[0, 0] += 1.0
        assert not torch.allclose(net(_vector(rows)), net(_vector(moved)), atol=1e-5)


def test_padding_rows_are_ignored_whatever_they_hold():
    torch.manual_seed(0)
    net = EgoAttention(EGO, PER_NEIGHBOUR, K, hidden=32).eval()
    rows = _rows(2)
    junk = rows.clone()
    junk[2:, : PER_NEIGHBOUR - 1] = 5.0  # flag left at 0: no vehicle
    with torch.no_grad():
        assert torch.allclose(net(_vector(rows)), net(_vector(junk)), atol=1e-6)


def test_privileged_rows_travel_with_their_vehicle():
    torch.manual_seed(0)
    net = EgoAttention(EGO, PER_NEIGHBOUR + 2, K, hidden=32).eval()
    rows, hidden = _rows(3), torch.randn(K, 2)
    order = [1, 2, 0, 3]
    with torch.no_grad():
        a = net(_vector(rows, hidden))
        assert torch.allclose(a, net(_vector(rows[order], hidden[order])), atol=1e-5)
        assert not torch.allclose(a, net(_vector(rows[order], hidden)), atol=1e-5)
