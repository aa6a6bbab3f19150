"""The episode GIF: one frame per step, equal frame sizes, a second row for reconstructions."""

import imageio.v3 as iio
import numpy as np
import pytest

import latentdrive
from latentdrive.evaluate.gif import save_episode_gif

STEPS = 3


@pytest.fixture(scope="module")
def episode():
    env = latentdrive.make_env("merge", backend="fast")
    obs, info = env.reset(seed=0)
    scenes, observations = [info["scene"]], [obs]
    for _ in range(STEPS - 1):
        obs, _, terminated, truncated, info = env.step(np.ones(2, dtype=np.int64))
        assert not (terminated or truncated)
        scenes.append(info["scene"])
        observations.append(obs)
    return scenes, observations, env.config.observation


def test_one_frame_per_step(episode, tmp_path):
    scenes, observations, cfg = episode
    out = save_episode_gif(tmp_path / "sub" / "ep.gif", scenes, observations, cfg, title="merge, idle")
    assert out == tmp_path / "sub" / "ep.gif" and out.exists()
    assert [p.name for p in out.parent.iterdir()] == ["ep.gif"]  # no temporary left behind
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == STEPS
    assert frames.ndim == 4 and frames.shape[-1] in (3, 4)


def test_reconstruction_row_makes_taller_frames(episode, tmp_path):
    scenes, observations, cfg = episode
    plain = iio.imread(save_episode_gif(tmp_path / "a.gif", scenes, observations, cfg, agent=1), index=None)
    recons = [np.clip(o[1] * 0.5, 0, 1) for o in observations]
    both = iio.imread(save_episode_gif(tmp_path / "b.gif", scenes, observations, cfg, agent=1,
                                       reconstructions=recons, fps=4), index=None)
    assert both.shape[0] == plain.shape[0] == STEPS
    assert both.shape[2] == plain.shape[2]
    assert both.shape[1] > plain.shape[1]


@pytest.mark.parametrize(
    ("cut", "kwargs", "needle"),
    [
        ("all", {}, "empty"),
        ("obs", {}, "observations"),
        (None, {"agent": 2}, "agent 2 is out of range"),
        (None, {"agent": -1}, "agent -1 is out of range"),
        (None, {"reconstructions": "short"}, "reconstructions"),
        (None, {"reconstructions": "badshape"}, "reconstructions[0]"),
        (None, {"fps": 0}, "fps"),
    ],
)
def test_bad_input_is_refused(episode, tmp_path, cut, kwargs, needle):
    scenes, observations, cfg = episode
    if cut == "all":
        scenes, observations = [], []
    elif cut == "obs":
        observations = observations[:-1]
    if kwargs.get("reconstructions") == "short":
        kwargs = {"reconstructions": [o[0] for o in observations[:-1]]}
    elif kwargs.get("reconstructions") == "badshape":
        kwargs = {"reconstructions": [o for o in observations]}
    with pytest.raises(ValueError) as err:
        save_episode_gif(tmp_path / "x.gif", scenes, observations, cfg, **kwargs)
    msg = str(err.value)
    assert needle in msg and "\n" not in msg
    assert not any(tmp_path.iterdir())
