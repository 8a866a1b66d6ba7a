"""ROS messages (as deserialized by ``rosbags``) to session files: images, calibration, force, pose.

Pure conversions, no bag reading: :mod:`contact_viz.io.importers.bag` calls these one message at a
time. Field names of ROS 1 (``K``, ``D``, ``R``, ``P``) and ROS 2 (``k``, ``d``, ``r``, ``p``)
CameraInfo are both accepted.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import cv2
import numpy as np

from contact_viz.io.decoders import JPEG_SOI
from contact_viz.io.importers.common import NS_PER_S

__all__ = [
    "IMAGE_ENCODINGS",
    "EncodedImage",
    "camera_info_yaml",
    "compressed_image",
    "image_message",
    "pose_row",
    "stamp_ns",
    "wrench_xyz",
]

# ROS image encoding -> (channels, bytes per channel, OpenCV conversion to BGR or None, channel order)
# "order": "rgb" = swap to BGR for writing, "bgr" = as is, "gray" = one channel, "cv" = use the conversion
_BAYER = {  # ROS names the first row's pattern; OpenCV's RGGB aliases use the same naming
    "rggb": cv2.COLOR_BayerRGGB2BGR, "bggr": cv2.COLOR_BayerBGGR2BGR,
    "gbrg": cv2.COLOR_BayerGBRG2BGR, "grbg": cv2.COLOR_BayerGRBG2BGR,
}
IMAGE_ENCODINGS: dict[str, tuple[int, int, str, int | None]] = {
    "rgb8": (3, 1, "rgb", None), "bgr8": (3, 1, "bgr", None), "8uc3": (3, 1, "bgr", None),
    "rgba8": (4, 1, "rgb", None), "bgra8": (4, 1, "bgr", None), "8uc4": (4, 1, "bgr", None),
    "mono8": (1, 1, "gray", None), "8uc1": (1, 1, "gray", None),
    "rgb16": (3, 2, "rgb", None), "bgr16": (3, 2, "bgr", None), "16uc3": (3, 2, "bgr", None),
    "rgba16": (4, 2, "rgb", None), "bgra16": (4, 2, "bgr", None),
    "mono16": (1, 2, "gray", None), "16uc1": (1, 2, "gray", None),
    "uyvy": (2, 1, "cv", cv2.COLOR_YUV2BGR_UYVY), "yuv422": (2, 1, "cv", cv2.COLOR_YUV2BGR_UYVY),
    "yuyv": (2, 1, "cv", cv2.COLOR_YUV2BGR_YUYV), "yuv422_yuy2": (2, 1, "cv", cv2.COLOR_YUV2BGR_YUYV),
    **{f"bayer_{p}8": (1, 1, "cv", code) for p, code in _BAYER.items()},
    **{f"bayer_{p}16": (1, 2, "cv", code) for p, code in _BAYER.items()},
}
PNG_COMPRESSION = 1  # zlib level of written PNGs (lossless): 63 ms vs 107 ms at level 3 for a 640x360 frame, 3% larger
_PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


class MessageError(ValueError):
    """A message that cannot be converted; the text says what was expected (the caller names the topic)."""


@dataclass(frozen=True)
class EncodedImage:
    """An image ready to be written as a file: its bytes, file suffix and size."""

    data: bytes  # file contents (PNG or JPEG)
    suffix: str  # ".png" or ".jpg"
    shape: tuple[int, int]  # (height, width), px


def stamp_ns(msg, log_time_ns: int) -> int:
    """The message's header stamp in ns; the bag's receive time when it has no header or a zero stamp."""
    header = getattr(msg, "header", None)
    if header is None:
        return int(log_time_ns)
    stamp = header.stamp
    ns = int(stamp.sec) * NS_PER_S + int(getattr(stamp, "nanosec", getattr(stamp, "nsec", 0)))
    return ns if ns != 0 else int(log_time_ns)


def image_message(msg) -> EncodedImage:
    """A ``sensor_msgs/Image`` as a lossless PNG (8-bit, or 16-bit for 16-bit encodings)."""
    encoding = str(msg.encoding).strip().lower()
    if encoding not in IMAGE_ENCODINGS:
        raise MessageError(f"expected an image encoding OpenCV can convert ({', '.join(sorted(IMAGE_ENCODINGS))}), "
                           f"found {msg.encoding!r}")
    channels, depth, order, code = IMAGE_ENCODINGS[encoding]
    height, width, step = int(msg.height), int(msg.width), int(msg.step)
    row_bytes = width * channels * depth
    data = np.frombuffer(memoryview(msg.data), dtype=np.uint8) if not isinstance(msg.data, np.ndarray) \
        else msg.data.view(np.uint8).ravel()
    if height < 1 or width < 1 or step < row_bytes or data.size < step * height:
        raise MessageError(f"expected {height} rows of step {step} >= {row_bytes} bytes ({width} px x {channels} "
                           f"channels x {depth} bytes, {msg.encoding}), found {data.size} bytes of data")
    rows = data[: step * height].reshape(height, step)[:, :row_bytes]
    if depth == 2:
        pixels = rows.copy().view(">u2" if msg.is_bigendian else "<u2").astype(np.uint16)
    else:
        pixels = rows
    pixels = pixels.reshape(height, width, channels) if channels > 1 else pixels.reshape(height, width)
    if order == "rgb":
        pixels = cv2.cvtColor(np.ascontiguousarray(pixels), cv2.COLOR_RGBA2BGRA if channels == 4 else cv2.COLOR_RGB2BGR)
    elif order == "cv":
        pixels = cv2.cvtColor(np.ascontiguousarray(pixels), code)
    if pixels.ndim == 3 and pixels.shape[2] == 4:
        pixels = pixels[:, :, :3]  # alpha dropped
    ok, buffer = cv2.imencode(".png", np.ascontiguousarray(pixels), [cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION])
    if not ok:
        raise MessageError(f"could not encode the {width}x{height} {msg.encoding} image as PNG")
    return EncodedImage(buffer.tobytes(), ".png", (height, width))


def compressed_image(msg) -> EncodedImage:
    """A ``sensor_msgs/CompressedImage`` (JPEG or PNG): its bytes as they are, size from the file header."""
    from PIL import Image

    data = bytes(memoryview(msg.data)) if not isinstance(msg.data, np.ndarray) else msg.data.tobytes()
    if data.startswith(JPEG_SOI):
        suffix = ".jpg"
    elif data.startswith(_PNG_MAGIC):
        suffix = ".png"
    else:
        raise MessageError(f"expected JPEG or PNG bytes in a CompressedImage, found format {msg.format!r} "
                           f"starting with {data[:4].hex()}")
    try:
        with Image.open(io.BytesIO(data)) as image:
            width, height = image.size
    except (OSError, ValueError, SyntaxError) as exc:
        raise MessageError(f"expected a readable {suffix[1:].upper()} image, could not read its header ({exc})") from exc
    return EncodedImage(data, suffix, (height, width))


def _field(msg, *names):
    for name in names:
        if hasattr(msg, name):
            return getattr(msg, name)
    raise MessageError(f"expected a field {' or '.join(names)}")


def camera_info_yaml(msg, name: str) -> tuple[str, tuple[int, int]]:
    """(left.yaml / right.yaml text in the ROS camera_info format, (height, width)) of a CameraInfo message."""
    width, height = int(msg.width), int(msg.height)
    fields = {"camera_matrix": (("k", "K"), (3, 3)), "distortion_coefficients": (("d", "D"), None),
              "rectification_matrix": (("r", "R"), (3, 3)), "projection_matrix": (("p", "P"), (3, 4))}
    out = [f"image_width: {width}", f"image_height: {height}", f"camera_name: {name}"]
    for key, (names, shape) in fields.items():
        values = [float(v) for v in np.asarray(_field(msg, *names), dtype=np.float64).ravel()]
        if shape is not None and len(values) != shape[0] * shape[1]:
            raise MessageError(f"expected {shape[0] * shape[1]} values in {names[0]}, found {len(values)}")
        if shape is not None and not any(values):
            raise MessageError(f"expected a calibrated camera, found an all-zero {names[0]} (uncalibrated camera_info)")
        rows, cols = shape if shape is not None else (1, len(values))
        if key == "distortion_coefficients":
            out.append(f"distortion_model: {msg.distortion_model or 'plumb_bob'}")
        out.append(f"{key}:\n  rows: {rows}\n  cols: {cols}\n  data: [{', '.join(repr(v) for v in values)}]")
    return "\n".join(out) + "\n", (height, width)


def wrench_xyz(msg) -> tuple[float, float, float]:
    """The force (N) of a ``geometry_msgs/WrenchStamped`` or ``Wrench``."""
    wrench = getattr(msg, "wrench", msg)
    force = wrench.force
    return float(force.x), float(force.y), float(force.z)


def pose_row(msg) -> tuple[float, float, float, float, float, float, float, str]:
    """(x, y, z m, qx, qy, qz, qw, frame_id) of a ``PoseStamped``, ``TransformStamped``, ``Pose`` or ``Transform``."""
    header = getattr(msg, "header", None)
    frame_id = str(header.frame_id) if header is not None else ""
    if hasattr(msg, "pose"):
        p, q = msg.pose.position, msg.pose.orientation
    elif hasattr(msg, "transform"):
        p, q = msg.transform.translation, msg.transform.rotation
    elif hasattr(msg, "position"):
        p, q = msg.position, msg.orientation
    else:
        p, q = msg.translation, msg.rotation
    return float(p.x), float(p.y), float(p.z), float(q.x), float(q.y), float(q.z), float(q.w), frame_id
