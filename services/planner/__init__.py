"""planner: turns mission commands into timed trajectory references (seed 004, ch. 5) that keep
clear of what the UAV knows is occupied, and guards them in flight.

- core.py, timing.py, scan.py, pursuit.py, intercept.py: the seed's manoeuvres and their time
  parameterisation;
- freespace.py, search.py, avoid.py: the map the planner keeps from its mapper, the path search on
  it, and each manoeuvre routed, timed and checked against it;
- guard.py: the active reference's next seconds against the latest map, every tick;
- commands.py: which manoeuvre a command gets; node.py wires it all to Zenoh.
"""
