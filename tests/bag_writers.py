"""Small real ROS bags for the tests, written with rosbags' own writers from a `contact-viz synth` session.

Each bag holds the session's left and right images, two CameraInfo topics from its K.txt, its
force as WrenchStamped at three samples per frame (the frame's own value at the frame's stamp and
two others between frames), and a tool pose per frame. Stamps: frame i at round(i * 1e9 / fps) ns
(the session's own times); right images 1 ms later; one extra right image after the last frame.
"""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np

FORCE_BETWEEN_N = 100.0  # force of the between-frame samples (far from every frame's own value), N
RIGHT_DELAY_NS = 1_000_000  # right images are stamped this much after the left ones, ns


def session_tables(session: Path) -> dict:
    """K (3, 3), baseline (m), fps, per-frame force (n, 3) and the sorted stems of a synth session."""
    lines = (session / "K.txt").read_text().split("\n")
    K = np.array([float(v) for v in lines[0].split()]).reshape(3, 3)
    baseline = float(lines[1])
    with open(session / "force.csv") as handle:
        force = np.array([[float(r["fx"]), float(r["fy"]), float(r["fz"])] for r in csv.DictReader(handle)])
    stems = sorted(p.stem for p in (session / "left").iterdir())
    return {"K": K, "baseline": baseline, "fps": 30.0, "force": force, "stems": stems}


