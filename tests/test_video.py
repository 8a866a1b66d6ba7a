"""Tests of the video encoding of the recordings (contact_viz.viz.video), decoded back with PyAV."""

from __future__ import annotations

import math

import numpy as np
import pytest

av = pytest.importorskip("av")

from contact_viz.viz.video import (  # noqa: E402
    BackgroundEncoder,
    VideoEncoder,
    VideoParams,
    even_size,
    psnr_db,
    rgb_to_i420,
)

DECODERS = {"av1": "libdav1d", "h264": "h264"}  # PyAV decoders of the two codecs


def bt601_rgb_to_yuv(rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Full-resolution Y, U, V of BT.601 limited range (the textbook 8-bit coefficients), float."""
    r, g, b = (rgb[..., k].astype(np.float64) for k in range(3))
    y = 16 + 0.257 * r + 0.504 * g + 0.098 * b
    u = 128 - 0.148 * r - 0.291 * g + 0.439 * b
    v = 128 + 0.439 * r - 0.368 * g - 0.071 * b
    return y, u, v


def bt601_i420_to_rgb(i420: np.ndarray) -> np.ndarray:
    """I420 (BT.601 limited range) back to RGB, the textbook formula with nearest chroma upsampling."""
    height = i420.shape[0] * 2 // 3
    width = i420.shape[1]
    y = i420[:height].astype(np.float64) - 16
    chroma = i420[height:].reshape(2, height // 2, width // 2).astype(np.float64) - 128
    u, v = (np.repeat(np.repeat(c, 2, axis=0), 2, axis=1) for c in chroma)
    rgb = np.stack([1.164 * y + 1.596 * v, 1.164 * y - 0.392 * u - 0.813 * v, 1.164 * y + 2.017 * u], axis=-1)
    return np.clip(np.rint(rgb), 0, 255).astype(np.uint8)


def moving_scene(n: int, height: int = 144, width: int = 256, seed: int = 0) -> list[np.ndarray]:
    """Frames like an endoscope's: a smooth tissue-coloured texture panning by 2 px a frame (brightness
    detail, little colour detail, as in camera images), with a dark grey bar (a 'tool') moving down."""
    import cv2

    rng = np.random.default_rng(seed)
    coarse = rng.uniform(-60, 60, (height // 8 + 2, (width + 2 * n) // 8 + 2)).astype(np.float32)
    shade = cv2.resize(coarse, ((width + 2 * n) // 8 * 8 + 16, height // 8 * 8 + 16), interpolation=cv2.INTER_CUBIC)
    tissue = np.array([190.0, 110.0, 100.0], np.float32)  # pinkish
    texture = np.clip(tissue + shade[:, :, None] * np.array([1.0, 0.8, 0.8], np.float32), 0, 255).astype(np.uint8)
    frames = []
    for t in range(n):
        frame = texture[:height, 2 * t:2 * t + width].copy()
        frame[: 20 + 3 * t, width // 2 - 12:width // 2 + 12] = (70, 70, 80)
        frames.append(np.ascontiguousarray(frame))
    return frames


def obu_types(sample: bytes) -> list[int]:
    """Types of the OBUs of an AV1 low-overhead-format sample (AV1 spec 5.3: header, leb128 size)."""
    types, pos = [], 0
    while pos < len(sample):
        header = sample[pos]
        assert header & 0x80 == 0, "forbidden bit set"
        has_extension, has_size = bool(header & 0x04), bool(header & 0x02)
        assert has_size, "low-overhead format: every OBU carries its size"
        types.append((header >> 3) & 0x0F)
        pos += 1 + has_extension
        size = shift = 0
        while True:
            byte = sample[pos]
            pos += 1
            size |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                break
        pos += size
    assert pos == len(sample)
    return types


def decode(codec: str, samples) -> list[np.ndarray]:
    """Decode samples in order with a fresh PyAV decoder: the I420 frames."""
    decoder = av.CodecContext.create(DECODERS[codec], "r")
    frames = []
    for sample in samples:
        frames += decoder.decode(av.Packet(sample.data))
    frames += decoder.decode(None)
    return [f.to_ndarray() for f in frames]


def test_rgb_to_i420_is_bt601_limited_range_and_pads_odd_sizes():
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    i420 = rgb_to_i420(rgb)
    y, u, v = bt601_rgb_to_yuv(rgb)
    assert i420.shape == (9, 8)
    np.testing.assert_allclose(i420[:6], y, atol=0.51)
    # chroma: one sample per 2x2 block, that of its top-left pixel
    np.testing.assert_allclose(i420[6:].reshape(2, 3, 4)[0], u[::2, ::2], atol=0.51)
    np.testing.assert_allclose(i420[6:].reshape(2, 3, 4)[1], v[::2, ::2], atol=0.51)
    # round trip through the textbook inverse: close on smooth colours
    flat = np.full((4, 4, 3), (200, 120, 40), np.uint8)
    np.testing.assert_allclose(bt601_i420_to_rgb(rgb_to_i420(flat)).astype(int), flat, atol=2)
    # odd sizes: one more row / column, a copy of the last
    odd = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    assert even_size(5, 7) == (6, 8)
    padded = rgb_to_i420(odd)
    assert padded.shape == (9, 8)
    y_odd = bt601_rgb_to_yuv(odd)[0]
    np.testing.assert_allclose(padded[:5, :7], y_odd, atol=0.51)
    np.testing.assert_allclose(padded[5, :7], y_odd[4], atol=0.51)
    np.testing.assert_allclose(padded[:5, 7], y_odd[:, 6], atol=0.51)


@pytest.mark.parametrize("codec", ["av1", "h264"])
def test_one_sample_per_frame_keyframes_seekable_and_faithful(codec):
    fps, n = 10.0, 25
    frames = moving_scene(n)
    encoder = VideoEncoder(256, 144, fps, VideoParams(codec=codec, keyframe_interval_s=1.0))
    samples = []
    for index, frame in enumerate(frames):
        samples += encoder.encode(rgb_to_i420(frame), 100 + index)
    samples += encoder.flush()
    # one sample per frame, in order, tagged; a keyframe every 10 frames (1 s at 10 frames/s)
    assert [s.tag for s in samples] == [100 + i for i in range(n)]
    assert [i for i, s in enumerate(samples) if s.is_keyframe] == [0, 10, 20]
    for s in samples:
        if codec == "av1":
            types = obu_types(s.data)
            # 1 = sequence header (with every keyframe, so a decoder can start there), 6 = frame
            assert (1 in types) == s.is_keyframe
            assert 6 in types or 3 in types  # a frame, or a frame header
        else:
            assert s.data.startswith(b"\x00\x00\x00\x01") or s.data.startswith(b"\x00\x00\x01")
            nal_types = [part[0] & 0x1F for part in s.data.split(b"\x00\x00\x01")[1:] if part]
            assert (7 in nal_types) == s.is_keyframe  # SPS with every keyframe
            assert 5 in nal_types or not s.is_keyframe  # IDR slice
    # decoded back: as many frames, in order, faithful (PSNR against the source, textbook conversion)
    decoded = decode(codec, samples)
    assert len(decoded) == n
    psnrs = [psnr_db(bt601_i420_to_rgb(d), f) for d, f in zip(decoded, frames)]
    assert min(psnrs) >= 38.0, psnrs
    # and the frames are not all alike: PSNR of frame k against frame k+5 is far lower
    assert psnr_db(bt601_i420_to_rgb(decoded[0]), frames[5]) < min(psnrs) - 10
    # seeking: a fresh decoder starting at the second keyframe decodes the rest
    tail = decode(codec, samples[10:])
    assert len(tail) == n - 10
    assert psnr_db(bt601_i420_to_rgb(tail[0]), frames[10]) >= 38.0
    # the stream says BT.601 limited range (what rgb_to_i420 makes), so viewers convert it back right
    decoder = av.CodecContext.create(DECODERS[codec], "r")
    first = [f for s in samples[:2] for f in decoder.decode(av.Packet(s.data))] + decoder.decode(None)
    assert first[0].colorspace in (5, 6) and first[0].color_range == 1  # BT470BG/SMPTE170M, MPEG (limited)


def test_lower_crf_is_larger_and_better():
    frames = moving_scene(6, seed=1)

    def encode(crf):
        encoder = VideoEncoder(256, 144, 30.0, VideoParams(crf=crf))
        samples = [s for i, f in enumerate(frames) for s in encoder.encode(rgb_to_i420(f), i)] + encoder.flush()
        decoded = decode("av1", samples)
        return sum(len(s.data) for s in samples), np.mean([psnr_db(bt601_i420_to_rgb(d), f)
                                                            for d, f in zip(decoded, frames)])

    (size_hi, psnr_hi), (size_lo, psnr_lo) = encode(20), encode(45)
    assert size_hi > size_lo and psnr_hi > psnr_lo


def test_background_encoder_gives_the_same_stream_in_order():
    frames = moving_scene(12, seed=2)
    direct = VideoEncoder(256, 144, 30.0)
    want = [s for i, f in enumerate(frames) for s in direct.encode(rgb_to_i420(f), i)] + direct.flush()
    background = BackgroundEncoder(VideoEncoder(256, 144, 30.0), max_pending=2)
    got = []
    for i, f in enumerate(frames):
        got += background.submit(rgb_to_i420(f), i)
    got += background.close()
    assert [s.tag for s in got] == list(range(12))
    assert [s.is_keyframe for s in got] == [s.is_keyframe for s in want]
    decoded = decode("av1", got)
    assert min(psnr_db(bt601_i420_to_rgb(d), f) for d, f in zip(decoded, frames)) >= 38.0


def test_bad_parameters_and_frames_are_refused():
    with pytest.raises(ValueError, match="codec"):
        VideoParams(codec="mpeg2")
    with pytest.raises(ValueError, match="crf"):
        VideoParams(codec="h264", crf=60)
    with pytest.raises(ValueError, match="keyframe_interval_s"):
        VideoParams(keyframe_interval_s=0)
    with pytest.raises(ValueError, match="even"):
        VideoEncoder(255, 144, 30.0)
    encoder = VideoEncoder(256, 144, 30.0)
    with pytest.raises(ValueError, match="I420"):
        encoder.encode(np.zeros((144, 256), np.uint8), 0)
    assert psnr_db(np.zeros(4, np.uint8), np.zeros(4, np.uint8)) == math.inf
    assert psnr_db(np.zeros(4, np.uint8), np.full(4, 255, np.uint8)) == pytest.approx(0.0)


@pytest.mark.parametrize("codec", ["av1", "h264"])
def test_an_encoder_leaves_every_thread_and_child_process_at_the_normal_policy(codec):
    """SVT-AV1, opened as root, makes the calling thread and its own threads real-time (SCHED_FIFO 99): a process
    started afterwards inherited it, and two CPU-bound ones froze everything else on a 2-core machine."""
    import os
    import subprocess
    import sys

    encoder = VideoEncoder(64, 48, 30.0, VideoParams(codec=codec))
    for k in range(3):
        encoder.encode(rgb_to_i420(np.full((48, 64, 3), 40 * k, np.uint8)), k)
    encoder.flush()
    realtime = (os.SCHED_FIFO, os.SCHED_RR)
    policies = {int(t): os.sched_getscheduler(int(t)) for t in os.listdir("/proc/self/task")}
    assert not [t for t, policy in policies.items() if policy in realtime], policies
    child = subprocess.run([sys.executable, "-c", "import os; print(os.sched_getscheduler(0))"],
                           capture_output=True, text=True, check=True)
    assert int(child.stdout) == os.SCHED_OTHER
