"""The fast backend: many environments stepped at once by compiled kernels.

Same road geometry (read from highway-env's own builders), vehicle models, placement,
randomization and Scene output as :mod:`latentdrive.sim.highway`, reproduced equation by
equation; ``README.md`` beside this file lists what is reproduced and the few known
differences, :mod:`latentdrive.sim.validate` measures fidelity and throughput.

- :class:`FastBatch`: B environments (mixed scenarios allowed), one call per step.
- :class:`FastBackend`: one environment behind the Backend protocol.
"""

from __future__ import annotations

from latentdrive.sim.fast.backend import FastBackend
from latentdrive.sim.fast.batch import FastBatch

__all__ = ["FastBackend", "FastBatch"]
