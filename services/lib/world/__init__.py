"""The simulated world as the sensors see it: primitives built from the world model (primitives.py),
the numba ray caster over their packed table (raycast.py) and its numpy reference
(numpy_caster.py). The simulated LiDAR and camera both cast into it."""
