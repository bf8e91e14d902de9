"""The sensor_driver service: organised LiDAR scans of one UAV on falconry/<uav>/points.

First version (walking skeleton): a simulated rotating 32×512 LiDAR ray-cast in numpy against
the simulator's world and targets. Later issues deepen it: Ouster/Livox beam models, a
numba-compiled caster, replay of recorded files and real hardware behind the same output.
"""
