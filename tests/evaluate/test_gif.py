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


def test_side_by_side_runs_to_the_longest_episode_and_keeps_a_finished_ones_last_scene(episode, tmp_path):
    from latentdrive.evaluate.gif import save_side_by_side_gif

    scenes, _, cfg = episode
    out = save_side_by_side_gif(tmp_path / "s.gif", [("long", scenes, cfg), ("short", scenes[:1], cfg)], title="merge")
    frames = iio.imread(out, index=None)
    assert frames.shape[0] == STEPS
    half = frames.shape[2] // 2
    # The short episode's panel stands still after its only step (beyond its title, which
    # says the episode is over, and a few pixels of the GIF's per-frame palette); the long
    # one's moves.
    body = slice(frames.shape[1] // 4, None)

    def changed(a, b, side):
        return float((frames[a, body, side] != frames[b, body, side]).any(-1).mean())

    assert changed(0, -1, slice(None, half)) > 0.005 > 0.001 > changed(1, -1, slice(half, None))
    one = iio.imread(save_side_by_side_gif(tmp_path / "o.gif", [("long", scenes, cfg)]), index=None)
    assert one.shape[2] * 2 == pytest.approx(frames.shape[2], abs=2)
    for bad, needle in (([], "non-empty"), ([("x", [], cfg)], "non-empty")):
        with pytest.raises(ValueError, match=needle):
            save_side_by_side_gif(tmp_path / "x.gif", bad)
    with pytest.raises(ValueError, match="agent 5 is out of range in long's episode"):
        save_side_by_side_gif(tmp_path / "x.gif", [("long", scenes, cfg)], agent=5)
    assert not (tmp_path / "x.gif").exists()
