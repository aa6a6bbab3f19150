"""Do PyTorch's CPU kernels, chosen by instruction set, change the last bits of the VFAN's ops?

Runs the same seeded conv3d, linear and softmax once per ATen CPU capability this CPU
offers (``ATEN_CPU_CAPABILITY``: default, avx2, avx512 where present), each in a fresh
process, and prints each output's largest difference (over its first 200,000 values) from
the first capability's: 0 means bitwise equal there. Usage: ``python scripts/kernel_bits.py``.

``--train OUT`` then trains the same raw policy (same seed, same config) once per
capability with ``latentdrive train-policy`` into ``OUT/<capability>``, and prints whether
the final weights are bitwise equal and each run's held-out failure rate (its own
end-of-run evaluation, ``eval.csv``): what the kernel set alone does to a training run.
``--steps``, ``--scenario`` and ``--episodes`` size it.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

_CHILD = """
import json, torch
torch.manual_seed(0); torch.set_num_threads(1)
x = torch.rand(64, 4, 4, 32, 64)
conv = torch.nn.Conv3d(4, 16, 3, padding=1)
lin = torch.nn.Linear(4096, 256)
with torch.no_grad():
    out = {"conv3d": conv(x), "linear": lin(torch.rand(512, 4096)), "softmax": torch.softmax(torch.rand(512, 4096), -1)}
print(json.dumps({"capability": torch.backends.cpu.get_cpu_capability(),
                  "out": {k: v.flatten().tolist()[:200000] for k, v in out.items()}}))
"""


def _capabilities() -> list[str]:
    """The ATen capabilities this CPU runs (torch falls back silently from the others)."""
    # Forced onto instructions the CPU lacks, a kernel dies (SIGILL): run one to know.
    probe = ("import torch; torch.nn.functional.conv3d(torch.rand(1, 1, 4, 4, 4), torch.rand(2, 1, 3, 3, 3)); "
             "print(torch.backends.cpu.get_cpu_capability())")
    found: list[str] = []
    for cap in ("default", "avx2", "avx512"):
        res = subprocess.run([sys.executable, "-c", probe], env={**os.environ, "ATEN_CPU_CAPABILITY": cap},
                             capture_output=True, text=True, check=False)
        if res.returncode == 0 and (cap == "default" or res.stdout.strip().lower() == cap):
            found.append(cap)
    return found


def _train(out: Path, steps: int, scenario: str, episodes: int) -> int:
    from safetensors.numpy import load_file

    rates, weights = {}, {}
    for cap in _capabilities():
        run = out / cap
        if not (run / "checkpoint.safetensors").exists():
            cmd = [sys.executable, "-m", "latentdrive", "train-policy", str(run), "--mode", "raw", "--scenarios", scenario,
                   "--steps", str(steps), "--envs", "8", "--seed", "0", "-q", "--set", "eval_every=0",
                   "--set", f"eval_episodes={episodes}", "--set", "segment=100000"]
            res = subprocess.run(cmd, env={**os.environ, "ATEN_CPU_CAPABILITY": cap}, check=False,
                                 stdout=subprocess.DEVNULL)
            if res.returncode == -signal.SIGILL:  # a kernel this CPU cannot run
                print(f"{cap}: not available on this CPU")
                shutil.rmtree(run, ignore_errors=True)
                continue
            res.check_returncode()
        weights[cap] = {k: v for k, v in load_file(str(run / "checkpoint.safetensors")).items() if k.startswith("model/")}
        with open(run / "eval.csv", newline="") as f:
            row = [r for r in csv.DictReader(f) if r["scenario"] == "mixed"][-1]
        rates[cap] = (float(row["failure_rate"]), int(row["episodes"]))
    first = next(iter(weights))
    print(f"{'capability':<12}{'weights equal to ' + first:>22}{'max |diff|':>14}{'failure rate':>16}")
    for cap, w in weights.items():
        same = all((w[k] == weights[first][k]).all() for k in w)
        diff = max(float(abs(w[k] - weights[first][k]).max()) for k in w)
        rate, n = rates[cap]
        print(f"{cap:<12}{'yes' if same else 'no':>22}{diff:>14.3g}{rate:>11.3f} of {n}")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--train", metavar="OUT", default="", help="also train one raw policy per capability into OUT")
    ap.add_argument("--steps", type=int, default=4000, help="agent-transitions per run (default 4000)")
    ap.add_argument("--scenario", default="roundabout")
    ap.add_argument("--episodes", type=int, default=100, help="held-out episodes of each run's evaluation")
    args = ap.parse_args()
    runs = []
    for cap in ("default", "avx2", "avx512"):
        env = {**os.environ, "ATEN_CPU_CAPABILITY": cap}
        res = subprocess.run([sys.executable, "-c", _CHILD], env=env, capture_output=True, text=True, check=False)
        if res.returncode != 0:  # forced onto instructions this CPU lacks (SIGILL)
            print(f"{cap}: not available on this CPU")
            continue
        got = json.loads(res.stdout)
        if got["capability"].lower() != cap and cap != "default":
            continue  # this CPU lacks it: torch fell back
        runs.append(got)
    first = runs[0]
    print(f"{'capability':<12}{'op':<10}{'max |diff| vs ' + first['capability']:>24}")
    for run in runs:
        for op, vals in run["out"].items():
            ref = first["out"][op]
            diff = max(abs(a - b) for a, b in zip(vals, ref, strict=True))
            print(f"{run['capability']:<12}{op:<10}{diff:>24.3g}")
    if args.train:
        print()
        return _train(Path(args.train), args.steps, args.scenario, args.episodes)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
