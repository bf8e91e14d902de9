"""The sensor_driver service: organised LiDAR scans of one UAV on falconry/<uav>/points, and
(simulation, evaluation only) the id of what each ray hit on falconry/<uav>/points_truth.

Ouster OS0/OS1 and Livox Mid-360 models (services/lib/lidar/models.py) cast into the simulated
world (services/lib/world: the primitives and the numba caster the camera shares), range and sensor
pose noise, a carrier body mask, optional intensity, the scheduled LiDAR faults (faults.py) and
the sanity checks every scan passes before it goes out (services/lib/lidar/sanity.py).
"""
