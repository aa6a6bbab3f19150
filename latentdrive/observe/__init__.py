"""Observations: pure functions from a Scene to VelocityMap tensors (no simulator imports), and of those tensors to the vehicles they show (:mod:`latentdrive.observe.objects`)."""

from latentdrive.observe.velocitymap import (
    AV,
    CHANNELS,
    HV,
    MV,
    RL,
    FrameStack,
    SensorNoise,
    draw_noise,
    render_agents,
    render_frame,
    velocity_log_map,
)

__all__ = ["AV", "CHANNELS", "HV", "MV", "RL", "FrameStack", "SensorNoise", "draw_noise", "render_agents", "render_frame", "velocity_log_map"]
