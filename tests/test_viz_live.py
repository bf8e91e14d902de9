"""The viewer's live input on real Zenoh sessions: it never blocks a publisher, drops scans first
when it falls behind, and bounds its queue whatever arrives."""
from __future__ import annotations

import time

import msgspec
import numpy as np
import pytest

from schemas.arrays import from_numpy
from schemas.messages import Header, Odometry, PointCloud, Pose
from services.lib.runtime.zenoh_config import ZenohSettings, open_session
from services.tools.viz.live import LiveFeed

pytestmark = pytest.mark.alone  # a feed timed on the wall clock


def test_a_viewer_that_does_not_keep_up_drops_scans_first_then_anything_past_its_bound(hub):
    session, endpoint = hub
    feed = LiveFeed(session, scan_backlog=5, max_backlog=20, health_period=0)
    publisher = open_session(ZenohSettings(connect=[endpoint], shared_memory=False))
    try:
        time.sleep(0.5)  # let the subscriptions reach the publisher
        cloud = msgspec.msgpack.encode(PointCloud(
            header=Header(stamp=1), width=4, height=2, sensor_pose=Pose(),
            points=from_numpy(np.zeros((2, 4, 3), np.float32))))
        odometry = msgspec.msgpack.encode(Odometry(header=Header(stamp=1), pose=Pose()))
        started = time.monotonic()
        for _ in range(60):  # nothing drains the feed meanwhile
            publisher.put("falconry/uav1/points", cloud)
            publisher.put("falconry/uav1/odometry", odometry)
        sent_in = time.monotonic() - started
        deadline = time.monotonic() + 10
        while feed.backlog + sum(feed.dropped.values()) < 120 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert feed.backlog + sum(feed.dropped.values()) == 120
        assert feed.backlog <= 21
        assert feed.dropped["points"] >= 60 - 6 and feed.dropped["odometry"] > 0
        assert "points" in feed.dropped_line()
        assert sent_in < 2.0  # the publisher was never held up
        first = feed.get(timeout=0.1)
        assert first is not None and first.key.startswith("falconry/uav1/") and first.received > 0
    finally:
        feed.close()
        publisher.close()
