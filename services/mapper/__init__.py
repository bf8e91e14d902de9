"""mapper: owns the occupancy voxel map G(v) (seed 000, sec. III-A, III-C, III-D, III-E): the
exponential update from the classifier's label sets and exact ray lengths, the separate-cluster
reset and the pinned a-priori map. core.py is the algorithm, update.py its compiled passes,
node.py the Zenoh wiring (deltas of changed voxel states, periodic snapshots)."""
