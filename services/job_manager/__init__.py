"""job_manager: the mission state machine of one UAV (seed 004, ch. 3).

First version (walking skeleton): pre-flight check, take-off, lawnmower sweep of the UAV's
equal-area share of the arena, landing on the mission timer. Targets, state timers,
forbidden zones, the abort system and revenge mode come with later issues.
"""
