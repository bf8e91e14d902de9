"""The planner's watch on its job manager.

The seed's planner only carries out the job manager's commands. A job manager that stops
talking (frozen, hung, killed and not yet back) would leave the vehicle on its last trajectory,
an attack run or a sweep leg, while its partners, no longer hearing its status, keep clear only of
the last position it reported (the lost-link rule's no-fly column). So the planner treats the
job manager's silence as an order to stop: after `timeout` without a status of its own UAV it
brakes to a hover where it is, once, and obeys again when the job manager speaks. Pure: stamps
in, decisions out.
"""
from __future__ import annotations


class JobManagerWatchdog:
    def __init__(self, timeout_ns: int) -> None:
        self.timeout_ns = timeout_ns
        self.last_heard: int | None = None  # None until the first status: nothing to watch before
        self.tripped = False

    def heard(self, now_ns: int) -> bool:
        """The job manager spoke at `now_ns`; True when that ends a silence we acted on."""
        self.last_heard = now_ns
        recovered, self.tripped = self.tripped, False
        return recovered

    def silent_too_long(self, now_ns: int) -> bool:
        """True once per silence, at the first check `timeout` after the last status."""
        if self.tripped or self.last_heard is None or now_ns - self.last_heard < self.timeout_ns:
            return False
        self.tripped = True
        return True
