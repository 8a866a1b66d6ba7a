"""Video encoding of the stereo images for the recordings: PyAV (libsvtav1 or libx264) on the fly, no Rerun here.

:class:`VideoEncoder` turns a stream of same-size frames into *samples*, one per frame, in the form
Rerun's ``VideoStream`` expects: AV1 as a sequence of OBUs (low-overhead bitstream format, a
sequence header with every keyframe), H.264 as Annex B (SPS/PPS with every keyframe); no B-frames
(every sample carries exactly one shown frame, in presentation order), a keyframe every
``keyframe_interval_s`` so that seeking on the timeline decodes at most that much video.

Frames go in as 8-bit YUV 4:2:0 (I420, BT.601 limited range, OpenCV's ``COLOR_RGB2YUV_I420``:
:func:`rgb_to_i420`), and the streams say so in their colour metadata, so a viewer that follows it
(Rerun's AV1 decoder and the browsers do) shows the colours of the source.

Pure of Rerun and of the session: the debugger feeds frames and logs the samples.
"""

from __future__ import annotations

import math
import sys
import tempfile
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from fractions import Fraction

import os

# SVT-AV1 prints its configuration to stderr unless told: errors only (and those of opening an encoder are
# captured, see VideoEncoder)
os.environ.setdefault("SVT_LOG", "1")

import av  # noqa: E402
import cv2  # noqa: E402
import numpy as np  # noqa: E402

from contact_viz.params import check_fields, checked  # noqa: E402

__all__ = [
    "CODECS",
    "DEFAULT_CRF",
    "FRAME_SIZES",
    "BackgroundEncoder",
    "EncodedSample",
    "EncoderUnavailable",
    "VideoEncoder",
    "VideoParams",
    "even_size",
    "size_problem",
    "rgb_to_i420",
    "i420_to_rgb",
    "psnr_db",
]

# codec name -> (PyAV/FFmpeg encoder, encoder options). AV1: SVT-AV1's fastest preset (M11; 12 and 13 map to it
# in SVT-AV1 4.x) with its low-delay prediction structure (pred-struct=1: no frame reordering and no look-ahead
# delay; 24 ms of CPU per 1080p frame against 35 ms for the default random-access structure, same size).
# lp=1: one SVT thread per stream (each stream has its own encoder thread already; 45 MB less memory for the two
# 1080p encoders and 6% less CPU than SVT's own threads). H.264: x264 ultrafast (17 ms per 1080p frame), Annex B with
# in-band SPS/PPS.
CODECS = {
    "av1": ("libsvtav1", {"preset": "11", "svtav1-params": "pred-struct=1:lp=1"}),
    "h264": ("libx264", {"preset": "ultrafast", "tune": "zerolatency", "bf": "0"}),
}
# default quality per codec: the AV1 default gives 44 dB median PSNR on the synthetic 1080p sessions at 4 kB a frame;
# x264's scale differs (its 30 gives 36 dB where AV1's 30 gives 41 on tests/test_video.py's scene)
DEFAULT_CRF = {"av1": 30, "h264": 23}
# codec -> ((min width, min height), (max width, max height)) of the frames its encoder takes, px. Measured by
# opening the encoders of CODECS with PyAV 18.1 (FFmpeg 8, SVT-AV1 4.1, x264): SVT-AV1 refuses a side under 4 px
# ("Svt[error]: Source Width must be at least 4"), a width over 16384 or a height over 8704; x264 a side over 16384
# (and, in 4:2:0, an odd side, "width not divisible by 2": even_size pads odd images, so frames are even). Checked
# before an encoder is opened (size_problem), so that it never prints its refusal.
FRAME_SIZES = {"av1": ((4, 4), (16384, 8704)), "h264": ((2, 2), (16384, 16384))}
_SMPTE170M = 6  # FFmpeg's AVCOL_SPC/PRI/TRC_SMPTE170M: BT.601 (525-line) matrix, primaries and transfer
_LIMITED_RANGE = 1  # FFmpeg's AVCOL_RANGE_MPEG: Y in 16-235, U and V in 16-240


