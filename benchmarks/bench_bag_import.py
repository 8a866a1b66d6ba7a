"""Benchmark: `contact-viz import bag` streams: peak memory flat in the bag's length.

Writes (with rosbags' own writers, under --workdir) two ROS bags of N and 4N stereo frames of
WIDTHxHEIGHT rgb8 images plus CameraInfo, a 1 kHz-ish wrench (10 samples per frame) and a pose per
frame, then imports each in a fresh process and prints the bag size, the import's wall time,
frames/s, and its peak RSS. Budget: the 4N bag's peak RSS within 15% of the N bag's (the images
are written as they are read; only stamps are kept).

Run: .venv/bin/python benchmarks/bench_bag_import.py [--frames 100] [--size 640x360] [--flavour ros1|ros2|mcap]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
from contact_viz.io.importers.bag import import_bag
result = import_bag(sys.argv[1], sys.argv[2])
print(json.dumps({"frames": result.frames, "seconds": time.perf_counter() - t0,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def write_bag(path: Path, flavour: str, frames: int, width: int, height: int) -> Path:
    from rosbags.typesys import Stores, get_typestore

    ros1 = flavour == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        writer = Writer(path, version=9,
                        storage_plugin=StoragePlugin.MCAP if flavour == "mcap" else StoragePlugin.SQLITE3)

    def header(ns: int):
        stamp = T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)
        fields = dict(stamp=stamp, frame_id="cam")
        return T["std_msgs/msg/Header"](seq=0, **fields) if ros1 else T["std_msgs/msg/Header"](**fields)

    yy, xx = np.mgrid[0:height, 0:width]
    base = np.stack([(xx * 255 // width), (yy * 255 // height), ((xx + yy) % 256)], axis=2).astype(np.uint8)
    rng = np.random.default_rng(0)
    fx = 0.8 * width
    with writer:
        conns = {}
        for topic, msgtype in (("/jhu_daVinci/left/image_raw", "sensor_msgs/msg/Image"),
                               ("/jhu_daVinci/right/image_raw", "sensor_msgs/msg/Image"),
                               ("/jhu_daVinci/left/camera_info", "sensor_msgs/msg/CameraInfo"),
                               ("/jhu_daVinci/right/camera_info", "sensor_msgs/msg/CameraInfo"),
                               ("/force_sensor/measured_cf", "geometry_msgs/msg/WrenchStamped"),
                               ("/PSM1/measured_cp", "geometry_msgs/msg/PoseStamped")):
            conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
        for side, tx in (("left", 0.0), ("right", -fx * 0.005)):
            K = np.array([fx, 0, width / 2, 0, fx, height / 2, 0, 0, 1], dtype=np.float64)
            P = np.array([fx, 0, width / 2, tx, 0, fx, height / 2, 0, 0, 0, 1, 0], dtype=np.float64)
            arrays = {"d": np.zeros(5), "k": K, "r": np.eye(3).ravel(), "p": P}
            roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
            msg = T["sensor_msgs/msg/CameraInfo"](header=header(1), height=height, width=width,
                                                  distortion_model="plumb_bob", binning_x=0, binning_y=0, roi=roi,
                                                  **{(k.upper() if ros1 else k): v for k, v in arrays.items()})
            writer.write(conns[f"/jhu_daVinci/{side}/camera_info"], 1,
                         serialize(msg, "sensor_msgs/msg/CameraInfo"))
        V3 = T["geometry_msgs/msg/Vector3"]
        for i in range(frames):
            ns = 10**9 + i * 33_333_333
            for side in ("left", "right"):
                pixels = np.roll(base, i, axis=1) ^ rng.integers(0, 8, base.shape, dtype=np.uint8)
                msg = T["sensor_msgs/msg/Image"](header=header(ns), height=height, width=width, encoding="rgb8",
                                                 is_bigendian=0, step=width * 3, data=pixels.ravel())
                writer.write(conns[f"/jhu_daVinci/{side}/image_raw"], ns, serialize(msg, "sensor_msgs/msg/Image"))
            for k in range(10):
                t = ns + k * 3_333_333
                wrench = T["geometry_msgs/msg/Wrench"](force=V3(x=0.1 * k, y=0.0, z=1.0), torque=V3(x=0.0, y=0.0, z=0.0))
                msg = T["geometry_msgs/msg/WrenchStamped"](header=header(t), wrench=wrench)
                writer.write(conns["/force_sensor/measured_cf"], t, serialize(msg, "geometry_msgs/msg/WrenchStamped"))
            pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=0.0, y=0.0, z=0.1 + 1e-4 * i),
                                               orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0))
            msg = T["geometry_msgs/msg/PoseStamped"](header=header(ns), pose=pose)
            writer.write(conns["/PSM1/measured_cp"], ns, serialize(msg, "geometry_msgs/msg/PoseStamped"))
    return path


def size_mb(path: Path) -> float:
    files = [path] if path.is_file() else [p for p in path.rglob("*") if p.is_file()]
    return sum(p.stat().st_size for p in files) / 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100, help="N: frames of the short bag (the long one has 4N)")
    parser.add_argument("--size", default="640x360", help="image size WIDTHxHEIGHT")
    parser.add_argument("--flavour", default="ros1", choices=("ros1", "ros2", "mcap"))
    parser.add_argument("--workdir", type=Path, default=None)
    args = parser.parse_args()
    width, height = (int(v) for v in args.size.lower().split("x"))
    work = Path(tempfile.mkdtemp(prefix="bench_bag_", dir=args.workdir))
    try:
        results = {}
        for frames in (args.frames, 4 * args.frames):
            bag = write_bag(work / (f"n{frames}.bag" if args.flavour == "ros1" else f"n{frames}"), args.flavour,
                            frames, width, height)
            out = work / f"s{frames}"
            t0 = time.perf_counter()
            proc = subprocess.run([sys.executable, "-c", CHILD, str(bag), str(out)], capture_output=True, text=True,
                                  check=True)
            wall = time.perf_counter() - t0
            results[frames] = {**json.loads(proc.stdout.strip().splitlines()[-1]), "wall_s": wall,
                               "bag_mb": size_mb(bag)}
            shutil.rmtree(out)
            shutil.rmtree(bag) if bag.is_dir() else bag.unlink()
        print(f"{args.flavour} bags, {width}x{height} rgb8 stereo, 10 wrench samples and 1 pose per frame")
        print(f"{'frames':>7} {'bag MB':>8} {'import s':>9} {'frames/s':>9} {'peak RSS MB':>12}")
        for frames, r in results.items():
            print(f"{frames:>7} {r['bag_mb']:>8.1f} {r['seconds']:>9.2f} {frames / r['seconds']:>9.1f} "
                  f"{r['peak_rss_mb']:>12.1f}")
        short, long = results[args.frames], results[4 * args.frames]
        ratio = long["peak_rss_mb"] / short["peak_rss_mb"]
        print(f"peak RSS ratio 4N / N: {ratio:.3f} (budget <= 1.15: {'met' if ratio <= 1.15 else 'NOT met'})")
    finally:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
