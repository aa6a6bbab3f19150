"""Episode outcomes: why an episode failed, on hand-made Scenes, and the JSON round trip."""

from __future__ import annotations

import numpy as np
import pytest

from latentdrive.evaluate.policies import reference_policy
from latentdrive.evaluate.run import evaluate_policy
from latentdrive.outcome import FAILURE_CAUSES, failure_cause, outcomes_from_json, outcomes_to_json
from latentdrive.scene import Kind, RoadRaster, Scene

ROAD = RoadRaster(mask=np.ones((40, 400), np.uint8), origin=np.zeros(2), resolution=1.0)


def scene(others: list[tuple[float, float, int, bool]], *, crashed: bool = True, arrived: bool = False,
          heading: float = 0.0) -> Scene:
    """AV 0 at the origin with ``heading``, crashed or not; ``others``: (x, y, kind, crashed)."""
    xy = np.array([[0.0, 0.0], *[(x, y) for x, y, _, _ in others]])
    n = len(xy)
    return Scene(
        position=xy, heading=np.full(n, heading), speed=np.full(n, 10.0), frenet_speed=np.full(n, 10.0),
        length=np.full(n, 5.0), width=np.full(n, 2.0),
        kind=np.array([Kind.AV, *[k for _, _, k, _ in others]], np.int8), mask=np.ones(n, bool),
        crashed=np.array([crashed, *[c for *_, c in others]]), agents=np.array([0]), road=ROAD,
        arrived=np.array([arrived] + [False] * (n - 1)),
    )


@pytest.mark.parametrize(("others", "cause"), [
    ([(5.0, 0.5, Kind.HV, True)], "HV ahead"),
    ([(-5.5, -0.3, Kind.HV, True)], "HV behind"),
    ([(1.0, 3.0, Kind.HV, True)], "HV beside"),
    ([(1.0, 3.0, Kind.AV, True)], "other AV"),
    # The HV in contact is the partner, not the farther wreck; a wreck out of range is no partner.
    ([(30.0, 0.0, Kind.AV, True), (-5.0, 0.0, Kind.HV, True)], "HV behind"),
    ([(20.0, 0.0, Kind.HV, True)], "no vehicle"),
    ([(5.0, 0.0, Kind.HV, False)], "no vehicle"),  # an HV close by that did not crash
])
def test_a_crash_is_named_by_where_its_partner_was(others, cause):
    assert failure_cause(scene(others)) == cause


def test_ahead_and_behind_follow_the_av_heading():
    # Heading north (+y): an HV 5 m north is ahead, one 5 m east is beside.
    north = np.pi / 2
    assert failure_cause(scene([(0.2, 5.0, Kind.HV, True)], heading=north)) == "HV ahead"
    assert failure_cause(scene([(5.0, 0.2, Kind.HV, True)], heading=north)) == "HV beside"


def test_no_crash_is_a_success_or_a_time_out_and_an_arrived_crash_is_after_arrival():
    assert failure_cause(scene([], crashed=False, arrived=True)) == ""
    assert failure_cause(scene([], crashed=False)) == "time-out"
    hit = scene([(5.0, 0.0, Kind.HV, True)], arrived=True)
    assert failure_cause(hit, arrived_before=np.array([True])) == "after arrival"
    # Crashing on the step of arrival is a crash while driving, as the reward counts it.
    assert failure_cause(hit, arrived_before=np.array([False])) == "HV ahead"
    assert failure_cause(hit) == "HV ahead"


def test_the_av_still_driving_names_the_crash_not_the_one_it_hit_after_arrival():
    # AV 0 had arrived and stopped; AV 1 drives into it: the crash is AV 1's, with the other AV.
    xy = np.array([[0.0, 0.0], [-5.0, 0.0]])
    s = Scene(position=xy, heading=np.zeros(2), speed=np.array([0.0, 10.0]), frenet_speed=np.array([0.0, 10.0]),
              length=np.full(2, 5.0), width=np.full(2, 2.0), kind=np.array([Kind.AV, Kind.AV], np.int8),
              mask=np.ones(2, bool), crashed=np.ones(2, bool), agents=np.arange(2), road=ROAD,
              arrived=np.array([True, False]))
    assert failure_cause(s, arrived_before=np.array([True, False])) == "other AV"


def test_rollout_causes_agree_with_the_outcome_and_round_trip_through_json():
    # The rule driver never changes lanes: on merge it drives into the end of its lane.
    outs = evaluate_policy(reference_policy("rule"), ["merge", "roundabout"], 8, envs=4, seed_offset=3)
    assert all((o.cause == "") == o.success for o in outs)
    assert all(o.cause in FAILURE_CAUSES for o in outs if o.failed)
    assert {o.cause for o in outs if o.scenario == "merge"} == {"no vehicle"}
    back = outcomes_from_json(outcomes_to_json(outs))
    assert [o.cause for o in back] == [o.cause for o in outs]


def test_files_without_causes_load_and_a_cause_that_contradicts_the_outcome_is_refused():
    outs = evaluate_policy(reference_policy("rule"), ["merge"], 2, envs=2, seed_offset=3)
    old = [{k: v for k, v in d.items() if k != "cause"} for d in outcomes_to_json(outs)]
    assert [o.cause for o in outcomes_from_json(old)] == ["unrecorded", "unrecorded"]
    bad = outcomes_to_json(outs)
    bad[1]["cause"] = ""  # a failed episode with a success's cause
    with pytest.raises(ValueError, match="outcome 1: cause ''"):
        outcomes_from_json(bad)
    bad[1]["cause"] = "meteor"
    with pytest.raises(ValueError, match="outcome 1: cause 'meteor'"):
        outcomes_from_json(bad)