@dataclass(frozen=True)
class VideoParams:
    """How the stereo images are video-encoded (``--images video``)."""

    # "av1" (decoded by the stock native viewer itself) or "h264" (the native viewer needs FFmpeg for it)
    codec: str = checked("av1", choices=CODECS)
    # constant rate factor: lower = better and larger (AV1 0-63, H.264 0-51); None = DEFAULT_CRF of the codec
    crf: int | None = checked(None, ge=0, le=63)
    keyframe_interval_s: float = checked(1.0, gt=0)  # at most this much video between keyframes (seek cost), s
    threads: int = checked(0, ge=0)  # encoder threads per stream (0 = the encoder's choice)

    def __post_init__(self) -> None:
        check_fields(self)
        if self.crf is None:
            object.__setattr__(self, "crf", DEFAULT_CRF[self.codec])
        if self.codec == "h264" and self.crf > 51:
            raise ValueError(f"VideoParams.crf must be an integer in [0, 51] for h264, got {self.crf!r}")


@dataclass(frozen=True)
class EncodedSample:
    """One encoded frame: its tag (the caller's frame index), the sample bytes and whether it is a keyframe."""

    tag: int  # what the caller passed to VideoEncoder.encode with this frame (the frame index)
    data: bytes  # AV1 OBUs or H.264 Annex B NAL units of exactly one shown frame
    is_keyframe: bool  # decodable without any earlier sample (carries the sequence header / SPS)


def even_size(height: int, width: int) -> tuple[int, int]:
    """The frame size of the video of an image of ``height`` x ``width`` px (4:2:0 needs both even), px."""
    return height + height % 2, width + width % 2


def size_problem(codec: str, width: int, height: int) -> str | None:
    """Why the ``codec`` encoder would refuse ``width`` x ``height`` px frames ("smaller than the av1 encoder takes
    (at least 4x4 px)"), or None if it takes them (:data:`FRAME_SIZES`)."""
    (min_w, min_h), (max_w, max_h) = FRAME_SIZES[codec]
    if width < min_w or height < min_h:
        return f"smaller than the {codec} encoder takes (at least {min_w}x{min_h} px)"
    if width > max_w or height > max_h:
        return f"larger than the {codec} encoder takes (at most {max_w}x{max_h} px)"
    return None


class EncoderUnavailable(RuntimeError):
    """The video encoder could not be opened (codec missing from this FFmpeg build, a frame size it refuses ...).

    The message is one line for the user, without the encoder's own log; ``reason`` is its part that does not
    depend on the frame size when the encoder was tried ("Source Width must be at least 4", "this FFmpeg build
    has no libsvtav1 encoder"), or the size check's phrase ("smaller than the av1 encoder takes (at least 4x4 px)").
    Callers log the images another way."""

    def __init__(self, message: str, reason: str = "") -> None:
        super().__init__(message)
        self.reason = reason or message


_ENCODER_LOG_PREFIXES = ("Svt[",)  # what SVT-AV1 writes to fd 2 (its errors; SVT_LOG=1 keeps its info lines off)


@contextmanager
def _encoder_output_captured() -> Iterator[list[str]]:
    """Capture what C code writes to file descriptor 2 in this block (SVT-AV1 prints its errors there, outside
    Python and PyAV's logging); the yielded list holds the encoder's lines at exit. Anything else written there
    meanwhile (another thread's output) is passed on to fd 2 afterwards. Without a usable fd 2, captures nothing."""
    lines: list[str] = []
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError, AttributeError):
        yield lines
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield lines
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            other = []
            for line in tmp.read().decode("utf-8", "replace").splitlines():
                (lines if line.startswith(_ENCODER_LOG_PREFIXES) else other).append(line)
            _write_fd2(other)


def _write_fd2(lines: list[str]) -> None:
    if lines:
        os.write(2, ("\n".join(lines) + "\n").encode("utf-8", "replace"))


def _open_failure(exc: Exception, encoder: str, printed: list[str], logs: list) -> str:
    """The reason, in one line, why ``encoder`` could not be opened: the encoder's own error lines (SVT-AV1's
    ``printed`` ones, FFmpeg's ``logs`` of level error or worse), else the exception's short text."""
    reasons = []
    for line in printed:  # "Svt[error]: Source Width must be at least 4"
        text = line.partition("]: ")[2].strip() or line.strip()
        if text and text not in reasons:
            reasons.append(text)
    if not reasons:  # FFmpeg's errors from this encoder (PyAV may also pass on an earlier, repeated one)
        for level, name, message in logs:
            text = message.strip()
            if level <= av.logging.ERROR and name == encoder and text and text not in reasons:
                reasons.append(text)
    if not reasons:
        if isinstance(exc, av.codec.codec.UnknownCodecError):
            reasons.append(f"this FFmpeg build has no {encoder} encoder")
        elif isinstance(exc, av.error.FFmpegError):
            reasons.append(exc.strerror or type(exc).__name__)
        else:
            reasons.append(str(exc).splitlines()[0] if str(exc) else type(exc).__name__)
    return "; ".join(reasons[:3])


