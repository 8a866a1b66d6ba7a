"""What a debugger run shows and how densely (:class:`DebuggerOptions`), which frames
(:func:`select_frames`), and what it did (:class:`RunSummary`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from contact_viz.checks.params import DiagnosticParams
from contact_viz.console import frame_name, frames_text
from contact_viz.geometry.pointcloud import CloudParams
from contact_viz.io.decoders import JPEG_REDUCTIONS
from contact_viz.params import PatchParams, check_fields, checked
from contact_viz.viz.video import VideoParams

IMAGE_MODES = ("video", "jpeg", "raw")  # how the images are logged: video stream, JPEG, decoded RGB


@dataclass(frozen=True)
class DebuggerOptions:
    """What ``contact-viz view`` shows and how densely."""

    start: int = checked(0, ge=0)  # first frame index shown (0-based, inclusive)
    end: int | None = checked(None, ge=0)  # stop before this frame index (exclusive); None = the last frame
    stride: int = checked(1, ge=1)  # show every stride-th frame from start, frames
    # "video" (AV1/H.264 stream), "jpeg" (exact JPEG files) or "raw" (RGB, 6 MB per 1080p image)
    images: str = checked("video", choices=IMAGE_MODES)
    video: VideoParams = field(default_factory=VideoParams)  # codec, quality and keyframes of images="video"
    # images="jpeg": JPEG quality for images that are not JPEG files already, 1-100
    jpeg_quality: int = checked(85, ge=1, le=100)
    with_right: bool = True  # log the right image (when the session has right/)
    # images="video": the right image at 1/right_step of its size, 1 or 2. 2: the right pane of the default layout
    # shows it at a third of its width anyway, and it halves the image work of a frame pair (JPEG files decode at
    # half size in a quarter of the time; a quarter of the pixels to encode): 21 ms less CPU per 1080p frame
    right_step: int = checked(2, choices=(1, 2))
    # log every depth_step-th depth pixel along rows and columns, px. 6: 320x180 at 1080p, the size of the depth pane
    # of the default layout on a 1080p screen; 51 kB a frame (3: 137 kB, 4: 81 kB, at 0.5 mm)
    depth_step: int = checked(6, ge=1)
    # uint16 depth units per metre. 2000: 0.5 mm steps up to 33 m; coarser steps compress better in the .rrd
    # (per 1080p frame at depth_step 6: 1 mm 39 kB, 0.5 mm 51 kB, 0.25 mm 63 kB, 0.1 mm 84 kB)
    depth_units_per_m: float = checked(2000.0, gt=0)
    points: bool = True  # log the RGB point cloud
    cloud: CloudParams = field(default_factory=CloudParams)  # point cloud density
    # decode left JPEGs at 1/n size for the point colours (1, 2, 4 or 8)
    color_reduction: int = checked(2, choices=JPEG_REDUCTIONS)
    patch_params: PatchParams = field(default_factory=PatchParams)  # the patch (must match the model's)
    diagnostics: DiagnosticParams = field(default_factory=DiagnosticParams)  # thresholds of the checks
    # flush the recording to its sinks every this many frames (bounds memory and loss), frames
    flush_every: int = checked(15, ge=1)
    prefetch: int = checked(4, ge=1)  # images read ahead of the frame being logged, frames
    image_workers: int = checked(2, ge=1)  # threads reading (decoding, converting) the images, one frame each
    hand_eye: tuple[tuple[float, ...], ...] | None = None  # 4x4 camera_T_base (m; io/kinematics.py); None = no tip
    kinematics_max_gap_s: float = checked(0.05, ge=0)  # a pose farther than this from a frame is not drawn there, s

    def __post_init__(self) -> None:
        check_fields(self)
        if self.hand_eye is not None and np.asarray(self.hand_eye, dtype=np.float64).shape != (4, 4):
            raise ValueError(f"DebuggerOptions.hand_eye must be a 4x4 transform, got {self.hand_eye!r}")


@dataclass(frozen=True)
class RunSummary:
    """What a run did, for the command line to print."""

    frames: int  # frames processed (logged), bad ones included
    bad_frames: int  # frames whose mask or depth could not be read
    diagnostic_counts: dict[str, int]  # diagnostic code -> frames it fired on
    interrupted: bool  # stopped early by KeyboardInterrupt (everything up to there is logged)
    elapsed_s: float  # wall time of the run, s
    wait_s: float  # waiting for the next frame: mask + depth decoding (background thread) and the patch, s
    image_wait_s: float  # waiting for the images (read and decoded in their own thread), s
    prepare_s: float  # point cloud, patch geometry, depth preview, posterior, the checks, s
    log_s: float  # Rerun calls and flushes, s
    diagnostic_ranges: dict[str, list[tuple[int, int]]] = field(default_factory=dict)  # code -> (first, last) frame runs
    instrument_frames: dict[int, int] = field(default_factory=dict)  # object id -> readable frames it is in
    nearest_frames: dict[int, int] = field(default_factory=dict)  # object id -> frames it was the nearest instrument
    contact_frames: dict[int, int] = field(default_factory=dict)  # with a model: object id -> frames it was in contact
    closest: tuple[int, float, int] | None = None  # (object id, distance mm, frame): the run's smallest |distance|
    with_model: bool = False  # the run had a model (contact_frames is meaningful)
    stop_signal: int = 0  # the signal that stopped the run (SIGINT 2, SIGTERM 15, SIGHUP 1), 0 if none
    frame_stems: tuple[str, ...] = ()  # the session's frame stems (index -> stem): frames are named by them
    session_messages: dict[str, str] = field(default_factory=dict)  # session check code that fired -> its message

    @property
    def nearest_instrument(self) -> int | None:
        """The instrument nearest the tissue on the most frames (ties: the lowest object id); None if no frame
        had an instrument with a distance."""
        if not self.nearest_frames:
            return None
        return min(self.nearest_frames, key=lambda k: (-self.nearest_frames[k], k))

    def instrument_lines(self) -> list[str]:
        """The instruments' part of the report: which were seen, the nearest one, which were in contact."""
        out = []
        if len(self.instrument_frames) > 1:
            out.append("instruments: " + ", ".join(f"{k} on {n} frame{'s' * (n != 1)}"
                                                   for k, n in sorted(self.instrument_frames.items())))
        nearest = self.nearest_instrument
        if nearest is not None:
            others = [f"{k} on {n}" for k, n in sorted(self.nearest_frames.items(), key=lambda kv: (-kv[1], kv[0]))
                      if k != nearest]
            n = self.nearest_frames[nearest]
            text = f"nearest instrument: {nearest} (nearest on {n} frame{'s' * (n != 1)}"
            text += "".join(f", {o}" for o in others) + ")"
            if self.closest is not None:
                tool, distance_mm, frame = self.closest
                who = f"instrument {tool}, " if len(self.instrument_frames) > 1 else ""
                text += f"; closest: {who}{distance_mm:.1f} mm at frame {frame_name(frame, self.frame_stems)}"
            out.append(text)
        elif self.instrument_frames:
            out.append("nearest instrument: none (no frame had a distance)")
        if self.with_model and self.instrument_frames:
            if self.contact_frames:
                out.append("in contact: " + ", ".join(
                    f"instrument {k} on {n} frame{'s' * (n != 1)}"
                    for k, n in sorted(self.contact_frames.items(), key=lambda kv: (-kv[1], kv[0]))))
            else:
                out.append("in contact: no instrument on any frame (no posterior at or above the threshold)")
        return out

    @property
    def stop_name(self) -> str:
        """How the run was stopped early: "interrupted (Ctrl-C)", "stopped by SIGTERM" ..."""
        import signal

        if self.stop_signal in (0, signal.SIGINT):
            return "interrupted (Ctrl-C)"
        return f"stopped by {signal.Signals(self.stop_signal).name}"

    @property
    def frames_per_s(self) -> float:
        return self.frames / self.elapsed_s if self.elapsed_s > 0 else math.nan

    def lines(self) -> list[str]:
        """A short human-readable report."""
        out = [f"{self.frames} frame{'' if self.frames == 1 else 's'} in {self.elapsed_s:.1f} s ({self.frames_per_s:.1f} frames/s)"
               + (f", {self.stop_name}: the recording is partial" if self.interrupted else "")]
        out.append(f"time: next frame {self.wait_s:.1f} s, images {self.image_wait_s:.1f} s, "
                   f"prepare {self.prepare_s:.1f} s, log {self.log_s:.1f} s")
        out += self.instrument_lines()
        fired = {code: n for code, n in self.diagnostic_counts.items() if n}
        if fired:
            out.append("diagnostics:")
            for code, n in fired.items():
                runs = self.diagnostic_ranges.get(code, [])
                text = frames_text(runs, self.frame_stems, 8)
                if code in self.session_messages and n == self.frames:  # a session check, on every frame shown
                    text = self.session_messages[code]
                out.append(f"  {code} on {n} frame{'s' * (n != 1)}" + (f": {text}" if text else ""))
        else:
            out.append("diagnostics: none fired")
        return out


def select_frames(n_frames: int, start: int = 0, end: int | None = None, stride: int = 1) -> range:
    """Frames ``start, start + stride, ...`` below ``end`` (default ``n_frames``); ValueError if none / out of range."""
    stop = n_frames if end is None else end
    if start >= n_frames:
        raise ValueError(f"start: frame {start} is past the last frame ({n_frames - 1}) of this session")
    if stop > n_frames:
        raise ValueError(f"end: {stop} is past the end of this session ({n_frames} frames; end is exclusive)")
    if stop <= start:
        raise ValueError(f"end ({stop}) must be greater than start ({start})")
    return range(start, stop, stride)
