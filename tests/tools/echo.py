"""A second process for round-trip tests: decodes every message type it receives on
test/in/<Type> with the typed decoder and publishes it re-encoded on test/out/<Type>."""
from __future__ import annotations

import queue

import msgspec

from schemas.messages import ALL_MESSAGES
from services.lib.runtime.zenoh_config import ZenohSettings, init_logging, open_session


def echo_main(endpoint: str) -> None:
    init_logging()
    # multiprocessing ends its children with os._exit, which skips Zenoh's /dev/shm clean-up
    session = open_session(ZenohSettings(connect=[endpoint], shared_memory=False))
    inbox: queue.SimpleQueue = queue.SimpleQueue()
    decoders = {t.__name__: msgspec.msgpack.Decoder(t) for t in ALL_MESSAGES}
    publishers = {name: session.declare_publisher(f"test/out/{name}") for name in decoders}
    subs = [
        session.declare_subscriber("test/in/*", lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes()))),
        session.declare_subscriber("test/stop", lambda s: inbox.put(("stop", b""))),
    ]
    token = session.liveliness().declare_token("test/alive/echo")
    try:
        while True:
            key, payload = inbox.get(timeout=60)
            if key == "stop":
                break
            name = key.rsplit("/", 1)[-1]
            msg = decoders[name].decode(payload)
            publishers[name].put(msgspec.msgpack.encode(msg))
    finally:
        token.undeclare()
        for sub in subs:
            sub.undeclare()
        session.close()
