"""mapper: owns the occupancy voxel map G(v) (seed 000, sec. III-A, III-C). First version with
hard label assignments and sampled free-space rays; later issues add the exponential weighted
update, exact ray lengths, separate-cluster reset and a-priori initialisation."""
