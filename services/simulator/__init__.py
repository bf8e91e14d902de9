"""The simulator service: arena, static obstacles, targets, point-mass UAV dynamics, ground
truth and the mission clock (one per run).

First version (walking skeleton): balloons on poles and circling intruder drones, point-mass
vehicles tracking their trajectory reference, balloon destruction by proximity. Later issues
deepen it with drone capture, scripted drone paths, a fault schedule and richer dynamics.
`scenario.py` reads scenario files, `core.py` is the pure physics, `node.py` the clock and wiring.
"""
