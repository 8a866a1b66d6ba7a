"""ROS 1 bags, ROS 2 bags (sqlite3 or MCAP) and bare MCAP files, read with ``rosbags`` (see the package docstring).

One pass over the chosen topics in the bag's time order: every image is written into the staging
folder as soon as it is read (so memory stays flat in the bag's length; only stamps are kept),
force and pose rows are written to their CSV files as they come, and the first CameraInfo of each
side is kept. At the end the left and right images are paired by header stamp and renamed to
their stems. Interrupted or failed, the staging folder is removed (common._staging).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from contact_viz.errors import SessionError
from contact_viz.io.calibration import read_calibration
from contact_viz.io.importers.common import (
    ImportResult,
    _place_calibration,
    _staging,
    _stem_width,
    _write_csv,
    _write_session_json,
)
from contact_viz.io.importers.dvrk import _ns_to_seconds_text
from contact_viz.io.importers.ros_messages import (
    MessageError,
    camera_info_yaml,
    compressed_image,
    image_message,
    pose_row,
    stamp_ns,
    wrench_xyz,
)
from contact_viz.io.kinematics import KINEMATICS_COLUMNS, KINEMATICS_FILE

__all__ = ["BagTopic", "DVRK_TOPICS", "import_bag", "list_topics", "list_lines"]

IMAGE_TYPES = ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage")
INFO_TYPES = ("sensor_msgs/msg/CameraInfo",)
WRENCH_TYPES = ("geometry_msgs/msg/WrenchStamped", "geometry_msgs/msg/Wrench")
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped",
              "geometry_msgs/msg/Pose", "geometry_msgs/msg/Transform")
ROLE_TYPES = {"left": IMAGE_TYPES, "right": IMAGE_TYPES, "left_info": INFO_TYPES, "right_info": INFO_TYPES,
              "force": WRENCH_TYPES, "pose": POSE_TYPES}
ROLE_OPTIONS = {"left": "--left", "right": "--right", "left_info": "--left-info", "right_info": "--right-info",
                "force": "--force", "pose": "--pose"}
DVRK_TOPICS = {  # preferred topic names of a dVRK recording, per role, in order
    "left": ("/jhu_daVinci/left/image_raw", "/jhu_daVinci/left/image_rect_color", "/jhu_daVinci/left/image_raw/compressed"),
    "right": ("/jhu_daVinci/right/image_raw", "/jhu_daVinci/right/image_rect_color",
              "/jhu_daVinci/right/image_raw/compressed"),
    "left_info": ("/jhu_daVinci/left/camera_info",),
    "right_info": ("/jhu_daVinci/right/camera_info",),
    "force": ("/force_sensor/measured_cf", "/atinetft/wrench", "/netft_data"),
    "pose": ("/PSM1/measured_cp", "/PSM2/measured_cp", "/dvrk/PSM1/position_cartesian_current"),
}
PAIR_TOLERANCE_PERIODS = 0.25  # default left/right pairing tolerance, as a fraction of the median left frame period
PROGRESS_EVERY = 16  # call progress() every this many messages


@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag, for --list and the topic choice."""

    topic: str
    msgtype: str  # ROS 2 style name, e.g. sensor_msgs/msg/Image (rosbags normalises ROS 1 types to it)
    count: int  # messages
    rate_hz: float  # count / the bag's duration (NaN for a bag of one instant)


@contextmanager
def _open_reader(src: Path):
    """An opened rosbags AnyReader for a .bag file, a ROS 2 bag folder or a bare .mcap/.db3 file (closed after)."""
    from rosbags.highlevel import AnyReader

    if not src.exists():
        raise SessionError(src, "missing: expected a ROS 1 .bag file, a ROS 2 bag folder (metadata.yaml + .db3 or "
                                ".mcap) or an .mcap file")
    if src.is_file() and src.suffix.lower() not in (".bag", ".mcap", ".db3"):
        raise SessionError(src, "expected a ROS 1 .bag file, a ROS 2 bag folder or an .mcap file (by its suffix)")
    try:
        reader = AnyReader([src])
        reader.open()
    except Exception as exc:  # rosbags raises many kinds for a damaged file; one line for all of them
        hint = "; a ROS 1 recording that was cut short needs `rosbag reindex` first" if src.suffix == ".bag" else ""
        raise SessionError(src, f"expected a readable ROS bag, could not open it ({type(exc).__name__}: "
                                f"{exc}){hint}") from exc
    try:
        yield reader
    finally:
        reader.close()


