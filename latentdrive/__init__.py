"""latentdrive: generalizable driving policies from restricted latent representations.

``latentdrive.make_env("merge", n_av=3)`` builds a scenario's gymnasium env,
``latentdrive.make_vec("merge", 64)`` a batch of them on the fast backend; importing the
package registers ``latentdrive/<scenario>-v0`` with gymnasium.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

__version__ = "0.1.0"
__all__ = ["__version__", "make_env", "make_vec"]

if TYPE_CHECKING:
    from latentdrive.env import DrivingEnv
    from latentdrive.vec import DrivingVecEnv


def make_env(scenario: str, **overrides: Any) -> DrivingEnv:
    """Create a scenario's env; see :func:`latentdrive.env.make_env`."""
    from latentdrive.env import make_env as _make_env

    return _make_env(scenario, **overrides)


def make_vec(scenario: Any, num_envs: int, backend: str = "fast", **overrides: Any) -> DrivingVecEnv:
    """Create a vector env of ``num_envs`` environments; see :func:`latentdrive.vec.make_vec`."""
    from latentdrive.vec import make_vec as _make_vec

    return _make_vec(scenario, num_envs, backend=backend, **overrides)


def _register() -> None:
    # Registration only names the entry point; the env module (and highway-env) load on make.
    try:
        import gymnasium as gym
    except ImportError:  # pragma: no cover - gymnasium is a dependency
        return
    for name in ("roundabout", "intersection", "merge", "exit", "highway"):
        env_id = f"latentdrive/{name}-v0"
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point="latentdrive.env:DrivingEnv", kwargs={"scenario": name})


_register()
