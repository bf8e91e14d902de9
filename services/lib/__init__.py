"""The libraries the services share (they import only the contract and each other, without a
cycle): runtime, geometry, voxels, lidar, world (the simulated world's primitives and caster),
tracks (how a Track message is read), imu (the IMU model the simulator samples and the localizer
fuses), pinhole (the camera intrinsics the camera and Object Detect share)."""