def _topics(reader) -> list[BagTopic]:
    duration_s = (reader.end_time - reader.start_time) / 1e9 if reader.connections else 0.0
    counts: dict[tuple[str, str], int] = {}
    for conn in reader.connections:
        counts[(conn.topic, conn.msgtype)] = counts.get((conn.topic, conn.msgtype), 0) + int(conn.msgcount)
    return [BagTopic(t, m, n, n / duration_s if duration_s > 0 else math.nan) for (t, m), n in sorted(counts.items())]


def list_topics(src: str | Path) -> list[BagTopic]:
    """The topics of bag ``src`` with their types, message counts and mean rates."""
    with _open_reader(Path(src).expanduser()) as reader:
        return _topics(reader)


def list_lines(src: str | Path) -> list[str]:
    """`contact-viz import bag SRC --list`: a table of the topics and the role the defaults give each."""
    src = Path(src).expanduser()
    with _open_reader(src) as reader:
        topics = _topics(reader)
        kind = "ROS 1 bag" if not reader.is2 else "ROS 2 bag"
        duration_s = (reader.end_time - reader.start_time) / 1e9 if topics else 0.0
    roles: dict[str, str] = {}
    for role in ROLE_TYPES:
        try:
            chosen = _choose(role, topics, None, roles, src)
        except SessionError:
            chosen = None
        if chosen is not None:
            roles[role] = chosen.topic
    by_topic: dict[str, list[str]] = {}
    for role, topic in roles.items():
        by_topic.setdefault(topic, []).append(role.replace("_", "-"))
    width = max([len("topic")] + [len(t.topic) for t in topics])
    type_width = max([len("type")] + [len(t.msgtype) for t in topics])
    out = [f"{src}: {kind}, {duration_s:.2f} s, {sum(t.count for t in topics)} messages, {len(topics)} topics",
           f"{'topic':<{width}}  {'type':<{type_width}}  {'count':>7}  {'rate Hz':>8}  default role"]
    for t in topics:
        rate = f"{t.rate_hz:8.2f}" if math.isfinite(t.rate_hz) else f"{'-':>8}"
        out.append(f"{t.topic:<{width}}  {t.msgtype:<{type_width}}  {t.count:>7}  {rate}  "
                   f"{', '.join(by_topic.get(t.topic, []))}".rstrip())
    return out


def _side_words(topic: str) -> set[str]:
    return {w for w in topic.lower().replace("-", "/").replace("_", "/").split("/") if w}


def _topic_error(src: Path, topic: str, expected: str) -> SessionError:
    """A SessionError naming the bag and the topic: "<bag>: topic <name>: <expected>"."""
    return SessionError(src, f"topic {topic}: {expected}")


def _choose(role: str, topics: list[BagTopic], given: str | None, chosen: dict[str, str],
            src: Path = Path("bag")) -> BagTopic | None:
    """The topic of ``role``: ``given`` (checked), else the dVRK default, else the only candidate; None if none.

    Candidates have one of the role's types; image and camera_info roles also need "left" / "right"
    as a word of the topic name, and a camera_info topic in the chosen image's namespace wins.
    Several candidates without a rule to pick one: SessionError asking for the option.
    """
    types = ROLE_TYPES[role]
    option = ROLE_OPTIONS[role]
    if given is not None:
        match = [t for t in topics if t.topic == given]
        if not match:
            raise _topic_error(src, given, f"{option}: expected a topic of the bag, found topics "
                                           f"{', '.join(t.topic for t in topics) or 'none'}")
        if match[0].msgtype not in types:
            raise _topic_error(src, given, f"{option}: expected a topic of type {' or '.join(types)}, found "
                                           f"{match[0].msgtype}")
        return match[0]
    candidates = [t for t in topics if t.msgtype in types and t.count > 0]
    side = role.split("_")[0] if role.split("_")[0] in ("left", "right") else None
    if side is not None:
        candidates = [t for t in candidates if side in _side_words(t.topic)]
    for name in DVRK_TOPICS[role]:
        for t in candidates:
            if t.topic == name:
                return t
    if side is not None and role.endswith("_info") and side in chosen:
        namespace = chosen[side].removesuffix("/compressed").rsplit("/", 1)[0]
        near = [t for t in candidates if t.topic == f"{namespace}/camera_info"]
        if near:
            return near[0]
    if role == "pose":
        measured = [t for t in candidates if t.topic.endswith("measured_cp") and "/local/" not in t.topic]
        if len(measured) == 1:
            return measured[0]
    if len(candidates) > 1:
        raise SessionError(src, f"expected one {role.replace('_', ' ')} topic, found several: "
                                f"{', '.join(t.topic for t in candidates)}; choose with {option}")
    return candidates[0] if candidates else None


