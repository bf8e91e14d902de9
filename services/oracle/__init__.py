"""The oracle detector (evaluation only): noisy detections made from the LiDAR points that
really hit a target, in place of the classifier until the real perception pipeline lands.

First version (issue 3): centroid of each target's returned points plus gaussian noise. It
reads the sensor driver's per-ray hit ids (falconry/<uav>/points_truth), never GroundTruth, so
visibility, range, occlusion and sparse returns are those of the real scan. Later work adds
misses and false alarms with set rates, and point-by-point scoring of the real detector.
"""
