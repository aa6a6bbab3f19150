"""The calibrated presets against the specs they replaced (docs/calibration/)."""

from __future__ import annotations


def test_wrecks_among_human_drivers_are_counted_and_calibrated_away() -> None:
    from pathlib import Path

    from latentdrive.evaluate.policies import reference_policy
    from latentdrive.evaluate.run import evaluate_policy

    old = str(Path(__file__).parents[2] / "docs" / "calibration" / "roundabout-6hv.yaml")
    stop = reference_policy("stop")
    # With the AVs braking to a stop, six HVs (two per ring region) wreck each other often.
    before = evaluate_policy(stop, [old], 32, envs=16)
    assert sum(o.traffic_crashed for o in before) >= 4
    after = evaluate_policy(stop, ["roundabout"], 32, envs=16)
    assert sum(o.traffic_crashed for o in after) <= 1

