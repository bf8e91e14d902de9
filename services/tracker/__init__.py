"""tracker: multi-target tracking of flying objects with a constant-acceleration Kalman filter
per track (seed 000, sec. III-F). First version on detections only; later issues add the
point-cloud buffer of Alg. 2, map-based cluster rejection and alternative filters."""