def _pair(left_ns: np.ndarray, right_ns: np.ndarray, tolerance_ns: float) -> np.ndarray:
    """For each left stamp the index of its right partner (-1 if none): closest pairs first, each used once."""
    partner = np.full(len(left_ns), -1, dtype=np.int64)
    if len(right_ns) == 0 or len(left_ns) == 0:
        return partner
    order = np.argsort(right_ns, kind="stable")
    sorted_right = right_ns[order]
    after = np.searchsorted(sorted_right, left_ns)
    pairs = []
    for i, a in enumerate(after):
        for j in (a - 1, a):  # the nearest right stamps on either side
            if 0 <= j < len(sorted_right):
                gap = abs(int(sorted_right[j]) - int(left_ns[i]))
                if gap <= tolerance_ns:
                    pairs.append((gap, i, int(order[j])))
    used = set()
    for gap, i, j in sorted(pairs):
        if partner[i] < 0 and j not in used:
            partner[i] = j
            used.add(j)
    return partner


def _stamps_text(stamps_ns: Sequence[int], limit: int = 5) -> str:
    shown = ", ".join(_ns_to_seconds_text(int(s)) for s in list(stamps_ns)[:limit])
    return shown + (" ..." if len(stamps_ns) > limit else "")


def import_bag(
    src: str | Path,
    out: str | Path,
    *,
    left: str | None = None,
    right: str | None = None,
    left_info: str | None = None,
    right_info: str | None = None,
    force: str | None = None,
    pose: str | None = None,
    pair_tolerance_s: float | None = None,
    calibration: Sequence[str | Path] = (),
    progress: Callable[[int, int], None] | None = None,
) -> ImportResult:
    """Import a ROS 1 bag, ROS 2 bag folder or .mcap file ``src`` as a new session ``out``.

    Topics: the given names, else the dVRK defaults (DVRK_TOPICS), else the only topic of the
    right type (and side). ``pose="none"`` / ``force="none"`` skip them. ``pair_tolerance_s``:
    largest left/right stamp difference of a stereo pair (default: PAIR_TOLERANCE_PERIODS of the
    median left frame period). ``calibration``: files that replace the camera_info topics.
    ``progress(done, total)`` counts messages. Raises SessionError (one line naming the topic or
    file) or ValueError (bad arguments).
    """
    from contact_viz.io.session import missing_inputs

    src = Path(src).expanduser()
    if pair_tolerance_s is not None and not (math.isfinite(pair_tolerance_s) and pair_tolerance_s >= 0):
        raise ValueError(f"--pair-tolerance-ms must be a finite number >= 0, got {pair_tolerance_s * 1000!r}")
    notes: list[str] = []
    out_path = Path(out)
    with _open_reader(src) as reader:
        topics = _topics(reader)
        chosen: dict[str, str] = {}
        for role in ("left", "right", "left_info", "right_info", "force", "pose"):
            given = {"left": left, "right": right, "left_info": left_info, "right_info": right_info,
                     "force": force, "pose": pose}[role]
            if given is not None and given.lower() == "none" and role in ("force", "pose", "right"):
                continue
            if role.endswith("_info") and calibration:
                continue
            topic = _choose(role, topics, given, chosen, src)
            if topic is not None:
                chosen[role] = topic.topic
        images = [t for t in topics if t.msgtype in IMAGE_TYPES]
        if "left" not in chosen:
            raise SessionError(src, "expected a left image topic (sensor_msgs/Image or CompressedImage with 'left' in "
                               f"its name; choose with --left), found image topics "
                               f"{', '.join(t.topic for t in images) or 'none'}")
        for role in ("left_info", "right_info"):
            if not calibration and role not in chosen:
                raise SessionError(src, f"expected a sensor_msgs/CameraInfo topic for the {role.split('_')[0]} camera "
                                        f"(e.g. {DVRK_TOPICS[role][0]}; choose with {ROLE_OPTIONS[role]}) or "
                                        "--calibration FILE, found none")
        if "right" not in chosen:
            notes.append("no right image topic: no right/ images (no SGBM depth)")
        if "force" not in chosen:
            notes.append("no force topic (geometry_msgs/WrenchStamped or Wrench): no force.csv, no force labels")
        roles_of: dict[str, list[str]] = {}
        for role, topic in chosen.items():
            roles_of.setdefault(topic, []).append(role)
        connections = [c for c in reader.connections if c.topic in roles_of]
        total = sum(int(c.msgcount) for c in connections)
        with _staging(src, out_path) as tmp:
            state = _Pass(src, tmp, chosen)
            done = 0
            try:
                for conn, log_ns, raw in _messages(reader, connections, src):
                    try:
                        msg = reader.deserialize(raw, conn.msgtype)
                    except Exception as exc:  # a damaged message: rosbags' many error kinds as one line
                        raise _topic_error(src, conn.topic, f"expected a readable {conn.msgtype} message at "
                                           f"{_ns_to_seconds_text(log_ns)} s ({type(exc).__name__}: {exc})") from exc
                    for role in roles_of[conn.topic]:
                        state.take(role, conn.topic, msg, log_ns)
                    done += 1
                    if progress is not None and (done % PROGRESS_EVERY == 0 or done == total):
                        progress(done, total)
            finally:
                state.close()
            frames, force_rows, pose_rows, tolerance_ns = state.finish(src, calibration, pair_tolerance_s, notes)
            _write_session_json(tmp / "session.json", out_path.name, "bag", src.resolve(), frames,
                                {"topics": chosen, "pair_tolerance_ms": tolerance_ns / 1e6})
    out_path = out_path.expanduser().resolve()
    result = ImportResult("bag", src.resolve(), out_path, len(frames), {"written": len(frames)}, force_rows,
                          notes, missing_inputs(out_path))
    if pose_rows:
        result.notes.append(f"{KINEMATICS_FILE}: {pose_rows} poses from {chosen['pose']}")
    return result


