"""Recording and replay of Falconry runs as MCAP files.

- `mcap_io`: the file format: one channel per key expression, the raw msgpack payloads as
  message data, the message type's JSON Schema per channel; a tolerant reader that replays a
  file cut short by a crash up to its last complete chunk.
- `record`: `Recorder`, a Zenoh subscriber (or a feed from the caller's own session) writing
  the messages it receives (`falconry record`, `falconry sim --record`).
- `replay`: `Replayer`, which publishes a recording back, paced by its receive times or in
  lockstep as the clock master (`falconry replay --lockstep`), so perception can be re-run on
  exactly the same data; `schedule` orders it, `selection` picks the services it feeds.
- `json_view`: any message as JSON (the Foxglove export and `falconry export` use it).
"""
