"""Recording and replay of Falconry runs as MCAP files (issue 3, item 6; first version).

- `mcap_io`: the file format: one channel per key expression, the raw msgpack payloads as
  message data, the message type's JSON Schema per channel; a tolerant reader that replays a
  file cut short by a crash up to its last complete chunk.
- `record`: `Recorder`, a Zenoh subscriber (or a feed from the caller's own session) writing
  every message it receives; `falconry record` and, later, `falconry sim --record` use it.
- `replay`: `Replayer`, which publishes a recording back, paced by its receive times or in
  lockstep as the clock master (`falconry replay --lockstep`), so perception can be re-run on
  exactly the same data.

Later work deepens it: conversion of payloads to JSON/CBOR for viewers that cannot decode
msgpack, replay of a time window, and a recorded-file source behind the sensor driver.
"""