def poses(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) positions (m) and (n, 4) unit quaternions (x, y, z, w) of a known tool track."""
    i = np.arange(n, dtype=np.float64)
    position = np.stack([0.01 + 0.001 * i, -0.02 + 0.0005 * i, 0.08 - 0.001 * i], axis=1)
    angle = 0.1 * i
    quat = np.stack([np.zeros(n), np.sin(angle / 2), np.zeros(n), np.cos(angle / 2)], axis=1)
    return position, quat


def write_bag(session: Path, out: Path, flavour: str, *, left: str = "/jhu_daVinci/left/image_raw",
              right: str = "/jhu_daVinci/right/image_raw", left_info: str = "/jhu_daVinci/left/camera_info",
              right_info: str = "/jhu_daVinci/right/camera_info", force: str = "/force_sensor/measured_cf",
              pose: str = "/PSM1/measured_cp", encoding: str = "rgb8", compressed: bool = False,
              pose_type: str = "PoseStamped", skip_right: tuple[int, ...] = (), extra_right: bool = True,
              sizes: dict[int, tuple[int, int]] | None = None, with_info: bool = True) -> Path:
    """Write ``session`` as a ``flavour`` ("ros1", "ros2" sqlite3, "mcap") bag at ``out``; returns the path to import."""
    from rosbags.typesys import Stores, get_typestore

    tables = session_tables(session)
    ros1 = flavour == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    T = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    Header, Time = T["std_msgs/msg/Header"], T["builtin_interfaces/msg/Time"]

    def header(ns: int, frame_id: str = "camera"):
        stamp = Time(sec=ns // 10**9, nanosec=ns % 10**9)
        return Header(seq=0, stamp=stamp, frame_id=frame_id) if ros1 else Header(stamp=stamp, frame_id=frame_id)

    if ros1:
        from rosbags.rosbag1 import Writer

        writer = Writer(out)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        plugin = StoragePlugin.MCAP if flavour == "mcap" else StoragePlugin.SQLITE3
        writer = Writer(out, version=9, storage_plugin=plugin)
    messages = []  # (log time ns, connection key, message, type)
    fps, n = tables["fps"], len(tables["stems"])
    stamps = [round(i * 1e9 / fps) for i in range(n)]
    image_type = "sensor_msgs/msg/CompressedImage" if compressed else "sensor_msgs/msg/Image"

    def image_msg(path: Path, ns: int, index: int):
        if compressed:
            data = np.frombuffer(path.read_bytes(), dtype=np.uint8)
            return T[image_type](header=header(ns), format="jpeg", data=data)
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if sizes and index in sizes:
            bgr = cv2.resize(bgr, sizes[index])
        pixels = {"rgb8": lambda: bgr[:, :, ::-1], "bgr8": lambda: bgr,
                  "mono8": lambda: cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)}.get(encoding, lambda: bgr)()
        pixels = np.ascontiguousarray(pixels)
        height, width = pixels.shape[:2]
        channels = 1 if pixels.ndim == 2 else pixels.shape[2]
        return T[image_type](header=header(ns), height=height, width=width, encoding=encoding, is_bigendian=0,
                             step=width * channels, data=pixels.ravel())

    for i, stem in enumerate(tables["stems"]):
        messages.append((stamps[i], "left", image_msg(session / "left" / f"{stem}.jpg", stamps[i], i), image_type))
        if i not in skip_right:
            ns = stamps[i] + RIGHT_DELAY_NS
            messages.append((ns, "right", image_msg(session / "right" / f"{stem}.jpg", ns, i), image_type))
    if extra_right:
        ns = stamps[-1] + round(0.5e9 / fps)
        messages.append((ns, "right", image_msg(session / "right" / f"{tables['stems'][-1]}.jpg", ns, n - 1),
                         image_type))
    K, baseline = tables["K"], tables["baseline"]
    height, width = cv2.imread(str(session / "left" / f"{tables['stems'][0]}.jpg")).shape[:2]
    if with_info:
        for key, tx in (("left_info", 0.0), ("right_info", -K[0, 0] * baseline)):
            P = np.array([K[0, 0], 0, K[0, 2], tx, 0, K[1, 1], K[1, 2], 0, 0, 0, 1, 0], dtype=np.float64)
            fields = dict(header=header(0), height=height, width=width, distortion_model="plumb_bob",
                          binning_x=0, binning_y=0,
                          roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0,
                                                                   do_rectify=False))
            arrays = {"d": np.zeros(5), "k": K.ravel().astype(np.float64), "r": np.eye(3).ravel(), "p": P}
            fields.update({(k.upper() if ros1 else k): v for k, v in arrays.items()})
            messages.append((1, key, T["sensor_msgs/msg/CameraInfo"](**fields), "sensor_msgs/msg/CameraInfo"))
    Vector3, Wrench = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Wrench"]
    for i in range(n):
        for k in range(3):
            ns = stamps[i] + round(k * 1e9 / fps / 3)
            value = tables["force"][i] if k == 0 else np.full(3, FORCE_BETWEEN_N)
            wrench = Wrench(force=Vector3(x=float(value[0]), y=float(value[1]), z=float(value[2])),
                            torque=Vector3(x=0.0, y=0.0, z=0.0))
            messages.append((ns, "force", T["geometry_msgs/msg/WrenchStamped"](header=header(ns, "ft"), wrench=wrench),
                             "geometry_msgs/msg/WrenchStamped"))
    position, quat = poses(n)
    Point, Quaternion = T["geometry_msgs/msg/Point"], T["geometry_msgs/msg/Quaternion"]
    for i in range(n):
        q = Quaternion(x=quat[i, 0], y=quat[i, 1], z=quat[i, 2], w=quat[i, 3])
        if pose_type == "PoseStamped":
            msg = T["geometry_msgs/msg/PoseStamped"](header=header(stamps[i], "PSM1_base"), pose=T[
                "geometry_msgs/msg/Pose"](position=Point(x=position[i, 0], y=position[i, 1], z=position[i, 2]),
                                          orientation=q))
        else:
            msg = T["geometry_msgs/msg/TransformStamped"](
                header=header(stamps[i], "PSM1_base"), child_frame_id="PSM1_tip",
                transform=T["geometry_msgs/msg/Transform"](translation=Vector3(
                    x=position[i, 0], y=position[i, 1], z=position[i, 2]), rotation=q))
        messages.append((stamps[i], "pose", msg, f"geometry_msgs/msg/{pose_type}"))
    topics = {"left": left, "right": right, "left_info": left_info, "right_info": right_info, "force": force,
              "pose": pose}
    with writer:
        connections = {}
        for _, key, _, msgtype in messages:
            if key not in connections:
                connections[key] = writer.add_connection(topics[key], msgtype, typestore=store)
        for ns, key, msg, msgtype in sorted(messages, key=lambda m: m[0]):
            writer.write(connections[key], ns, serialize(msg, msgtype))
    if flavour == "mcap":
        return next(out.glob("*.mcap"))
    return out
