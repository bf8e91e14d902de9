"""Falconry's code in three layers above the contract (schemas/), each importing only downwards
(tests/test_layers.py holds it; docs/architecture.md draws it):

- `lib/`: what the services share: the runtime (Zenoh sessions, clocks, the lockstep gate, the
  service base), geometry, voxels, the LiDAR models, the simulated world's primitives and caster,
  track views, the IMU model, the pinhole camera model.
- the services, one folder each (camera, classifier, job_manager, localizer, mapper,
  object_detect, oracle, planner, sensor_driver, simulator, tracker): a pure `core` and a thin
  Zenoh `node`; a service imports the contract and `lib/`, never another service.
- `tools/`: what runs the services and looks at their runs: the launcher (the `falconry` command),
  the recorder, evaluation against ground truth, the viewer.
"""
