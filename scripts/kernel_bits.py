"""Do PyTorch's CPU kernels, chosen by instruction set, change the last bits of the VFAN's ops?

Runs the same seeded conv3d, linear and softmax once per ATen CPU capability this CPU
offers (``ATEN_CPU_CAPABILITY``: default, avx2, avx512 where present), each in a fresh
process, and prints each output's largest difference (over its first 200,000 values) from
the first capability's: 0 means bitwise equal there. Usage: ``python scripts/kernel_bits.py``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

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


def main() -> int:
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
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