def _thread_policies() -> dict[int, int]:
    """{thread id: scheduling policy} of this process's threads (Linux; {} elsewhere)."""
    out = {}
    try:
        tids = os.listdir("/proc/self/task")
    except OSError:
        return out
    for tid in tids:
        try:
            out[int(tid)] = os.sched_getscheduler(int(tid))
        except (OSError, ValueError):
            pass
    return out


@contextmanager
def _scheduling_kept() -> Iterator[None]:
    """Opened as root, SVT-AV1 makes the calling thread and the threads it starts real-time (SCHED_FIFO, priority
    99). Every process started from such a thread inherits it, and CPU-bound real-time processes starve all others
    (two of them froze a `batch` run on a 2-core machine). Threads that became real-time meanwhile are put back to
    the normal policy."""
    realtime = (getattr(os, "SCHED_FIFO", -1), getattr(os, "SCHED_RR", -1))
    before = _thread_policies()
    try:
        yield
    finally:
        for tid, policy in _thread_policies().items():
            if policy in realtime and before.get(tid) not in realtime:
                try:
                    os.sched_setscheduler(tid, os.SCHED_OTHER, os.sched_param(0))
                except OSError:
                    pass


def rgb_to_i420(rgb: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB -> (3H'/2, W') uint8 I420 (BT.601 limited range), H' x W' = :func:`even_size`.

    OpenCV's conversion: each chroma sample is that of the top-left pixel of its 2x2 block (1.5 ms
    a 1080p frame; averaging the block's colour first costs 8 ms and gains ~3 dB only on detailed
    colour such as random colour noise, not on camera images). An odd height or width gets one
    more row or column, a copy of the last (the video shows it).
    """
    height, width = rgb.shape[:2]
    if height % 2 or width % 2:
        rgb = cv2.copyMakeBorder(rgb, 0, height % 2, 0, width % 2, cv2.BORDER_REPLICATE)
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2YUV_I420)


def i420_to_rgb(i420: np.ndarray) -> np.ndarray:
    """(3H/2, W) uint8 I420 (BT.601 limited range) -> (H, W, 3) uint8 RGB: the inverse of :func:`rgb_to_i420`."""
    return cv2.cvtColor(i420, cv2.COLOR_YUV2RGB_I420)


def psnr_db(a: np.ndarray, b: np.ndarray) -> float:
    """Peak signal-to-noise ratio of two uint8 arrays of the same shape, dB (inf when equal)."""
    if a.shape != b.shape:
        raise ValueError(f"psnr_db: shapes differ, {a.shape} and {b.shape}")
    mse = float(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2))
    return math.inf if mse == 0 else 10.0 * math.log10(255.0 ** 2 / mse)


class VideoEncoder:
    """Encodes frames of one stream (``width`` x ``height``, both even) into :class:`EncodedSample` s, in order.

    ``encode(i420, tag)`` returns the samples that became ready (usually this frame's; the
    encoder may hold a frame or two back), ``flush()`` the rest at the end. Not thread-safe: one
    thread per encoder (its frames must arrive in order anyway).

    :class:`EncoderUnavailable` (one line, nothing printed) when the encoder cannot be opened: a size outside
    :data:`FRAME_SIZES` (checked first: the encoder is not opened), a codec missing from this FFmpeg build, or
    any other refusal (the encoder's own error lines become the message instead of reaching the console).
    """

    def __init__(self, width: int, height: int, fps: float, params: VideoParams = VideoParams()) -> None:
        if width % 2 or height % 2 or width <= 0 or height <= 0:
            raise ValueError(f"VideoEncoder: width and height must be even and positive (4:2:0), got {width}x{height}")
        if not (math.isfinite(fps) and fps > 0):
            raise ValueError(f"VideoEncoder: fps must be > 0, got {fps!r}")
        name, options = CODECS[params.codec]
        problem = size_problem(params.codec, width, height)
        if problem is not None:
            raise EncoderUnavailable(f"{width}x{height} px frames are {problem}", problem)
        self.params = params
        self.width, self.height = width, height
        av.logging.set_level(av.logging.ERROR)  # SVT-AV1 prints its whole configuration at INFO
        with av.logging.Capture() as logs, _encoder_output_captured() as printed:
            try:
                cc = self._open(name, options, width, height, fps, params)
            except Exception as exc:  # noqa: BLE001 (whatever the reason: the caller shows the images another way)
                error = exc
            else:
                error = None
        if error is None and printed:  # what SVT_LOG set by the user asks for (its default, 1, prints nothing here)
            _write_fd2(printed)
        if error is not None:
            reason = _open_failure(error, name, printed, logs)
            raise EncoderUnavailable(f"the {params.codec} encoder ({name}) could not be opened for {width}x{height} "
                                     f"px frames: {reason}", reason) from error
        self._cc = cc
        self._tags: dict[int, int] = {}  # pts -> caller's tag
        self._pts = 0

    @staticmethod
    def _open(name: str, options: dict, width: int, height: int, fps: float, params: VideoParams):
        rate = Fraction(fps).limit_denominator(1001)
        cc = av.CodecContext.create(name, "w")
        cc.width, cc.height = width, height
        cc.pix_fmt = "yuv420p"
        cc.time_base = 1 / rate
        cc.framerate = rate
        cc.gop_size = max(1, round(params.keyframe_interval_s * fps))
        cc.max_b_frames = 0  # Rerun's VideoStream has no decode timestamps: no B-frames
        cc.thread_count = params.threads
        # what rgb_to_i420 makes: BT.601 (SMPTE 170M) limited range, written into the stream's colour metadata
        cc.colorspace = _SMPTE170M  # matrix coefficients
        cc.color_primaries = _SMPTE170M
        cc.color_trc = _SMPTE170M
        cc.color_range = _LIMITED_RANGE
        cc.options = {**options, "crf": str(params.crf)}
        with _scheduling_kept():
            cc.open()
        return cc

    def _samples(self, packets) -> list[EncodedSample]:
        out = []
        for packet in packets:
            if packet.pts is None or packet.size == 0:
                continue
            out.append(EncodedSample(tag=self._tags.pop(packet.pts), data=bytes(packet),
                                     is_keyframe=bool(packet.is_keyframe)))
        return out

    def encode(self, i420: np.ndarray, tag: int) -> list[EncodedSample]:
        """Feed one frame (``(3H/2, W)`` uint8 I420, see :func:`rgb_to_i420`), tagged ``tag``; samples now ready."""
        if i420.shape != (self.height * 3 // 2, self.width) or i420.dtype != np.uint8:
            raise ValueError(f"VideoEncoder.encode: expected a ({self.height * 3 // 2}, {self.width}) uint8 I420 "
                             f"frame, got {i420.shape} {i420.dtype}")
        frame = av.VideoFrame.from_ndarray(i420, format="yuv420p")
        frame.pts = self._pts
        self._tags[self._pts] = tag
        self._pts += 1
        return self._samples(self._cc.encode(frame))

    def flush(self) -> list[EncodedSample]:
        """The samples still held by the encoder; the encoder is finished afterwards."""
        return self._samples(self._cc.encode(None))


class BackgroundEncoder:
    """A :class:`VideoEncoder` fed through one worker thread (concurrent.futures), so encoding overlaps the caller.

    PyAV releases the GIL while the encoder works, so the caller's Python code runs meanwhile.
    ``submit`` queues a frame and returns the samples finished so far, in order; it blocks while
    more than ``max_pending`` frames wait (memory stays bounded). ``close`` returns the rest.
    """

    def __init__(self, encoder: VideoEncoder, max_pending: int = 4) -> None:
        if max_pending < 1:
            raise ValueError(f"BackgroundEncoder: max_pending must be >= 1, got {max_pending!r}")
        self._encoder = encoder
        self.frame_shape_i420 = (encoder.height * 3 // 2, encoder.width)  # the I420 frames it takes, (rows, cols)
        self._max_pending = max_pending
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="contact-viz-video")
        self._pending: deque[Future] = deque()

    def submit(self, i420: np.ndarray, tag: int) -> list[EncodedSample]:
        """Queue one frame (see :meth:`VideoEncoder.encode`); the samples finished so far."""
        self._pending.append(self._pool.submit(self._encoder.encode, i420, tag))
        return self.ready()

    def ready(self) -> list[EncodedSample]:
        """The samples of the frames finished so far (waits only while more than ``max_pending`` are queued)."""
        out: list[EncodedSample] = []
        while self._pending and (self._pending[0].done() or len(self._pending) > self._max_pending):
            out += self._pending.popleft().result()
        return out

    def close(self) -> list[EncodedSample]:
        """Wait for every queued frame, flush the encoder and stop the thread; the remaining samples."""
        try:
            out: list[EncodedSample] = []
            while self._pending:
                out += self._pending.popleft().result()
            return out + self._pool.submit(self._encoder.flush).result()
        finally:
            self._pool.shutdown(wait=True, cancel_futures=True)
