"""The simulator service (one per run): arena, static obstacles, targets, point-mass UAV
dynamics with noisy odometry and emergency landing, collisions of the UAVs' bodies with obstacles,
each other and the ground, balloons swaying in wind, scripted intruder drones that can be
captured, the scenario's fault schedule, ground truth and the mission clock.

`scenario.py`, `specs.py` and `checks.py` read and validate scenario files; `vehicles.py`,
`targets.py`, `paths.py` and `contact.py` are the pure physics that `core.py` ties together;
`node.py` drives the clock and wires it all to Zenoh.
"""
