"""Looking at runs: the fleet viewer (every UAV's beliefs, the world and the evaluation layer in one
rerun recording, live from a run or converted from any MCAP recording: `falconry view`, `falconry
sim --viz/--rrd`) and the export of a recording to Foxglove (`foxglove_export` with
`foxglove_schemas`: `falconry export --format foxglove`, JSON with JSON Schemas, Foxglove's own
types where it has one: point clouds, poses and frames, scene entities, images).
"""
