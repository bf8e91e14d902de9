"""Perception time per scan (seed 000): the classifier and the mapper of one UAV, each on one core,
on recorded OS0-128 × 1024 scans of mbzirc.

Records a lockstep run of `mbzirc` whose sensor drivers simulate an Ouster OS0-128 at 1024 columns
(or reads --recording), then replays uav1's scans through the two cores in the services' order:
classify the scan against the map replica, integrate it into the map (rays and label sets, the
a-priori map of the world model pinned as the mapper node does), hand the map delta to the
replica. Prints, per core, the median and 95th percentile time per scan (goal: each at most
25 ms median: VoFOD keeps up with 10 Hz in C++, two of them fit one core), the peak memory the
loop allocated (tracemalloc; numpy reports its buffers to it) and the process's resident memory,
and the size of a map delta message per scan (what would cross a radio link).

    .venv/bin/python benchmarks/perception.py                 # records 30 s of mbzirc first: ~2 min
    .venv/bin/python benchmarks/perception.py --recording run.mcap
"""
from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import tracemalloc  # noqa: E402
from pathlib import Path  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # a plain checkout works too

import msgspec  # noqa: E402
import numpy as np  # noqa: E402

from schemas.arrays import from_numpy, to_numpy  # noqa: E402
from schemas.messages import Header, PointCloud, VoxelMap, WorldModel  # noqa: E402
from services.classifier.core import SensorPose  # noqa: E402
from services.lib.geometry import rotation_matrix  # noqa: E402
from services.lib.lidar.rays import scan_rays  # noqa: E402
from services.tools.recorder.mcap_io import read_recording  # noqa: E402
from services.lib.runtime.health import process_usage  # noqa: E402

from perception_loop import PerceptionLoop  # noqa: E402  (beside this file)

GOAL_MS = 25.0
SENSOR = "os0-128-1024"
WARM_UP = 3  # scans left out of the figures (numba loads its caches, numpy warms up)


def record(path: Path, duration: float) -> None:
    config = path.with_suffix(".toml")
    config.write_text(f'[sensor_driver]\nmodel = "{SENSOR}"\n')
    argv = [sys.executable, "-m", "services.tools.launcher", "sim", "mbzirc", "--uavs", "2", "--lockstep", "--duration",
            str(duration), "--detector", "oracle", "--quiet", "--progress", "0", "--config", str(config),
            "--record", str(path)]
    print(f"recording {duration:g} s of mbzirc with {SENSOR} scans ...", flush=True)
    result = subprocess.run(argv, capture_output=True, text=True)
    if result.returncode != 0:
        raise SystemExit(f"recording failed:\n{result.stdout[-2000:]}{result.stderr[-2000:]}")


def load(path: Path, uav: str) -> tuple[WorldModel | None, list[PointCloud]]:
    world, clouds = None, []
    world_decoder, cloud_decoder = msgspec.msgpack.Decoder(WorldModel), msgspec.msgpack.Decoder(PointCloud)
    for message in read_recording(str(path), lambda k: k in ("falconry/sim/world", f"falconry/{uav}/points")):
        if message.key.endswith("/world"):
            world = world or world_decoder.decode(message.payload)
        else:
            clouds.append(cloud_decoder.decode(message.payload))
    return world, clouds


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recording", type=Path, help="an MCAP recording to read (default: record one)")
    parser.add_argument("--duration", type=float, default=30.0, help="mission time to record, s (default 30)")
    parser.add_argument("--uav", default="uav1", help="whose scans (default uav1)")
    args = parser.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # one core
    with tempfile.TemporaryDirectory() as tmp:
        path = args.recording
        if path is None:
            path = Path(tmp) / "perception.mcap"
            record(path, args.duration)
        world, clouds = load(path, args.uav)
    if not clouds:
        raise SystemExit(f"no scans of {args.uav} in the recording")
    print(f"{len(clouds)} scans of {args.uav}: {clouds[0].sensor_model}, {clouds[0].height} × {clouds[0].width}")

    loop = PerceptionLoop(apriori=world.obstacles if world is not None else None)
    mapper = loop.mapper
    encoder = msgspec.msgpack.Encoder()
    classify_ms, map_ms, delta_bytes, detections = [], [], [], 0
    tracemalloc.start()
    for k, cloud in enumerate(clouds):
        points = to_numpy(cloud.points)
        pose = SensorPose(np.asarray(cloud.sensor_pose.position), rotation_matrix(cloud.sensor_pose.orientation),
                          None if cloud.pose_covariance is None else to_numpy(cloud.pose_covariance))
        started = time.perf_counter()  # the mapper node makes the rays of each scan it receives
        rays = scan_rays(points, cloud.width, cloud.sensor_model, cloud.frame, cloud.sensor_pose.position,
                         cloud.sensor_pose.orientation, None if cloud.mask is None else to_numpy(cloud.mask))
        rays_s = time.perf_counter() - started
        step = loop.step(cloud.header.stamp, points, pose, rays)
        if k >= WARM_UP:
            classify_ms.append(step.classify_s * 1e3)
            map_ms.append((rays_s + step.map_s) * 1e3)
            delta_bytes.append(len(encoder.encode(VoxelMap(
                header=Header(stamp=cloud.header.stamp), snapshot=False, voxel_size=mapper.voxel_size,
                origin=mapper.params.origin, shape=mapper.shape, indices=from_numpy(step.delta.indices),
                values=from_numpy(step.delta.values)))))
            detections += len(step.scan.positions)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    _, resident = process_usage()

    print(f"\nper scan over {len(classify_ms)} scans (after {WARM_UP} warm-up), one core:")
    for name, values in (("classifier", classify_ms), ("mapper", map_ms)):
        median = statistics.median(values)
        print(f"  {name:<10} median {median:6.1f} ms   p95 {percentile(values, 95):6.1f} ms   "
              f"(goal <= {GOAL_MS:g} ms median: {'met' if median <= GOAL_MS else 'NOT met'})")
    print(f"  map delta  median {statistics.median(delta_bytes) / 1e3:6.1f} kB   p95 "
          f"{percentile(delta_bytes, 95) / 1e3:6.1f} kB   max {max(delta_bytes) / 1e3:6.1f} kB per scan "
          f"({statistics.mean(delta_bytes) * 10 / 1e3:.0f} kB/s at 10 Hz)")
    held = sum(c.points.data.nbytes for c in clouds)
    print(f"  memory     peak {peak / 1e6:.0f} MB allocated in the loop (two dense {mapper.grid.nbytes / 1e6:.0f} MB "
          f"grids and their scratch); {resident / 1e6:.0f} MB resident, {held / 1e6:.0f} MB of it the loaded scans")
    print(f"  detections {detections} in {len(classify_ms)} scans")
    return 0


if __name__ == "__main__":
    sys.exit(main())
