"""The sensor_driver service: organised LiDAR scans of one UAV on falconry/<uav>/points, and
(simulation, evaluation only) the id of what each ray hit on falconry/<uav>/points_truth.

Second version (issue 3): Ouster OS0/OS1 and Livox Mid-360 models (services/lidar/models.py), a numba ray
caster (raycast.py) checked against the numpy reference (numpy_caster.py), range and sensor
pose noise, a carrier body mask, optional intensity and the scheduled LiDAR faults (faults.py).
Later work deepens it: motion distortion within a frame, dropouts and weather, replay of
recorded files and real hardware behind the same output.
"""
