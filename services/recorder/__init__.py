"""Recording and replay of Falconry runs as MCAP files (issue 3, item 6; first version).

- `mcap_io`: the file format: one channel per key expression, the raw msgpack payloads as
  message data, the message type's JSON Schema per channel; a tolerant reader that replays a
  file cut short by a crash up to its last complete chunk.
- `record`: `Recorder`, a Zenoh subscriber (or a feed from the caller's own session) writing
  every message it receives; `falconry record` and, later, `falconry sim --record` use it.
- `replay`: `Replayer`, which publishes a recording back, paced by its receive times or in
  lockstep as the clock master (`falconry replay --lockstep`), so perception can be re-run on
  exactly the same data.
- `foxglove_export` (with `json_view` and `foxglove_schemas`): `falconry export --format
  foxglove`, a recording as JSON with JSON Schemas, Foxglove's own types where it has one
  (point clouds, poses and frames, scene entities, images).
"""
