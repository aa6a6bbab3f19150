"""Aggregates over training seeds, with rliable's stratified-bootstrap intervals.

One trained policy is one draw from the training process: the episode-level intervals of
:mod:`latentdrive.evaluate.stats` say how well *that* policy was measured, not how another
training seed would do. These intervals resample training seeds (within each task, i.e.
scenario, when several are pooled), as recommended by Agarwal et al. (2021), whose
``rliable`` implements them.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

__all__ = ["seed_interval"]


def seed_interval(scores: ArrayLike, *, reps: int = 2000, seed: int = 0, alpha: float = 0.05) -> dict[str, Any]:
    """Mean of ``scores`` ``(n_seeds, n_tasks)`` (or ``(n_seeds,)``) with a ``1 - alpha``
    percentile interval from rliable's stratified bootstrap over seeds.

    Returns ``{"mean", "lo", "hi", "seeds"}``; with one seed there is nothing to resample,
    and ``lo``/``hi`` are None (say so rather than print a zero-width interval). The
    bootstrap draws from numpy's global generator seeded with ``seed`` for the call (its state
    is restored after): same scores, same interval.
    """
    x = np.asarray(scores, dtype=np.float64)
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] < 1:
        raise ValueError(f"scores must be (n_seeds, n_tasks) with both at least 1, got shape {x.shape}")
    mean = float(x.mean())
    if x.shape[0] == 1:
        return {"mean": mean, "lo": None, "hi": None, "seeds": 1}
    # Imported here: rliable pulls in arch and pandas, which only aggregation needs.
    from rliable import library as rly

    # rliable's StratifiedBootstrap draws its resamples from numpy's global generator, not
    # from the random_state it is given (rliable 1.2.0, ``update_indices``): seed the global
    # one for the call and put its state back, so that the same scores give the same
    # interval and the caller's own random stream is left as it was.
    saved = np.random.get_state()  # noqa: NPY002 (rliable's generator is the global one)
    np.random.seed(seed)  # noqa: NPY002
    try:
        with warnings.catch_warnings():
            # arch warns that RandomState will go; rliable still passes one on.
            warnings.simplefilter("ignore", FutureWarning)
            _, cis = rly.get_interval_estimates({"x": x}, lambda s: np.array([s.mean()]), reps=reps,
                                                confidence_interval_size=1 - alpha,
                                                random_state=np.random.RandomState(seed))
    finally:
        np.random.set_state(saved)  # noqa: NPY002
    lo, hi = (float(v) for v in np.asarray(cis["x"]).reshape(2))
    return {"mean": mean, "lo": lo, "hi": hi, "seeds": int(x.shape[0])}
