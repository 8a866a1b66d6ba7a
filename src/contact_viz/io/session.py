"""Read a recorded session directory: calibration, frame order, force, labels and per-frame layers.

The session directory format (the contract)::

    SESSION/
      session.json        optional: {"name", "phantom", "task", "fps"} (fps default 30)
      K.txt               line 1 = 9 numbers, row-major 3x3 K (px); line 2 = stereo baseline (m)
                          (or ROS left.yaml + right.yaml, or an OpenCV stereo.yaml: see calibration.py)
      left/<stem>.png|jpg|jpeg    left frames (the frame list); rectified, unless the calibration
                                  says otherwise (then left/right/masks/depth are rectified on load)
      right/<stem>.png|jpg|jpeg   right frames (optional; needed for SGBM depth)
      masks/<stem>.png    tool mask: palettized (index = object id) or 8-bit 0/255 (or RGB, nonzero = tool)
      depth/<stem>.npy    float32 metres, or depth/<stem>.png uint16 millimetres; 0, NaN, inf = invalid
      disparity/<stem>.npy  float32 px (FoundationStereo's raw output), used when depth/ is absent
      force.csv           optional: `frame` (stem) or `timestamp` (s) column, plus fx, fy, fz (N)
      frames.csv          optional: frame,timestamp (s); needed when force.csv is indexed by timestamp
      labels.csv          optional manual labels: frame,contact (0/1); they replace the force labels.
                          With a tool column (frame,tool,contact): per instrument (object id); a
                          frame's label is then 1 when any (selected) instrument it names is in contact
      kinematics.csv      optional robot tool pose: timestamp,x_m,y_m,z_m,qx,qy,qz,qw,frame_id (io/kinematics.py)
      tool_tips.csv       optional tool-tip keypoints: frame,x_px,y_px (the RGB baseline's crop centres)

Depth comes from one source per session, chosen in this order and logged (``Session.depth_note``):
``depth/``; else ``disparity/`` (depth = fx * baseline / (disparity + offset)); else OpenCV
semi-global matching of the left/right pair (``stereo.py``), computed lazily per frame and cached
outside the session directory.

``open_session`` validates everything that is session-wide up front and raises one
:class:`SessionError` naming the file and what was expected. Per-frame problems never raise:
``Session.iter_frames`` yields a :class:`BadFrame` for them and carries on. Nothing here ever
writes into the session directory (the SGBM cache lives in the cache folder).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Iterator, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from contact_viz.io.calibration import Calibration, Rectification, StereoCalibration, read_calibration, read_only
from contact_viz.errors import SessionError, SessionFormatError, SessionWarning
from contact_viz.io.prefetch import prefetched
from contact_viz.params import LabelParams
from contact_viz.io.decoders import (
    _check_image_shape,
    read_image_size,
    read_depth_m,
    read_depth_rows_m,
    read_disparity_px,
    read_rgb,
    read_mask_ids,
    read_tool_mask,
)
from contact_viz.io.session_files import (
    _find_masks,
    _list_stems,
    _read_force_csv,
    _read_frames_csv,
    _read_labels_csv,
    _read_session_json,
    find_depth_source,
    force_labels,
    missing_inputs,
    natural_key,
    tool_label_arrays,
)
from contact_viz.geometry.stereo import DEPTH_METHODS, SGBMParams, disparity_to_depth
from contact_viz.geometry.stereo_region import fine_region
from contact_viz.io.depth_cache import DisparityCache
from contact_viz.io.kinematics import KINEMATICS_FILE, TOOL_TIPS_FILE, Kinematics, read_kinematics, read_tool_tips

__all__ = [
    "LAYERS",
    "BadFrame",
    "Calibration",
    "DEPTH_SOURCES",
    "Frame",
    "Session",
    "SessionWarning",
    "missing_inputs",
    "natural_key",
    "open_session",
    "read_depth_m",
    "read_disparity_px",
    "read_rgb",
    "read_mask_ids",
    "read_tool_mask",
]

log = logging.getLogger(__name__)

LAYERS = frozenset({"mask", "depth", "left", "right"})  # names of the per-frame layers iter_frames can decode
DEFAULT_FPS = 30.0  # frame rate used when session.json gives none, frames/s
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")  # accepted left/right image file types, in lookup preference
JPEG_SUFFIXES = (".jpg", ".jpeg")  # of those, the JPEG ones (decodable at reduced size)
DEPTH_SOURCES = ("depth", "disparity", "sgbm")  # where a session's depth can come from, in preference order



# --------------------------------------------------------------------------------------------
# Data types
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Frame:
    """One decoded frame. Layers that were not requested are None."""

    index: int  # position in the session's frame order, 0-based
    stem: str  # file stem shared by left/, right/, masks/, depth/
    timestamp_s: float  # frame time, s
    tool_mask: np.ndarray | None  # (H, W) bool, True = tool (the instruments selected; all by default)
    depth_m: np.ndarray | None  # (H, W) float32, m, read-only; invalid where not a finite number > 0
    left_rgb: np.ndarray | None  # (H, W, 3) uint8 RGB
    right_rgb: np.ndarray | None  # (H, W, 3) uint8 RGB; None also when the frame has no right image
    # (H, W) bool: where depth_m is SGBM's fine match (the tools and their surroundings); elsewhere it is the
    # coarse pass's. None: all of depth_m is of one kind (a depth or disparity file, or SGBM without a mask)
    depth_fine: np.ndarray | None = None
    # (H, W) uint16 object id of every instrument in the mask, 0 = background (binary masks: id 1); with the
    # mask layer. Instruments not selected (object_ids) are here too: they are never tissue
    tool_ids: np.ndarray | None = None


@dataclass(frozen=True)
class BadFrame:
    """A frame whose requested layers could not be read; ``error`` names the file and the expectation."""

    index: int  # position in the session's frame order, 0-based
    stem: str  # file stem
    timestamp_s: float  # frame time, s
    error: SessionError  # what went wrong, naming the file

    @property
    def reason(self) -> str:
        """The error message: "<path>: <what was expected>"."""
        return str(self.error)


# Session
# --------------------------------------------------------------------------------------------


class Session:
    """An opened session: metadata, calibration, per-frame times/force/labels, lazy frame decoding.

    Attributes (arrays are read-only, n = number of frames):
        root: session directory (absolute). name / phantom / task: from session.json.
        fps: frames/s. calibration: rectified left K (px) and baseline (m).
        stereo: the calibration file(s) read and, when the images are raw, the rectification.
        rectification: maps applied on load to left/right/masks/depth (None if already rectified).
        stems: frame stems in numeric order. image_size: (height, width) px of the left images.
        timestamps_s: (n,) float64, s. force_xyz_n: (n, 3) float64, N (NaN = no sample).
        force_n: (n,) float64 magnitude, N (NaN = unknown). labels: (n,) int8 1/0/-1 (unknown).
        label_source: (n,) str "manual" / "force" / "none". has_right: right/ holds images.
        tool_labels: labels.csv's per-instrument labels (frame,tool,contact): object id -> (n,) int8
        1/0/-1 (no row), for the selected instruments; None when labels.csv has no tool column.
        depth_source: "depth", "disparity" or "sgbm" (see DEPTH_SOURCES). depth_note: one line
        saying where depth comes from. depth_config: what the depth depends on, for cache keys.
        depth_cache_dir: where SGBM disparities are cached (None for other sources).
        kinematics: kinematics.csv's pose samples (io.kinematics.Kinematics) or None.
        tool_tips_xy: (n, 2) float64 px from tool_tips.csv, NaN where it has no row; None without it.
    """

    def __init__(
        self,
        *,
        root: Path,
        name: str,
        phantom: str | None,
        task: str | None,
        fps: float,
        calibration: Calibration,
        stems: list[str],
        image_size: tuple[int, int],
        timestamps_s: np.ndarray,
        force_xyz_n: np.ndarray,
        force_n: np.ndarray,
        labels: np.ndarray,
        label_source: np.ndarray,
        tool_labels: dict[int, np.ndarray] | None = None,
        left_files: dict[str, Path],
        right_files: dict[str, Path],
        mask_files: dict[str, Path],
        depth_files: dict[str, Path],
        object_ids: tuple[int, ...] | None,
        depth_source: str = "depth",
        depth_note: str = "depth from depth/",
        stereo: StereoCalibration | None = None,
        sgbm_cache: DisparityCache | None = None,
        kinematics: Kinematics | None = None,
        tool_tips_xy: np.ndarray | None = None,
        label_params: LabelParams = LabelParams(),
    ) -> None:
        if depth_source not in DEPTH_SOURCES:
            raise ValueError(f"depth_source must be one of {DEPTH_SOURCES}, got {depth_source!r}")
        if depth_source == "sgbm" and sgbm_cache is None:
            raise ValueError("depth_source 'sgbm' needs an sgbm_cache")
        self.root = root
        self.name = name
        self.phantom = phantom
        self.task = task
        self.fps = fps
        self.calibration = calibration
        self.stereo = stereo
        self.rectification: Rectification | None = stereo.rectification if stereo is not None else None
        self.stems = stems
        self.image_size = image_size
        self.timestamps_s = read_only(timestamps_s)
        self.force_xyz_n = read_only(force_xyz_n)
        self.force_n = read_only(force_n)
        self.labels = read_only(labels)
        self.label_source = read_only(label_source)
        self.label_params = label_params  # what the force labels were made with
        # labels.csv's per-instrument labels (its tool column): object id -> (n,) int8, -1 = no row; None without
        self.tool_labels = None if tool_labels is None else {k: read_only(v) for k, v in tool_labels.items()}
        self.has_right = bool(right_files)
        self.object_ids = object_ids  # the instruments selected (None = every object id in the masks)
        self.depth_source = depth_source
        self.depth_note = depth_note
        self._left_files = left_files
        self._right_files = right_files
        self._mask_files = mask_files
        self._depth_files = depth_files  # stem -> depth/ or disparity/ file, by depth_source
        self._sgbm = sgbm_cache if depth_source == "sgbm" else None
        self.depth_cache_dir = self._sgbm.directory if self._sgbm is not None else None
        self.depth_config = {"source": depth_source}
        self.kinematics = kinematics  # kinematics.csv (robot tool pose samples) or None
        self.tool_tips_xy = tool_tips_xy  # (n, 2) px from tool_tips.csv, NaN where absent; None without the file
        self._grow: dict[str, np.ndarray] = {}  # extend(): the arrays' buffers, with room to grow
        self._forgotten = 0  # forget_files(): frames before this have no file names any more
        if self._sgbm is not None:
            self.depth_config["sgbm"] = asdict(self._sgbm.params)

    def __len__(self) -> int:
        return len(self.stems)

    @property
    def sgbm_cache(self):
        """The cache of the SGBM depth (:class:`~contact_viz.io.depth_cache.DisparityCache`), None unless the
        depth comes from SGBM."""
        return self._sgbm

    def __repr__(self) -> str:
        height, width = self.image_size
        return f"Session({self.name!r}, {len(self)} frames, {width}x{height} px, root={str(self.root)!r})"

    # ---- per-frame decoding ----

    def extend(self, stems: Sequence[str], files: dict[str, dict[str, Path]], timestamps_s: Sequence[float]) -> None:
        """Append frames after the last one (a session being recorded, contact_viz.io.live): their
        ``stems``, ``files`` (layer "left", "right", "mask", "depth" -> stem -> path) and times (s).
        Their force and labels are unknown (NaN, -1). Arrays grow by doubling: appending is O(1)."""
        if not stems:
            return
        n, k = len(self.stems), len(stems)
        for name, fill in (("timestamps_s", np.nan), ("force_xyz_n", np.nan), ("force_n", np.nan),
                           ("labels", -1), ("label_source", "none")):
            current = getattr(self, name)
            buffer = self._grow.get(name)
            if buffer is None or len(buffer) < n + k:
                buffer = np.empty((max(2 * (n + k), 64),) + current.shape[1:], dtype=current.dtype)
                buffer[:n] = current
                self._grow[name] = buffer
            buffer[n:n + k] = fill
            if name == "timestamps_s":
                buffer[n:n + k] = timestamps_s
            view = buffer[:n + k].view()  # read-only to readers, as the arrays open_session makes (no copy)
            view.flags.writeable = False
            setattr(self, name, view)
        self.stems.extend(stems)
        for layer, target in (("left", self._left_files), ("right", self._right_files), ("mask", self._mask_files),
                              ("depth", self._depth_files)):
            target.update(files.get(layer, {}))

    def forget_files(self, before: int) -> None:
        """Drop the file names of frames ``< before`` (a followed session: they are not read again, and
        an hour of them would be tens of MB); their stems, times and force stay."""
        for stem in self.stems[self._forgotten:max(before, self._forgotten)]:
            for files in (self._left_files, self._right_files, self._mask_files, self._depth_files):
                files.pop(stem, None)
        self._forgotten = max(before, self._forgotten)

    def _check_shape(self, path: Path, shape: tuple[int, ...], what: str) -> None:
        """SessionError unless ``shape`` (an array's, channels ignored) is the left images' (H, W)."""
        _check_image_shape(path, shape, self.image_size, what)

    def _layer_path(self, files: dict[str, Path], stem: str, expected: Path, what: str) -> Path:
        path = files.get(stem)
        if path is None:
            raise SessionError(expected, f"missing: expected {what} for frame {stem!r}")
        return path

    def image_path(self, side: str, index: int) -> Path | None:
        """The ``side`` ("left" or "right") image file of frame ``index``, or None when there is none."""
        if side not in ("left", "right"):
            raise ValueError(f"side must be 'left' or 'right', got {side!r}")
        files = self._left_files if side == "left" else self._right_files
        return files.get(self.stems[index])

    def layer_file(self, layer: str, stem: str) -> Path | None:
        """The file frame ``stem``'s "mask" or "depth" (depth/ or disparity/) is read from; None
        when there is none (a missing file, SGBM depth)."""
        files = {"mask": self._mask_files, "depth": self._depth_files}.get(layer)
        if files is None:
            raise ValueError(f"layer must be 'mask' or 'depth', got {layer!r}")
        return files.get(stem)

    def _image(self, side: str, stem: str, decoded: dict[str, np.ndarray]) -> np.ndarray:
        """Frame ``stem``'s ``side`` image, (H, W, 3) uint8 RGB, rectified if needed; memoized in ``decoded``."""
        if side not in decoded:
            files = self._left_files if side == "left" else self._right_files
            expected = self.root / side / f"{stem}.png"
            path = self._layer_path(files, stem, expected, f"a {side} image")
            rgb = read_rgb(path)
            self._check_shape(path, rgb.shape, f"{side} image")
            if self.rectification is not None:
                rgb = self.rectification.apply(side, rgb)
            decoded[side] = rgb
        return decoded[side]

    def _mask_ids(self, stem: str, decoded: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Frame ``stem``'s object ids (H, W) uint16 (every instrument), rectified if needed; memoized in ``decoded``."""
        if decoded is not None and "mask_ids" in decoded:
            return decoded["mask_ids"]
        expected = self.root / "masks" / f"{stem}.png"
        path = self._layer_path(self._mask_files, stem, expected, "a tool mask PNG")
        ids = read_mask_ids(path, self.object_ids)
        self._check_shape(path, ids.shape, "tool mask")
        if self.rectification is not None:
            ids = self.rectification.apply("left", ids, nearest=True)
        if decoded is not None:
            decoded["mask_ids"] = ids
        return ids

    def _mask(self, stem: str, decoded: dict[str, np.ndarray] | None = None) -> np.ndarray:
        """Frame ``stem``'s tool mask (H, W) bool: the selected instruments; memoized in ``decoded``."""
        if decoded is not None and "mask" in decoded:
            return decoded["mask"]
        ids = self._mask_ids(stem, decoded)
        tool_mask = np.isin(ids, self.object_ids) if self.object_ids else ids != 0
        if decoded is not None:
            decoded["mask"] = tool_mask
        return tool_mask

    def _depth(self, stem: str, decoded: dict[str, np.ndarray]) -> tuple[np.ndarray, str]:
        """(depth (H, W) float32 m NaN-invalid, origin "file" / "cached" / "computed") of frame ``stem``."""
        cal = self.calibration
        if self.depth_source == "depth":
            path = self._layer_path(
                self._depth_files, stem, self.root / "depth" / f"{stem}.npy",
                "a depth map (.npy float32 m or .png uint16 mm)",
            )
            depth_m = read_depth_m(path)
            self._check_shape(path, depth_m.shape, "depth map")
            if self.rectification is not None:
                depth_m = self.rectification.apply("left", depth_m, nearest=True)
            return depth_m, "file"
        if self.depth_source == "disparity":
            path = self._layer_path(
                self._depth_files, stem, self.root / "disparity" / f"{stem}.npy", "a disparity map (.npy float32 px)"
            )
            disparity = read_disparity_px(path)
            self._check_shape(path, disparity.shape, "disparity map")
            return disparity_to_depth(disparity, cal.fx, cal.baseline_m, cal.disparity_offset_px), "file"
        left_path = self._left_files[stem]
        right_path = self._layer_path(
            self._right_files, stem, self.root / "right" / f"{stem}.png",
            "a right image (SGBM depth needs the stereo pair)",
        )
        mask_path = self._mask_files.get(stem)  # known tool mask: matched without foreground fattening
        disparity, cached = self._sgbm.disparity(
            stem, left_path, right_path,
            lambda: (self._image("left", stem, decoded), self._image("right", stem, decoded)),
            mask_path=mask_path, load_mask=lambda: self._mask_ids(stem, decoded) != 0,
        )  # every instrument is taken out of the pair, selected or not
        params = self._sgbm.params
        if mask_path is not None and params.tool_mask_aware and params.region:
            decoded["depth_fine"] = fine_region(self._mask_ids(stem, decoded) != 0, params.region_px)
        return disparity_to_depth(disparity, cal.fx, cal.baseline_m, cal.disparity_offset_px), (
            "cached" if cached else "computed"
        )

    def check_format(self) -> None:
        """Refuse up front a mask or depth folder whose files all hold the wrong kind of data.

        The first frame's mask and depth (or disparity) file are decoded; a shape, dtype,
        channel or bit-depth fault there (:class:`SessionFormatError`) that the last frame's
        file shares is a session error, raised naming the first file, so that no command
        skips every frame one by one and writes a table of bad frames. A fault of the first
        frame alone, or one that is not about the format (missing, unreadable, truncated),
        stays a per-frame problem: that frame is skipped with a warning. SGBM depth is not
        decoded here (it is computed from the images, whose size is checked per frame).
        """
        probes = sorted({0, len(self) - 1})
        layers = []
        if self._mask_files:
            layers.append(lambda stem: self._mask(stem))
        if self.depth_source != "sgbm":
            layers.append(lambda stem: self._depth(stem, {}))
        for decode in layers:
            found = []
            for index in probes:
                try:
                    decode(self.stems[index])
                except SessionFormatError as error:
                    found.append(error)
                except SessionError:
                    break
                else:
                    break
            if len(found) == len(probes):
                raise found[0]

    def load_depth(self, index: int, with_origin: bool = False):
        """Frame ``index``'s depth (H, W) float32 m (NaN invalid), or a BadFrame.

        With ``with_origin`` a (depth, origin) pair, origin = "file" (depth/ or disparity/),
        "cached" or "computed" (SGBM). Used by `contact-viz depth` to fill the cache.
        """
        if not 0 <= index < len(self):
            raise IndexError(f"frame index {index} out of range for a session of {len(self)} frames")
        stem = self.stems[index]
        try:
            depth_m, origin = self._depth(stem, {})
        except SessionError as error:
            return BadFrame(index=index, stem=stem, timestamp_s=float(self.timestamps_s[index]), error=error)
        return (depth_m, origin) if with_origin else depth_m

    def load_depth_rows(self, index: int, row0: int, row1: int) -> np.ndarray | BadFrame:
        """Rows ``row0`` to ``row1 - 1`` of frame ``index``'s depth, (row1 - row0, W) float32 m,
        read-only, values as stored (see read_depth_m); or a BadFrame.

        From depth/*.npy files stored rectified, only those rows are read (`contact-viz extract`
        needs the depth only around the tool); from any other source the whole map is decoded
        and cut. The file's shape and dtype are checked either way.
        """
        if not 0 <= index < len(self):
            raise IndexError(f"frame index {index} out of range for a session of {len(self)} frames")
        height = self.image_size[0]
        if not 0 <= row0 <= row1 <= height:
            raise ValueError(f"rows {row0}..{row1 - 1} out of range for images of {height} rows")
        stem = self.stems[index]
        try:
            path = self._depth_files.get(stem) if self.depth_source == "depth" else None
            if path is not None and path.suffix.lower() == ".npy" and self.rectification is None:
                depth_m = read_depth_rows_m(path, row0, row1, self.image_size)
            else:
                depth_m, _ = self._depth(stem, {})
                depth_m = depth_m[row0:row1]
        except SessionError as error:
            return BadFrame(index=index, stem=stem, timestamp_s=float(self.timestamps_s[index]), error=error)
        depth_m.flags.writeable = False
        return depth_m

    def load_frame(self, index: int, layers: Sequence[str] = ("mask", "depth")) -> Frame | BadFrame:
        """Decode the requested ``layers`` of frame ``index`` (synchronously); a BadFrame on any problem."""
        wanted = _check_layers(layers)
        if not 0 <= index < len(self):
            raise IndexError(f"frame index {index} out of range for a session of {len(self)} frames")
        return self._load(index, wanted)

    def _load(self, index: int, layers: frozenset[str]) -> Frame | BadFrame:
        stem = self.stems[index]
        timestamp_s = float(self.timestamps_s[index])
        tool_mask = depth_m = left_rgb = right_rgb = None
        decoded: dict[str, np.ndarray] = {}  # rectified images decoded for this frame, shared by the layers
        try:
            if "mask" in layers:
                tool_mask = self._mask(stem, decoded)
            if "depth" in layers:
                depth_m, _ = self._depth(stem, decoded)
                depth_m.flags.writeable = False  # whatever its source, a frame's depth is read-only
            if "left" in layers:
                left_rgb = self._image("left", stem, decoded)
            if "right" in layers and stem in self._right_files:
                right_rgb = self._image("right", stem, decoded)
        except SessionError as error:
            return BadFrame(index=index, stem=stem, timestamp_s=timestamp_s, error=error)
        return Frame(
            index=index,
            stem=stem,
            timestamp_s=timestamp_s,
            tool_mask=tool_mask,
            depth_m=depth_m,
            left_rgb=left_rgb,
            right_rgb=right_rgb,
            depth_fine=decoded.get("depth_fine"),
            tool_ids=decoded.get("mask_ids"),
        )

    def iter_frames(
        self,
        layers: Sequence[str] = ("mask", "depth"),
        indices: Sequence[int] | None = None,
        prefetch: int = 4,
        workers: int = 1,
    ) -> Iterator[Frame | BadFrame]:
        """Yield the frames ``indices`` (default: all) in order, decoding only ``layers``.

        Decoding runs in ``workers`` background threads, at most ``prefetch`` frames ahead of
        the consumer, so it overlaps the caller's compute. Per-frame problems are yielded as
        BadFrame. Closing the generator early (break) cancels pending work and joins the threads.
        Arguments are checked now (ValueError / IndexError), not at the first ``next``.
        """
        wanted = _check_layers(layers)
        order = list(range(len(self))) if indices is None else [int(i) for i in indices]
        bad = [i for i in order if not 0 <= i < len(self)]
        if bad:
            raise IndexError(f"frame indices {bad[:5]} out of range for a session of {len(self)} frames")
        return prefetched(functools.partial(self._load, layers=wanted), order, prefetch,
                          workers=min(workers, prefetch), thread_name="contact-viz-decode")


def _check_layers(layers: Sequence[str]) -> frozenset[str]:
    if isinstance(layers, str):
        layers = (layers,)
    wanted = frozenset(layers)
    unknown = sorted(wanted - LAYERS)
    if unknown:
        raise ValueError(f"layers: unknown layer(s) {unknown}; expected a subset of {sorted(LAYERS)}")
    return wanted




def open_session(
    path: str | Path,
    *,
    object_ids: Sequence[int] | None = None,
    label_params: LabelParams = LabelParams(),
    cache_dir: str | Path | None = None,
    depth_method: str | None = "sgbm",
    sgbm_params: SGBMParams | None = None,
    require_masks: bool = True,
    only_stems: Sequence[str] | None = None,
) -> Session:
    """Open and validate a session directory (see the module docstring for the format).

    ``only_stems``: open the session as if left/ held these frames only (a session still being
    recorded, whose other files may be half-written: contact_viz.io.live); it grows with
    :meth:`Session.extend`.

    ``object_ids`` restricts the run to those object ids of palettized / single-channel masks
    (default: every instrument, each nonzero id); the others stay in ``Frame.tool_ids``, never tissue. ``label_params`` sets the force threshold of the contact labels.
    ``depth_method`` computes depth from the stereo pair when there is neither depth/ nor
    disparity/ ("sgbm", with ``sgbm_params``; None = never compute), cached under ``cache_dir``
    (default: the package cache, see contact_viz.io.cache; never inside the session).
    ``require_masks=False`` allows a session without masks/ (mask layers then give BadFrames),
    e.g. to precompute depth. The chosen depth source is logged (INFO) and kept in
    ``Session.depth_note``. Raises SessionError (naming the file and what was expected) on any
    session-wide problem; warns (SessionWarning) about CSV rows naming stems that are not in left/.
    """
    if depth_method is not None and depth_method not in DEPTH_METHODS:
        raise ValueError(f"depth_method must be one of {DEPTH_METHODS} or None, got {depth_method!r}")
    if object_ids is not None:
        if not object_ids or any(isinstance(i, bool) or not isinstance(i, int) or i < 1 for i in object_ids):
            raise ValueError(f"object_ids must be positive integers (0 is background) or None, got {object_ids!r}")
        object_ids = tuple(sorted(set(object_ids)))
    root = Path(path).expanduser()
    expected = "a session directory (left/, masks/ and K.txt; depth/ optional, see the README)"
    try:
        if not root.exists():
            raise SessionError(root, f"missing: expected {expected}")
        if not root.is_dir():
            raise SessionError(root, f"expected {expected}, found a file")
        root = root.resolve(strict=True)
    except OSError as exc:  # a symbolic link loop, a path through a file, no permission
        raise SessionError(root, f"expected {expected}, could not open it ({exc.strerror or exc})") from None

    meta = _read_session_json(root / "session.json")
    left_dir = root / "left"
    if not left_dir.is_dir():
        raise SessionError(left_dir, "missing: expected a directory of rectified left frames left/<stem>.png|jpg")
    left_files = _list_stems(left_dir, IMAGE_SUFFIXES)
    if only_stems is not None:
        keep = set(only_stems)
        left_files = {stem: path for stem, path in left_files.items() if stem in keep}
    if not left_files:
        raise SessionError(left_dir, "expected rectified left frames left/<stem>.png|jpg|jpeg, found none")
    stems = sorted(left_files, key=natural_key)
    image_size = read_image_size(left_files[stems[0]])
    stereo = read_calibration(root, image_size)
    mask_files = _find_masks(root, required=require_masks)
    right_dir = root / "right"
    right_files = _list_stems(right_dir, IMAGE_SUFFIXES) if right_dir.is_dir() else {}
    source = find_depth_source(root, right_files, stereo, depth_method)
    depth_files = source.files
    if only_stems is not None:
        mask_files, right_files, depth_files = ({stem: path for stem, path in files.items() if stem in left_files}
                                                for files in (mask_files, right_files, source.files))
    sgbm_cache = None
    if source.kind == "sgbm":
        cal = stereo.calibration  # the search range from the calibration and SGBMParams.min_depth_m
        resolved = (sgbm_params or SGBMParams()).resolve(image_size[1], fx_px=cal.fx, baseline_m=cal.baseline_m,
                                                         disparity_offset_px=cal.disparity_offset_px)
        sgbm_cache = DisparityCache.for_session(root, stereo.files, resolved, cache_dir)
    note = f"{root.name}: {source.note}; {stereo.describe()}"
    log.info(note)

    fps = float(meta.get("fps", DEFAULT_FPS))
    frames_csv = root / "frames.csv"
    frame_times = _read_frames_csv(frames_csv, stems) if frames_csv.is_file() else None
    timestamps_s = frame_times if frame_times is not None else np.arange(len(stems), dtype=np.float64) / fps

    force_csv = root / "force.csv"
    if force_csv.is_file():
        force_xyz_n = _read_force_csv(force_csv, stems, frame_times, frames_csv)
    else:
        force_xyz_n = np.full((len(stems), 3), np.nan)
    force_n = np.linalg.norm(force_xyz_n, axis=1)
    labels = force_labels(force_n, label_params)
    label_source = np.where(labels >= 0, "force", "none").astype("<U6")

    labels_csv = root / "labels.csv"
    tool_labels = None
    if labels_csv.is_file():
        manual_index, manual_contact, manual_tools = _read_labels_csv(labels_csv, stems)
        if manual_tools is not None:  # per instrument: the scene is in contact when any instrument is
            tool_labels, manual_index, manual_contact = tool_label_arrays(
                len(stems), manual_index, manual_contact, manual_tools, object_ids)
        labels[manual_index] = manual_contact
        label_source[manual_index] = "manual"

    kinematics = read_kinematics(root / KINEMATICS_FILE) if (root / KINEMATICS_FILE).is_file() else None
    tool_tips_xy = read_tool_tips(root / TOOL_TIPS_FILE, stems) if (root / TOOL_TIPS_FILE).is_file() else None

    session = Session(
        root=root,
        name=meta.get("name") or root.name,
        phantom=meta.get("phantom"),
        task=meta.get("task"),
        fps=fps,
        calibration=stereo.calibration,
        stems=stems,
        image_size=image_size,
        timestamps_s=timestamps_s,
        force_xyz_n=force_xyz_n,
        force_n=force_n,
        labels=labels,
        label_source=label_source,
        label_params=label_params,
        tool_labels=tool_labels,
        left_files=left_files,
        right_files=right_files,
        mask_files=mask_files,
        depth_files=depth_files,
        object_ids=object_ids,
        depth_source=source.kind,
        depth_note=note,
        stereo=stereo,
        sgbm_cache=sgbm_cache,
        kinematics=kinematics,
        tool_tips_xy=tool_tips_xy,
    )
    session.check_format()
    return session
