import os
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import settings

# The default suite draws the same examples on every run, so a CI failure reproduces and a
# change cannot turn the suite red by luck. `make fuzz` searches fresh random examples, 20x
# as many (tests size their searches with helpers.examples); run it after touching a loader.
settings.register_profile("default", derandomize=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

os.environ.setdefault("PYGAME_HIDE_SUPPORT_PROMPT", "1")
os.environ.setdefault("MPLBACKEND", "Agg")
sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(scope="module")
def one_torch_thread() -> Iterator[None]:
    """Tiny torch workloads run as fast on one thread, and spare a busy machine the
    oversubscription that can slow multi-threaded kernels several-fold."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)
