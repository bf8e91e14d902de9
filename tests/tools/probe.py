"""A listener that a test starts inside a UAV's network namespace: it joins the run at
`--connect` and prints one JSON line per status message and clock tick it receives
({"key", "stamp"} with the message's mission time in s), until stdin closes. It stands for
"what reaches this UAV" during a link cut.

    ip netns exec NS python -m tests.tools.probe --connect tcp/HUB:PORT --listen tcp/UAV_ADDRESS:0
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import threading

import msgspec

from schemas import keys
from schemas.messages import SimClock, UavStatus
from services.lib.runtime.zenoh_config import ZenohSettings, init_logging, open_session


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--connect", required=True)
    parser.add_argument("--listen", required=True, help="the namespace's own address, like its services")
    args = parser.parse_args()
    init_logging()
    session = open_session(ZenohSettings(connect=[args.connect], listen=[args.listen], shared_memory=False))
    status = msgspec.msgpack.Decoder(UavStatus)
    clock = msgspec.msgpack.Decoder(SimClock)

    lock = threading.Lock()  # callbacks run on several Zenoh threads: one whole line at a time

    def emit(decoder):
        def on_sample(sample) -> None:
            message = decoder.decode(sample.payload.to_bytes())
            line = json.dumps({"key": str(sample.key_expr), "stamp": message.header.stamp / 1e9})
            with lock:
                print(line, flush=True)
        return on_sample

    handles = [session.declare_subscriber(keys.ALL_STATUS, emit(status)),
               session.declare_subscriber(keys.CLOCK, emit(clock))]
    print(json.dumps({"key": "ready", "stamp": 0.0}), flush=True)
    try:
        sys.stdin.read()  # the test closes stdin to stop the probe
    finally:
        # The launcher tears the namespace's links down as the run ends, so a close may wait on a
        # dead link for Zenoh's whole timeout: give it a moment, then leave regardless.
        closer = threading.Thread(target=_close, args=(session, handles), daemon=True)
        closer.start()
        closer.join(timeout=3.0)
        sys.stdout.flush()
        os._exit(0)


def _close(session, handles) -> None:
    try:
        for handle in handles:
            handle.undeclare()
        session.close()
    except Exception:  # noqa: BLE001 - a session whose radio was cut may fail to close; we exit anyway
        pass

if __name__ == "__main__":
    main()
