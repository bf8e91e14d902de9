"""classifier: clusters each LiDAR scan against its replica of the map and labels the clusters
background / flying object / unknown (seed 000, sec. III-B: rule A's d_close search, rule B's
flood fill of Alg. 1); publishes a detection per flying object and the voxel label sets for the
mapper. core.py is the algorithm, kernels.py its compiled passes, node.py the Zenoh wiring."""
