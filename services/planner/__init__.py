"""planner: turns mission commands into timed trajectory references (seed 004, ch. 5).

First version (walking skeleton): take-off, landing, hover, straight go-to and an
axis-aligned lawnmower over the working area's bounding rectangle, every segment with a
trapezoidal speed profile that stops at each corner. The inner rectangle of the arena
(§5.3), corner slow-down instead of full stops, approach with deadband and attack with
overshoot (§5.1–5.2) and interception of moving targets come with later issues.
"""
