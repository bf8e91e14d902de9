"""The oracle detector (evaluation only): noisy detections made from the LiDAR points that
really hit a target, and the label sets of a classifier that never errs, in place of the
classifier (`falconry sim --detector oracle`).

It reads the sensor driver's per-ray hit ids (falconry/<uav>/points_truth), never GroundTruth, so
visibility, range, occlusion and sparse returns are those of the real scan, and the mapper learns
free and occupied space as it does behind the classifier.
"""
