"""LiDAR knowledge shared by whoever needs a sensor's beam layout: the simulated driver that fires
the beams and the mapper that casts the rays which returned nothing (pure numpy)."""
