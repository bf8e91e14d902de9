"""Voxel-map code shared by the services that hold or read an occupancy map (pure numpy)."""
