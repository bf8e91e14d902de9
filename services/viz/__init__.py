"""The fleet viewer: every UAV's beliefs, the world and the evaluation layer in one rerun recording,
live from a run or converted from any MCAP recording (`falconry view`, `falconry sim --viz/--rrd`)."""
