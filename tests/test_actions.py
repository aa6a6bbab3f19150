import numpy as np

from latentdrive.actions import FASTER, IDLE, LEFT, SLOWER, idle_when_done


def test_finished_avs_are_driven_with_idle_whatever_they_are_told() -> None:
    actions = np.array([[LEFT, FASTER], [SLOWER, LEFT]])
    done = np.array([[True, False], [False, True]])
    out = idle_when_done(actions, done)
    assert out.dtype == np.int64 and out.tolist() == [[IDLE, FASTER], [SLOWER, IDLE]]
    assert actions.tolist() == [[LEFT, FASTER], [SLOWER, LEFT]]  # the input is not changed
