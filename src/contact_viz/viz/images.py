"""What the viewer shows of a frame's images: read, scaled and encoded (JPEG, raw RGB or a video
stream), in their own thread, with the images the checks read; problems become notes, never errors.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from contact_viz.errors import SessionError, SessionWarning
from contact_viz.io.decoders import read_jpeg_bytes, read_jpeg_reduced
from contact_viz.io.session import JPEG_SUFFIXES, Session, read_rgb
from contact_viz.pipeline.check import grey_step, load_grey
from contact_viz.viz import rerun_log
from contact_viz.viz.video import (
    CODECS,
    FRAME_SIZES,
    BackgroundEncoder,
    EncoderUnavailable,
    VideoEncoder,
    even_size,
    rgb_to_i420,
    size_problem,
)

DebuggerOptions = Any  # contact_viz.viz.debugger.DebuggerOptions (the debugger imports this module)


@dataclass(frozen=True)
class ShownImages:
    left_jpeg: bytes | None  # images="jpeg"
    left_rgb: np.ndarray | None  # images="raw"
    left_i420: np.ndarray | None  # images="video": the frame to encode
    colors_rgb: np.ndarray | None  # left image (full or reduced size) for the point colours
    right_jpeg: bytes | None
    right_rgb: np.ndarray | None
    right_i420: np.ndarray | None
    has_right: bool
    notes: tuple[str, ...]
    left_grey: np.ndarray | None = None  # the images the checks read (contact_viz.pipeline.check.load_grey)
    right_grey: np.ndarray | None = None


def every_nth_pixel(image: np.ndarray, n: int) -> np.ndarray:
    """``image[::n, ::n]``, contiguous. When n divides both sides, by OpenCV's nearest-neighbour resize (the same
    pixels: it takes source pixel n*i; 0.36 against 2.1 ms of CPU for a 1080p RGB image at n = 2, and it releases
    the GIL, which NumPy's strided copy holds while the run loop waits for it)."""
    height, width = image.shape[:2]
    if n > 1 and height % n == 0 and width % n == 0:
        return cv2.resize(image, (width // n, height // n), interpolation=cv2.INTER_NEAREST)
    return np.ascontiguousarray(image[::n, ::n])


def right_step_of(session: Session, options: DebuggerOptions) -> int:
    """The right image's scale-down factor: ``options.right_step`` with images="video", 1 otherwise, and 1 when the
    right video at 1/right_step would be smaller than the codec takes (images of a few pixels: nothing to save)."""
    if options.images != "video" or options.right_step == 1:
        return 1
    height, width = session.image_size
    video_h, video_w = even_size(-(-height // options.right_step), -(-width // options.right_step))
    min_w, min_h = FRAME_SIZES[options.video.codec][0]
    return options.right_step if video_w >= min_w and video_h >= min_h else 1


class ImageReader:
    """Loads what the viewer shows of a frame's left and right images; problems become notes.

    ``videos`` (images="video"): the video streams; a side they could not encode is read as in "jpeg"."""

    def __init__(self, session: Session, options: DebuggerOptions, with_right: bool,
                 videos: VideoStreams | None = None) -> None:
        self.session = session
        self.options = options
        self.with_right = with_right
        self.grey_step = grey_step(session, options.diagnostics)
        self.modes = {side: options.images for side in ("left", "right")}  # how each side's image is logged
        for side in videos.jpeg_sides if videos is not None else ():
            self.modes[side] = "jpeg"
        self.right_step = right_step_of(session, options)

    def _read(self, side: str, path: Path, want_colors: bool, step: int = 1):
        """(jpeg bytes, raw rgb, I420 frame, colour image, decoded RGB) of one image; raises SessionError on
        a problem. The decoded RGB (full size, rectified; None for JPEG files read without a full decode)
        feeds the image checks.

        ``step`` (images="video", the right image): the frame to encode, or the JPEG image of a stream the
        encoder refused, is the image at 1/step of its size."""
        height, width = self.session.image_size
        opts = self.options
        mode = self.modes[side]
        rectification = self.session.rectification
        if mode != "raw" and step > 1 and rectification is None and path.suffix.lower() in JPEG_SUFFIXES:
            bgr = read_jpeg_reduced(path, step, (height, width), side)  # a quarter of a full decode's time
            if mode == "jpeg":
                return self._jpeg(path, side, bgr), None, None, None, None
            return None, None, rgb_to_i420(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)), None, None
        if mode == "jpeg" and step == 1 and rectification is None and path.suffix.lower() in JPEG_SUFFIXES:
            data = read_jpeg_bytes(path, f"a JPEG {side} image")
            colors = None
            if want_colors:
                bgr = read_jpeg_reduced(path, opts.color_reduction, (height, width), side, data=data)
                colors = cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
            return data.tobytes(), None, None, colors, None
        rgb = read_rgb(path)
        if rectification is not None:  # raw recordings: show the rectified view the depth belongs to
            try:
                rgb = rectification.apply(side, rgb)
            except ValueError as exc:
                raise SessionError(path, str(exc)) from exc
        if rgb.shape[:2] != (height, width):
            raise SessionError(path, f"expected a {side} image of {height}x{width} px (height x width), "
                                     f"found {rgb.shape[0]}x{rgb.shape[1]}")
        if mode == "raw":
            return None, rgb, None, rgb, rgb
        small = rgb if step == 1 else cv2.resize(rgb, (-(-width // step), -(-height // step)),
                                                  interpolation=cv2.INTER_AREA)
        if mode == "video":
            n = opts.color_reduction  # the point colours need no more than a 1/n-size image
            colors = every_nth_pixel(rgb, n) if want_colors else None
            return None, None, rgb_to_i420(small), colors, rgb
        return self._jpeg(path, side, cv2.cvtColor(small, cv2.COLOR_RGB2BGR)), None, None, rgb, rgb

    def _jpeg(self, path: Path, side: str, bgr: np.ndarray) -> bytes:
        """``bgr`` JPEG-encoded at the options' jpeg_quality; SessionError if OpenCV cannot."""
        ok, encoded = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.options.jpeg_quality])
        if not ok:
            raise SessionError(path, f"could not JPEG-encode the {side} image")
        return encoded.tobytes()

    def _grey(self, side: str, index: int, rgb: np.ndarray | None) -> np.ndarray | None:
        try:
            return load_grey(self.session, side, index, self.grey_step, rgb=rgb)
        except SessionError:  # the image's note says why; its checks are skipped
            return None

    def load(self, index: int) -> ShownImages:
        stem = self.session.stems[index]
        notes = []
        left = right = (None, None, None, None, None)
        try:
            left_path = self.session.image_path("left", index)
            if left_path is None:
                raise SessionError(self.session.root / "left" / f"{stem}.jpg", "missing: expected the left image")
            left = self._read("left", left_path, self.options.points)
        except SessionError as exc:
            notes.append(f"frame {stem}: left image not shown: {exc}")
        right_path = self.session.image_path("right", index) if self.with_right else None
        if right_path is not None:
            try:
                right = self._read("right", right_path, False, self.right_step)
            except SessionError as exc:
                notes.append(f"frame {stem}: right image not shown: {exc}")
        # the checks' grey images: from the decoded RGB, or a reduced-size decode of a JPEG file
        greys = [self._grey(side, index, read[4]) if use else None
                 for side, read, use in (("left", left, True), ("right", right, right_path is not None))]
        return ShownImages(left[0], left[1], left[2], left[3], right[0], right[1], right[2], right_path is not None,
                       tuple(notes), *greys)


class VideoStreams:
    """The left and right video encoders (one thread each) of images="video", and logging their samples.

    A stream whose encoder cannot be opened (a size the codec refuses, checked before opening it; a codec
    missing from this FFmpeg build; any other refusal) is not a video: its side is in ``jpeg_sides`` (the
    image reader logs its images as JPEG images instead) and one SessionWarning per reason says so."""

    def __init__(self, session: Session, rec, options: DebuggerOptions, with_right: bool) -> None:
        params = options.video
        height, width = session.image_size
        fps = float(session.fps) / options.stride  # frames per second of the video (every stride-th frame)
        self.rec = rec
        self.session = session  # its frame times (read when a sample is logged: a followed session grows)
        sides = {rerun_log.ENTITY_LEFT_IMAGE: "left", rerun_log.ENTITY_RIGHT_IMAGE: "right"}
        wanted = [rerun_log.ENTITY_LEFT_IMAGE] + ([rerun_log.ENTITY_RIGHT_IMAGE] if with_right else [])
        step = {rerun_log.ENTITY_LEFT_IMAGE: 1, rerun_log.ENTITY_RIGHT_IMAGE: right_step_of(session, options)}
        self.encoders: dict[str, BackgroundEncoder] = {}
        # (refused by the size check?, the reason) -> [(side, its images' or frames' size)]: one warning line each
        refused: dict[tuple[bool, str], list[tuple[str, str]]] = {}
        for entity in wanted:
            image_h, image_w = -(-height // step[entity]), -(-width // step[entity])
            video_h, video_w = even_size(image_h, image_w)
            problem = size_problem(params.codec, video_w, video_h)
            if problem is not None:  # the encoder is not even opened (it would print its refusal)
                scaled = f" at 1/{step[entity]} size" if step[entity] > 1 else ""
                padded = f" (padded to {video_w}x{video_h} px)" if (video_h, video_w) != (image_h, image_w) else ""
                refused.setdefault((True, problem), []).append(
                    (sides[entity], f"{image_w}x{image_h} px images{scaled}{padded}"))
                continue
            try:
                self.encoders[entity] = BackgroundEncoder(VideoEncoder(video_w, video_h, fps, params))
            except EncoderUnavailable as exc:
                refused.setdefault((False, exc.reason), []).append((sides[entity], f"{video_w}x{video_h}"))
        self.entities = list(self.encoders)
        self._grey: dict[str, np.ndarray] = {}  # entity -> the frame an unreadable image is encoded as
        self.jpeg_sides = frozenset(side for streams in refused.values() for side, _ in streams)
        for (checked_size, reason), streams in refused.items():
            where = " and ".join(str(session.root / side) for side, _ in streams)
            sizes = " and ".join(dict.fromkeys(size for _, size in streams))
            why = (f"{sizes} are {reason}" if checked_size else
                   f"the {params.codec} encoder ({CODECS[params.codec][0]}) could not be opened for {sizes} px "
                   f"frames: {reason}")
            warnings.warn(f"{where}: {why}; logged as JPEG images instead", SessionWarning, stacklevel=3)
        if self.entities:
            rerun_log.log_video_codec(rec, self.entities, params.codec)

    def feed(self, index: int, shown: ShownImages) -> None:
        """Queue this frame's images and log the samples finished so far. A side whose image could not be read
        gets a mid-grey frame: a video shows its last frame until the next sample, and the viewer must not show
        the frame before as this one's."""
        for entity, i420 in ((rerun_log.ENTITY_LEFT_IMAGE, shown.left_i420),
                             (rerun_log.ENTITY_RIGHT_IMAGE, shown.right_i420)):
            encoder = self.encoders.get(entity)
            if encoder is None:
                continue
            if i420 is None:
                i420 = self._grey.setdefault(entity, np.full(encoder.frame_shape_i420, 128, np.uint8))
            self._log(entity, encoder.submit(i420, index))

    def _log(self, entity: str, samples) -> None:
        rerun_log.log_video_samples(self.rec, entity, samples, self.session.timestamps_s)

    def close(self) -> None:
        """Encode what is queued, flush the encoders and log the last samples."""
        for entity, encoder in self.encoders.items():
            self._log(entity, encoder.close())