def _messages(reader, connections, src: Path):
    """reader.messages(connections) with rosbags' read errors (a truncated or damaged bag) as one SessionError."""
    iterator = reader.messages(connections=connections)
    while True:
        try:
            item = next(iterator)
        except StopIteration:
            return
        except Exception as exc:  # rosbags raises many kinds for a truncated file
            raise SessionError(src, f"expected a complete ROS bag, reading stopped ({type(exc).__name__}: {exc}); "
                                    "truncated or damaged?") from exc
        yield item


class _Pass:
    """What one pass over the messages writes and keeps (stamps only, never image data)."""

    def __init__(self, src: Path, tmp: Path, chosen: dict[str, str]) -> None:
        self.src = src
        self.tmp = tmp
        self.chosen = chosen
        self.incoming = tmp / ".incoming"
        self.incoming.mkdir()
        self.stamps: dict[str, list[int]] = {"left": [], "right": []}
        self.files: dict[str, list[Path]] = {"left": [], "right": []}
        self.shape: tuple[int, int] | None = None
        self.shape_from = ""
        self.info: dict[str, tuple[str, tuple[int, int]]] = {}
        self.force_rows = self.pose_rows = 0
        self._force = self._pose = None
        if "force" in chosen:
            self._force_file = open(tmp / "force.csv", "w", newline="", encoding="utf-8")
            self._force = csv.writer(self._force_file)
            self._force.writerow(("timestamp", "fx", "fy", "fz"))
        if "pose" in chosen:
            self._pose_file = open(tmp / KINEMATICS_FILE, "w", newline="", encoding="utf-8")
            self._pose = csv.writer(self._pose_file)
            self._pose.writerow(KINEMATICS_COLUMNS)

    def take(self, role: str, topic: str, msg, log_ns: int) -> None:
        try:
            if role in ("left", "right"):
                self._image(role, topic, msg, log_ns)
            elif role.endswith("_info"):
                if role not in self.info:
                    self.info[role] = camera_info_yaml(msg, topic)
            elif role == "force":
                fx, fy, fz = wrench_xyz(msg)
                self._force.writerow((_ns_to_seconds_text(stamp_ns(msg, log_ns)), repr(fx), repr(fy), repr(fz)))
                self.force_rows += 1
            elif role == "pose":
                *values, frame_id = pose_row(msg)
                self._pose.writerow((_ns_to_seconds_text(stamp_ns(msg, log_ns)), *map(repr, values), frame_id))
                self.pose_rows += 1
        except MessageError as exc:
            raise _topic_error(self.src, topic, f"message at {_ns_to_seconds_text(log_ns)} s: {exc}") from None

    def _image(self, side: str, topic: str, msg, log_ns: int) -> None:
        image = compressed_image(msg) if hasattr(msg, "format") else image_message(msg)
        if self.shape is None:
            self.shape, self.shape_from = image.shape, topic
        elif image.shape != self.shape:
            raise _topic_error(self.src, topic, f"message at {_ns_to_seconds_text(log_ns)} s: expected a "
                               f"{self.shape[1]}x{self.shape[0]} image like the first of {self.shape_from}, found "
                               f"{image.shape[1]}x{image.shape[0]}")
        path = self.incoming / f"{side}_{len(self.files[side]):09d}{image.suffix}"
        path.write_bytes(image.data)
        self.files[side].append(path)
        self.stamps[side].append(stamp_ns(msg, log_ns))

    def close(self) -> None:
        for name in ("_force_file", "_pose_file"):
            handle = getattr(self, name, None)
            if handle is not None:
                handle.close()

    def finish(self, src: Path, calibration, pair_tolerance_s: float | None, notes: list[str]):
        """Pair, rename, write frames.csv and the calibration.

        Returns (frame times s, force rows, pose rows, pairing tolerance ns).
        """
        tmp = self.tmp
        left_ns = np.asarray(self.stamps["left"], dtype=np.int64)
        right_ns = np.asarray(self.stamps["right"], dtype=np.int64)
        if left_ns.size == 0:
            raise _topic_error(src, self.chosen["left"], "expected left images, found no messages on the topic")
        order = np.argsort(left_ns, kind="stable")
        left_ns = left_ns[order]
        if pair_tolerance_s is None:
            period_ns = float(np.median(np.diff(left_ns))) if left_ns.size > 1 else 0.0
            tolerance_ns = PAIR_TOLERANCE_PERIODS * period_ns
        else:
            tolerance_ns = pair_tolerance_s * 1e9
        partner = _pair(left_ns, right_ns, tolerance_ns)
        width = _stem_width(len(left_ns))
        (tmp / "left").mkdir()
        if right_ns.size:
            (tmp / "right").mkdir()
        rows = []
        for i, k in enumerate(order):
            stem = f"{i:0{width}d}"
            left_file = self.files["left"][k]
            left_file.rename(tmp / "left" / f"{stem}{left_file.suffix}")
            if partner[i] >= 0:
                right_file = self.files["right"][partner[i]]
                right_file.rename(tmp / "right" / f"{stem}{right_file.suffix}")
            rows.append((stem, _ns_to_seconds_text(int(left_ns[i]))))
        _write_csv(tmp / "frames.csv", ("frame", "timestamp"), rows)
        tol_ms = tolerance_ns / 1e6
        lone_left = left_ns[partner < 0]
        if right_ns.size and lone_left.size:
            notes.append(f"{lone_left.size} left frame(s) have no right image within {tol_ms:.2f} ms (kept without "
                         f"one: no SGBM depth for them), at {_stamps_text(lone_left)} s")
        used = np.zeros(right_ns.size, dtype=bool)
        used[partner[partner >= 0]] = True
        if (~used).any():
            notes.append(f"{int((~used).sum())} right image(s) have no left image within {tol_ms:.2f} ms and were "
                         f"not imported, at {_stamps_text(np.sort(right_ns[~used]))} s")
        for path in self.incoming.iterdir():
            path.unlink()
        self.incoming.rmdir()
        if self.force_rows:
            notes.append(f"force from {self.chosen['force']} ({self.force_rows} samples at its own rate)")
        elif "force" in self.chosen:
            (tmp / "force.csv").unlink()
            notes.append(f"force topic {self.chosen['force']} has no messages: no force.csv")
        if "pose" in self.chosen and not self.pose_rows:
            (tmp / KINEMATICS_FILE).unlink()
        if not _place_calibration(calibration, tmp, copy=True):
            for role, name in (("left_info", "left.yaml"), ("right_info", "right.yaml")):
                if role not in self.info:
                    raise _topic_error(src, self.chosen[role], "expected a sensor_msgs/CameraInfo message, found "
                                                               "none on the topic")
                text, shape = self.info[role]
                if shape != self.shape:
                    raise _topic_error(src, self.chosen[role], f"expected the calibration of the {self.shape[1]}x"
                                       f"{self.shape[0]} images, found camera_info for {shape[1]}x{shape[0]}")
                (tmp / name).write_text(text, encoding="utf-8")
            notes.append(f"calibration from {self.chosen['left_info']} and {self.chosen['right_info']} "
                         "written as left.yaml + right.yaml")
        read_calibration(tmp, self.shape)  # fail now, with the file named, if it is wrong
        return [int(s) / 1e9 for s in left_ns], self.force_rows, self.pose_rows, tolerance_ns
