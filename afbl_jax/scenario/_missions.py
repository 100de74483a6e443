"""Missions flown with a position loop: station keeping and waypoints (the Monte-Carlo
references of a vehicle that holds its position; the paper's attitude profiles are in
`afbl_jax.scenario.paper_reference`)."""

from __future__ import annotations

from ._references import PositionReference, Reference, make_position_reference, make_reference

MISSION_PROFILES = ("hold", "waypoints")
"""Position-hold reference profiles (`mission_reference`)."""


def mission_reference(profile: str) -> tuple[Reference, PositionReference]:
    """(attitude/altitude reference, position reference) of a position-hold mission.

    Both: climb z 0 -> 1 m at 1 s and descent 1 -> 0 m at 16 s, yaw 0 -> 0.2 rad at 8 s and
    back at 12 s (2 s minimum-jerk blends: at most 1.4 m/s^2 vertically, where the canonical
    scenarios' 1 s blends ask 5.8 m/s^2, more thrust than a loaded vehicle has left in wind);
    roll and pitch come
    from the position loop (the attitude reference's roll and pitch channels are zero and
    unused). ``"hold"``: hold the start position (0, 0). ``"waypoints"``: x 0 -> 2 m at 3 s and
    back at 11 s, y 0 -> 2 m at 6 s and back at 13 s (3 s blends: at most 1.3 m/s^2 and
    1.25 m/s).
    """
    steps = {
        "psi": [(8.0, 0.0, 0.2), (12.0, 0.2, 0.0)],
        "z": [(1.0, 0.0, 1.0), (16.0, 1.0, 0.0)],
    }
    reference = make_reference(steps=steps, max_steps=2, step_duration=2.0)
    if profile == "hold":
        return reference, make_position_reference(max_steps=2, step_duration=3.0)
    if profile == "waypoints":
        moves = {"x": [(3.0, 0.0, 2.0), (11.0, 2.0, 0.0)], "y": [(6.0, 0.0, 2.0), (13.0, 2.0, 0.0)]}
        return reference, make_position_reference(steps=moves, max_steps=2, step_duration=3.0)
    raise ValueError(
        f"unknown mission profile {profile!r}; allowed: {', '.join(MISSION_PROFILES)}."
    )
