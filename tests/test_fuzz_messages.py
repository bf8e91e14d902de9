"""Hypothesis fuzzes every subscribed message type through the real nodes: Zenoh's subscriber
callback, the node's decode and its counting, the handler, and the next clock tick that acts on
what the handler stored (tests/tools/fuzz.py has the payload families and the harness).

Each node is first given a realistic message of each of its other inputs (the world, its
odometry, ...), so the fuzzed one travels as far as it would in a run; what completes some inputs
(a scan's other half, a scan after a map) follows each fuzzed one (NEXT).

For every case and every node subscribed to the type: nothing escapes the node's loop; a payload
that does not decode is counted as a decode error on its key and reaches no handler; one that
decodes is counted as received and never as a decode error; and a message within the documented
contract (odd values included: NaN, ±inf, extremes, empty arrays) raises in no handler and no tick
(NOT_FIXED_HERE: listed instead). What the schema accepts but the contract does not (an array of the
wrong dtype or shape) may fail in a handler, where it is counted. The cases run per type are printed
once at the end of the session (tests/conftest.py).
"""
from __future__ import annotations

import re
import resource
from pathlib import Path

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings

from schemas import keys
from schemas.messages import LabelSet, PointCloud, PointTruth, SimClock, VoxelMap
from services.lib.runtime import node as runtime_node
from services.lib.voxels.replica import MapReplica
from tests.tools.fuzz import (CASES_RUN, FAMILIES, Case, FuzzRun, cases, corpus, encode, sparse, subscribers,
                              wire)

CASES_PER_TYPE = 1000
SUBSCRIBERS = subscribers()
# What a service does with some messages happens when another input arrives, sent after each fuzzed
# one with its stamp: a scan's other half for the mapper and the oracle, a scan for the classifier's map.
# The mapper and the classifier get every 8th row and 16th column of the scan: casting or classifying
# all of it after every case would double the time of their tests.
NEXT = {
    ("mapper", PointCloud): lambda seeds: seeds[LabelSet],
    ("mapper", LabelSet): lambda seeds: sparse(seeds[PointCloud], 8, 16),
    ("oracle", PointCloud): lambda seeds: seeds[PointTruth],
    ("oracle", PointTruth): lambda seeds: seeds[PointCloud],
    ("classifier", VoxelMap): lambda seeds: sparse(seeds[PointCloud], 8, 16),
}


@pytest.fixture
def runs(request) -> dict[str, FuzzRun]:
    return request.config.stash.setdefault(CASES_RUN, {})


@pytest.fixture
def gigabytes_refused():
    """No message may have a node allocate gigabytes (a lying PointCloud width once cost the mapper 12 GB):
    with 2 GiB more address space than the process holds, such an allocation fails at once, as a
    MemoryError the test sees, instead of taking the machine's memory."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    held = int(re.search(r"VmSize:\s+(\d+) kB", Path("/proc/self/status").read_text())[1]) * 1024
    limit = held + (2 << 30)
    resource.setrlimit(resource.RLIMIT_AS, (limit if soft == resource.RLIM_INFINITY else min(limit, soft), hard))
    yield
    resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def test_the_corpus_has_every_subscribed_type():
    assert set(SUBSCRIBERS) <= set(corpus())


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy's overflow and invalid-value warnings: expected
@pytest.mark.parametrize("msg_type", sorted(SUBSCRIBERS, key=lambda t: t.__name__), ids=lambda t: t.__name__)
@pytest.mark.slow(10)
def test_every_subscriber_survives_and_counts(msg_type, runs, monkeypatch, gigabytes_refused):
    # a fuzzed lockstep tick bounds keys nothing will send: give up waiting at once (counted as a timeout)
    monkeypatch.setattr(runtime_node, "INPUT_WAIT_S", 0.0)
    monkeypatch.setattr(runtime_node, "MESSAGE_WAIT_S", 0.0)
    # a map message may ask for any grid: refusing one takes the same path at 4 M voxels as at 268 M,
    # and holding the largest accepted one stays cheap (the default map is 2.5 M)
    monkeypatch.setattr(MapReplica, "MAX_VOXELS", 1 << 22)
    seeds = corpus()
    nodes = []
    for service in SUBSCRIBERS[msg_type]:
        wired = wire(service)
        for other in sorted(wired.subscribed() - {msg_type}, key=lambda t: t.__name__):
            wired.deliver(wired.keys_of[other], encode(seeds[other]))
        wired.tick()
        assert wired.node.counters.handler_errors == 0, "\n".join(wired.errors.records)
        nodes.append(wired)
    reference = msgspec.msgpack.Decoder(msg_type)
    fuzz_run = runs.setdefault(msg_type.__name__, FuzzRun(SUBSCRIBERS[msg_type]))
    run = fuzz_run.cases

    @settings(max_examples=CASES_PER_TYPE, deadline=None, derandomize=True, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(case=cases(msg_type))
    def fuzz(case: Case) -> None:
        run[case.family] += 1
        try:
            msg = reference.decode(case.payload)
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError):  # invalid UTF-8: UnicodeDecodeError
            msg = None
        for wired in nodes:
            node, key = wired.node, wired.keys_of[msg_type]
            counters = node.counters
            received, rejected = counters.received.get(key, 0), counters.decode_errors.get(key, 0)
            handler_errors = counters.handler_errors
            wired.deliver(key, case.payload)
            name = f"{node.service} on {key}"
            if msg is not None:
                assert counters.decode_errors.get(key, 0) == rejected, f"{name}: a decodable payload counted as bad"
                assert counters.received.get(key, 0) > received, f"{name}: a decodable payload not counted as received"
            else:
                assert counters.decode_errors.get(key, 0) == rejected + wired.subscriptions(key), \
                    f"{name}: a bad payload not counted (once per subscription it reached)"
                assert counters.received.get(key, 0) == received, f"{name}: a bad payload counted as received"
            if msg is None:
                continue  # it reached no handler: nothing changed
            if (follow := NEXT.get((node.service, msg_type))) is not None:
                then = follow(seeds)
                header = msgspec.structs.replace(then.header, stamp=msg.header.stamp)
                wired.deliver(wired.keys_of[type(then)], encode(msgspec.structs.replace(then, header=header)))
            if msg_type is SimClock:  # it was the tick; then the simulator restarts, to count from any step again
                wired.token(keys.alive(keys.SIM, "simulator"), False)
            else:
                wired.tick()
            if counters.handler_errors != handler_errors:
                error = wired.errors.records[-1]
                assert "MemoryError" not in error, f"{name}: a {msg_type.__name__} had it allocate gigabytes:\n{error}"
                assert case.family != "valid", f"{name}: a valid {msg_type.__name__} failed:\n{error}"

    fuzz()
    assert sum(run.values()) >= CASES_PER_TYPE
    assert all(run[family] for family in FAMILIES), run
