"""tracker: multi-target tracking of flying objects (seed 000, sec. III-F, Alg. 2).

- core.py: the buffered point-cloud tracker (one filter per track, detections replayed through
  the buffered scans, map-based cluster rejection, identities kept for targets that come back);
- filters/: the swappable tracking filters (constant-acceleration Kalman filter, seed 002's
  adaptive EKF, a particle filter) and the parts they are made of;
- fleet.py: the own tracks fused with the partners' (covariance intersection);
- kernels.py: the compiled per-point pass; node.py wires it all to Zenoh;
- frontend.py, single.py: seed 002's single-target front end and loop, for the filter comparison
  (benchmarks/tracking_comparison.py), not used by the node.
"""
