"""How well the fixed detector of ``scripts/map_blobs.py`` finds the vehicles a map draws.

Plays ``--steps`` decisions of ``--envs`` episodes per scenario (every AV keeps its lane,
action 1) on the fast backend with the default map and its sensor noise, and pairs each
vehicle the detector finds in an AV's newest frame with the nearest vehicle of the
exact-state vector inside the map's view (``scripts/state_dqn.py``'s ``features`` with its
``MAP_VIEW``), within ``--within`` metres. Prints per scenario: the exact vehicles, those
found, the pairs per exact vehicle (a found vehicle within ``--within`` of an exact one,
counted once per found vehicle), the share of exact vehicles with a found one within
``--within`` ("covered"), the share of found vehicles with no exact one within it
("spurious"), the median distance of a pair, the share of pairs the detector
matched to the frame before, and, over those, the median and 90th percentile of the error
of its motion against the exact velocity difference (m/s), beside the spread of the exact
values, and the share of observations whose nearest vehicle found lies more than 3 m from
the nearest exact one (a missed or misplaced car ahead). Usage::

    python scripts/blob_check.py [--ego-motion] [--frames 2] [--fill] [--smooth] [--envs 8] [--steps 80] [--seed 11] [--within 3]
"""

from __future__ import annotations

import argparse
import runpy
from pathlib import Path

import numpy as np

from latentdrive.config import ObservationConfig
from latentdrive.observe.state import PER_NEIGHBOUR
from latentdrive.rollout import rollout
from latentdrive.scenarios import SCENARIOS
from latentdrive.vec import make_vec

_HERE = Path(__file__).resolve().parent
_STATE = runpy.run_path(str(_HERE / "state_dqn.py"), run_name="state_dqn")
_BLOBS = runpy.run_path(str(_HERE / "map_blobs.py"), run_name="map_blobs")
K = 16


def pairs(scenario: str, envs: int, steps: int, seed: int, within: float, ego_motion: bool,
          frames: int = 2, fill: bool = False, smooth: bool = False
          ) -> tuple[int, int, np.ndarray, np.ndarray, int, int]:
    """The exact vehicles seen, those found, one row per pair (distance, matched, found
    motion x and y, exact velocity difference x and y), for each observation with both the
    distance between the nearest vehicle found and the nearest exact one (metres), the exact
    vehicles with a found one within ``within`` and the found ones with no exact one within it."""
    cfg = ObservationConfig()
    ego = _BLOBS["ego_size"](cfg, 4)
    vec = make_vec([scenario], envs, backend="fast")
    specs = list(vec.simulator.specs)
    names = np.asarray([s.name for s in specs], dtype=object)
    rows: list[list[float]] = []
    nearest: list[float] = []
    n_exact = n_found = covered = spurious = 0
    for step, rec in enumerate(rollout(vec, lambda inp: np.ones(inp.obs.shape[:2], dtype=np.int64), seed=seed)):
        if step >= steps:
            break
        inp = _STATE["next_input"](rec, names, vec.simulator)
        exact = _STATE["features"](inp, specs, K, 80.0, False, False, _STATE["MAP_VIEW"])[..., -K * PER_NEIGHBOUR:]
        found = _BLOBS["blob_features"](rec.next_obs, cfg, K, ego_motion=ego_motion, frames=frames,
                                         fill=fill, smooth=smooth)[..., ego:]
        for e, a in zip(*np.nonzero(rec.agents.active), strict=True):
            s = exact[e, a].reshape(K, PER_NEIGHBOUR)
            b = found[e, a].reshape(K, PER_NEIGHBOUR)
            s, b = s[s[:, -1] > 0], b[b[:, -1] > 0]
            n_exact, n_found = n_exact + len(s), n_found + len(b)
            if len(s) == 0 or len(b) == 0:
                spurious += len(b)
                continue
            nearest.append(float(np.hypot(*(b[0, :2] - s[0, :2]))) * 50.0)  # both nearest first
            d = np.hypot(b[:, None, 0] - s[None, :, 0], b[:, None, 1] - s[None, :, 1]) * 50.0
            j = d.argmin(1)
            covered += int((d.min(0) <= within).sum())
            spurious += int((d.min(1) > within).sum())
            for i in np.flatnonzero(d[np.arange(len(b)), j] <= within):
                rows.append([d[i, j[i]], b[i, 5], *(b[i, 2:4] * 20.0), *(s[j[i], 2:4] * 20.0)])
    vec.close()
    return (n_exact, n_found, np.asarray(rows, dtype=np.float64).reshape(-1, 6), np.asarray(nearest), covered,
            spurious)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ego-motion", action="store_true", help="the detector's --ego-motion (scripts/map_blobs.py)")
    ap.add_argument("--frames", type=int, default=2, help="the detector's frames (scripts/map_blobs.py)")
    ap.add_argument("--fill", action="store_true", help="the detector's fill (scripts/map_blobs.py; --frames 3 or 4)")
    ap.add_argument("--smooth", action="store_true", help="the detector's smooth (scripts/map_blobs.py; --frames 3 or 4)")
    ap.add_argument("--envs", type=int, default=8)
    ap.add_argument("--steps", type=int, default=80, help="decisions per environment")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--within", type=float, default=3.0, help="metres")
    args = ap.parse_args()
    if min(args.envs, args.steps) < 1 or args.within <= 0 or not 2 <= args.frames <= ObservationConfig().frames:
        ap.error(f"--envs and --steps must be at least 1, --within above 0, --frames 2 to {ObservationConfig().frames}")
    if (args.fill or args.smooth) and args.frames < 3:
        ap.error("--fill and --smooth follow a vehicle through two older frames: they need --frames 3 or 4")
    print("scenario      exact  found  paired  covered  spurious  median m  matched  motion error m/s: median  90%   exact spread (sd x, y)"
          "  nearest found > 3 m from nearest exact")
    for scenario in SCENARIOS:
        n_exact, n_found, p, near, covered, spurious = pairs(scenario, args.envs, args.steps, args.seed, args.within, args.ego_motion, args.frames,
                                     args.fill, args.smooth)
        m = p[p[:, 1] > 0]
        err = np.hypot(m[:, 2] - m[:, 4], m[:, 3] - m[:, 5])
        line = f"{scenario:12s} {n_exact:6d} {n_found:6d} {len(p) / max(n_exact, 1):7.2f} "
        line += f"{covered / max(n_exact, 1):8.2f} {spurious / max(n_found, 1):9.2f} "
        line += f"{np.median(p[:, 0]):9.2f} {len(m) / len(p):8.2f} " if len(p) else f"{'-':>9s} {'-':>8s} "
        if len(m):
            line += f"{np.median(err):24.1f} {np.quantile(err, 0.9):5.1f} {m[:, 4].std():13.1f}, {m[:, 5].std():.1f}"
        else:
            line += f"{'-':>24s} {'-':>5s} {'-':>13s}"
        print(line + (f"  {np.mean(near > 3.0):.2f}" if len(near) else "  -"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
