"""job_manager: the mission state machine of one UAV (seed 004, ch. 3).

- core.py: the state machine — automatic start (pre-flight check, take-off), the seed's states
  from IDLE to DESTROYING, landing on the mission timer, the abort system and the localizer's
  health when flying without GNSS;
- targets.py, sightings.py: the target filter, forbidden zones, attack tries and what was seen
  lately; areas.py: the equal-area working areas;
- team.py, plans.py: revenge mode, lost link, one chaser per target and separation planned ahead
  against the partners' shared references;
- params.py: its parameters; node.py wires it all to Zenoh.
"""
