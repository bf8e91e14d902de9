"""How a tracked target turns, read from its last corrected states rather than the filter's
acceleration.

The constant-acceleration filter (models.py) cannot follow a sustained turn: with the small jerk
noise that keeps it steady (q_acceleration), its acceleration estimate of a drone circling a
mast at 3.2 m/s on 4 m (2.6 m/s² towards the centre) was 0.7 m/s² and pointed the wrong way, and
its velocity lagged the true one by about 19°, so a prediction built on them was 2 m off 1 s
ahead and 6 m off 2 s ahead. The lagging velocity does turn at the true rate, and the corrected
positions lie on the circle. So, over the last `window` s of corrections:

- the turn rate ω is the least-squares slope of the unwrapped horizontal heading of the corrected
  velocities (the coordinated-turn rate of manoeuvring-target tracking, Li & Jilkov, "Survey of
  maneuvering target tracking, part I", 2003, sec. V, estimated outside the filter instead of as a
  state);
- the heading now is the direction of the chord from the oldest to the newest corrected position,
  which on an arc is the heading at its middle, turned on by ω·span/2.

The speed stays the filter's: an average over the window would lag a braking target's by
a·window/2, where the filter's was 7 % fast on the circle (0.4 m of track in 2 s).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

MIN_SAMPLES = 4
MIN_SPAN = 0.3  # s of corrections at least, so one noisy correction does not make a turn
# rad/s: a slower turn is no turn (the rate's noise on a straight track is ~0.07 rad/s), and the
# filter's own extrapolation stands, with its acceleration along the track (a braking drone)
MIN_RATE = 0.2


@dataclass(frozen=True)
class Turn:
    """A horizontal coordinated turn: the heading now (rad), turning at rate (rad/s,
    counter-clockwise seen from above)."""

    rate: float
    heading: float


class TurnHistory:
    """The last `window` s of one track's corrections, and the turn they show."""

    def __init__(self, window: float, min_speed: float, max_rate: float) -> None:
        self.window, self.min_speed, self.max_rate = window, min_speed, max_rate
        self._samples: deque[tuple[float, float, float, float]] = deque()  # (s, heading rad, x, y)

    def add(self, seconds: float, position: np.ndarray, velocity: np.ndarray) -> None:
        """A correction at `seconds`; a track rewound to an earlier correction forgets the
        samples from then on. Slower than min_speed its heading means nothing: the history ends."""
        while self._samples and self._samples[-1][0] >= seconds:
            self._samples.pop()
        vx, vy = float(velocity[0]), float(velocity[1])
        if np.hypot(vx, vy) < self.min_speed:
            self._samples.clear()
            return
        self._samples.append((seconds, float(np.arctan2(vy, vx)), float(position[0]), float(position[1])))
        while self._samples[0][0] < seconds - self.window:
            self._samples.popleft()

    def turn(self, now: float) -> Turn | None:
        """The turn at `now` (s; a track coasting since its last correction has turned on at the
        same rate); None until MIN_SAMPLES corrections over at least MIN_SPAN s are known, and
        for a turn slower than MIN_RATE."""
        if len(self._samples) < MIN_SAMPLES:
            return None
        t, heading, x, y = np.array(self._samples).T
        span = t[-1] - t[0]
        if span < MIN_SPAN:
            return None
        heading = np.unwrap(heading)
        centred = t - t.mean()
        rate = float(np.clip(centred @ (heading - heading.mean()) / (centred @ centred), -self.max_rate, self.max_rate))
        if abs(rate) < MIN_RATE:
            return None
        coasted = max(now - t[-1], 0.0)
        return Turn(rate, float(np.arctan2(y[-1] - y[0], x[-1] - x[0])) + rate * (0.5 * span + coasted))
