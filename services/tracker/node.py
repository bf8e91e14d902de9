"""tracker node: detections in, tracks out (first version, see core.py).

Subscribes falconry/<uav>/detections (Detections). Publishes falconry/<uav>/tracks (Tracks)
on every tick while there are tracks, each predicted to the tick's time, and an empty Tracks
at least once per second of mission time otherwise so subscribers know the tracker is alive.
Later versions also subscribe falconry/<uav>/points and falconry/<uav>/map (Alg. 2).
"""
from __future__ import annotations

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import Detections, Header, Track, Tracks
from services.runtime.clock import to_ns
from services.runtime.counted import CountedWarnings
from services.runtime.node import Node
from services.runtime.warmup import preload
from services.tracker.core import TrackerCore, TrackerParams


class TrackerNode(Node):
    service = "tracker"
    upstream = ("classifier", keys.ORACLE)  # whichever detector runs
    params_type = TrackerParams

    def setup(self) -> None:
        preload("filterpy.kalman", "scipy.optimize")  # the Kalman and assignment libraries, beside start-up
        self.core = TrackerCore(self.params)
        self.tracks_pub = self.publisher(self.topic("tracks"), Tracks)
        self.subscribe(self.topic("detections"), Detections, self.on_detections)
        self._alive_period_ns = to_ns(self.params.alive_period)
        self._last_published_ns: int | None = None
        self._bad_input = CountedWarnings(self.log)

    def on_detections(self, msg: Detections, key: str) -> None:
        positions = to_numpy(msg.positions)
        covariances = to_numpy(msg.covariances) if len(positions) else None
        self.core.update(msg.header.stamp, positions, covariances)
        self._bad_input.update({"detections with a non-finite position or an impossible covariance dropped":
                                self.core.rejected_detections,
                                "tracks dropped whose filter diverged to inf or NaN": self.core.diverged_tracks})

    def on_tick(self, now_ns: int) -> None:
        for track_id in self.core.prune(now_ns):
            self.log.debug("track %d lost", track_id)
        estimates = self.core.estimates(now_ns)
        quiet = self._last_published_ns is None or now_ns - self._last_published_ns >= self._alive_period_ns
        if not estimates and not quiet:
            return
        self._last_published_ns = now_ns
        self.tracks_pub.put(Tracks(header=Header(stamp=now_ns), tracks=[
            Track(
                id=e.id,
                state=from_numpy(e.state),
                covariance=from_numpy(e.covariance),
                detections=e.detections,
                confirmed=e.confirmed,
                uncertainty_radius=e.uncertainty_radius,
                last_detection=e.last_detection,
            )
            for e in estimates
        ]))


NODE = TrackerNode
