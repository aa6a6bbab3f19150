import json
import os
import subprocess
import sys

import numpy as np

from latentdrive.config import ObservationConfig
from latentdrive.observe import MV, RL, draw_noise
from latentdrive.scenarios import get_spec
from latentdrive.sim.fast import FastBatch

_SCRIPT = """
import json, numpy as np
from latentdrive.scenarios import get_spec
from latentdrive.sim.fast import FastBatch
batch = FastBatch([get_spec("intersection"), get_spec("merge")])
batch.reset([3, 4])
for _ in range(2):
    scenes = batch.step(np.array([[1, 3], [0, 1]]))
print(json.dumps([s.position.tolist() for s in scenes]))
"""


def test_kernels_give_the_same_result_interpreted():
    # Without numba the kernels run as plain Python; the results must not change.
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    out = subprocess.run([sys.executable, "-c", _SCRIPT], env=env, capture_output=True, text=True, check=True)
    interpreted = json.loads(out.stdout)
    batch = FastBatch([get_spec("intersection"), get_spec("merge")])
    batch.reset([3, 4])
    for _ in range(2):
        scenes = batch.step(np.array([[1, 3], [0, 1]]))
    for got, ref in zip(interpreted, scenes, strict=True):
        np.testing.assert_allclose(got, ref.position, atol=1e-9)


_RENDER = """
import json, numpy as np
from latentdrive.config import ObservationConfig
from latentdrive.observe import draw_noise
from latentdrive.scenarios import get_spec
from latentdrive.sim.fast import FastBatch
cfg = ObservationConfig(height=8, width=16, resolution=1.5, behind=12.0)
batch = FastBatch([get_spec("merge")])
batch.reset([5])
noise = [draw_noise(np.random.default_rng(1), 2, batch.scene(0).n_vehicles, cfg.noise)]
print(json.dumps(batch.render([0], cfg, noise, np.ones((1, 2), dtype=bool)).tolist()))
"""


def test_renderer_gives_the_same_frames_interpreted():
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1"}
    out = subprocess.run([sys.executable, "-c", _RENDER], env=env, capture_output=True, text=True, check=True)
    interpreted = np.array(json.loads(out.stdout), dtype=np.float32)
    cfg = ObservationConfig(height=8, width=16, resolution=1.5, behind=12.0)
    batch = FastBatch([get_spec("merge")])
    batch.reset([5])
    noise = [draw_noise(np.random.default_rng(1), 2, batch.scene(0).n_vehicles, cfg.noise)]
    compiled = batch.render([0], cfg, noise, np.ones((1, 2), dtype=bool))
    np.testing.assert_array_equal(interpreted, compiled)
    assert compiled[0, :, RL].any() and compiled[0, :, MV].any()
