"""Images too small (or otherwise refused) for the video encoder: `contact-viz view` logs them as JPEG images with one
warning line, and the encoder's own output (SVT-AV1 prints to fd 2 from C) never reaches the console."""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image

av = pytest.importorskip("av")
rr = pytest.importorskip("rerun")

sys.path.insert(0, str(Path(__file__).parent))

from test_viewer import Recording, decode_logged_video  # noqa: E402

from contact_viz.errors import SessionWarning  # noqa: E402
from contact_viz.io.session import open_session  # noqa: E402
from contact_viz.viz import rerun_log, video  # noqa: E402
from contact_viz.viz.debugger import DebuggerOptions, run_debugger  # noqa: E402
from contact_viz.viz.rerun_log import open_recording  # noqa: E402
from contact_viz.viz.video import (  # noqa: E402
    FRAME_SIZES,
    EncoderUnavailable,
    VideoEncoder,
    VideoParams,
    even_size,
    size_problem,
)

N_FRAMES = 4
LEFT, RIGHT = rerun_log.ENTITY_LEFT_IMAGE, rerun_log.ENTITY_RIGHT_IMAGE
ENCODER_NOISE = ("Svt[", "avcodec", "Traceback", "libsvtav1]", "Error setting encoder")


def write_tiny_session(root: Path, width: int, height: int, n_frames: int = N_FRAMES) -> None:
    """A session of ``width`` x ``height`` px PNG images (a colour per frame, random brightness per pixel, as camera
    images have little colour detail), no tool in the masks, flat depth."""
    rng = np.random.default_rng(width * 100 + height)
    for sub in ("left", "right", "masks", "depth"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    (root / "K.txt").write_text(f"100 0 {(width - 1) / 2} 0 100 {(height - 1) / 2} 0 0 1\n0.005\n")
    (root / "session.json").write_text('{"fps": 30}')
    for t in range(n_frames):
        stem = f"{t:06d}"
        Image.fromarray(np.zeros((height, width), np.uint8)).save(root / "masks" / f"{stem}.png")
        np.save(root / "depth" / f"{stem}.npy", np.full((height, width), 0.1, np.float32))
        colour = rng.integers(60, 190, 3)
        left = np.clip(colour + rng.integers(-40, 40, (height, width, 1)), 0, 255).astype(np.uint8)
        Image.fromarray(left).save(root / "left" / f"{stem}.png")
        Image.fromarray(left[:, ::-1].copy()).save(root / "right" / f"{stem}.png")


def tree_digest(root: Path) -> dict[str, str]:
    """Relative path -> sha256 of every file under ``root`` (directories by their listing)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
            for p in sorted(root.rglob("*"))}


def png_rgb(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB"))


def jpeg_rgb(value) -> np.ndarray:
    blob = value.values[0].values.to_numpy(zero_copy_only=False).astype(np.uint8).tobytes()
    return cv2.imdecode(np.frombuffer(blob, np.uint8), cv2.IMREAD_COLOR)[:, :, ::-1]


def too_small(codec: str, width: int, height: int) -> bool:
    video_h, video_w = even_size(height, width)
    return size_problem(codec, video_w, video_h) is not None


def pinhole_resolution(rec: Recording, entity: str) -> list[float]:
    return list(np.ravel(rec.static[(entity, "Pinhole:resolution")].as_py()))


def view(session_dir: Path, out: Path, *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "SVT_LOG"}  # the package's own default
    return subprocess.run([sys.executable, "-m", "contact_viz.cli", "view", str(session_dir), "--save", str(out),
                           *args], capture_output=True, text=True, timeout=300, env=env)


# ------------------------------------------------------------------------------------------
# The limits, against the encoders themselves
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("codec", sorted(FRAME_SIZES))
def test_frame_size_limits_are_the_encoders_own(codec, monkeypatch, capfd):
    """The smallest and largest frames of FRAME_SIZES open; one step beyond, the encoder itself refuses (the
    pre-check lifted), and its refusal becomes EncoderUnavailable's one line, nothing printed."""
    (min_w, min_h), (max_w, max_h) = FRAME_SIZES[codec]
    params = VideoParams(codec=codec)
    for width, height in ((min_w, min_h), (max_w, 64), (64, max_h)):
        assert size_problem(codec, width, height) is None
        VideoEncoder(width, height, 30.0, params)
    beyond = [(w, h) for w, h in ((min_w - 2, min_h), (min_w, min_h - 2), (max_w + 2, 64), (64, max_h + 2))
              if w > 0 and h > 0]
    for width, height in beyond:
        assert size_problem(codec, width, height) is not None
        with pytest.raises(EncoderUnavailable, match="encoder takes"):  # checked: the encoder is not opened
            VideoEncoder(width, height, 30.0, params)
    monkeypatch.setitem(FRAME_SIZES, codec, ((1, 1), (10**6, 10**6)))
    for width, height in beyond:
        with pytest.raises(EncoderUnavailable, match=f"the {codec} encoder .* could not be opened for "
                                                     f"{width}x{height} px frames: ") as caught:
            VideoEncoder(width, height, 30.0, params)
        assert "avcodec" not in str(caught.value) and "\n" not in str(caught.value)
    out, err = capfd.readouterr()
    assert not any(noise in out + err for noise in ENCODER_NOISE), out + err


def test_svt_refusal_is_captured_and_named(monkeypatch, capfd):
    """SVT-AV1's own error lines (written to fd 2 from C) become the reason; none reaches fd 2."""
    monkeypatch.setitem(FRAME_SIZES, "av1", ((2, 2), (16384, 8704)))
    with pytest.raises(EncoderUnavailable) as caught:
        VideoEncoder(2, 2, 30.0, VideoParams(codec="av1"))
    assert "Source Width must be at least 4" in str(caught.value)
    out, err = capfd.readouterr()
    assert "Svt[" not in err + out and "Error setting" not in err + out, err


def test_missing_codec_is_unavailable(monkeypatch, capfd):
    monkeypatch.setitem(video.CODECS, "av1", ("libno_such_encoder", {}))
    with pytest.raises(EncoderUnavailable, match="this FFmpeg build has no libno_such_encoder encoder"):
        VideoEncoder(64, 48, 30.0, VideoParams(codec="av1"))
    assert capfd.readouterr().err == ""


def test_output_capture_passes_other_lines_on(capfd):
    with video._encoder_output_captured() as printed:
        os.write(2, b"Svt[error]: Source Width must be at least 4\nsomething else\n")
    assert printed == ["Svt[error]: Source Width must be at least 4"]
    assert capfd.readouterr().err == "something else\n"


# ------------------------------------------------------------------------------------------
# contact-viz view on tiny sessions, through the real command line
# ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("width,height", [(1, 1), (2, 3), (3, 3), (4, 4), (5, 7)])
def test_view_tiny_session(tmp_path, width, height):
    session_dir = tmp_path / f"s{width}x{height}"
    write_tiny_session(session_dir, width, height)
    before = tree_digest(session_dir)
    out = tmp_path / "view.rrd"
    proc = view(session_dir, out)
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, text
    assert not any(noise in text for noise in ENCODER_NOISE), text
    size_lines = [line for line in text.splitlines() if "encoder takes" in line or "could not be opened" in line]
    small = too_small("av1", width, height)
    if small:
        assert len(size_lines) == 1, text
        line = size_lines[0]
        assert line.startswith(f"warning: {session_dir / 'left'} and {session_dir / 'right'}: {width}x{height} px "
                               "images"), line
        assert line.endswith("are smaller than the av1 encoder takes (at least 4x4 px); logged as JPEG images "
                             "instead"), line
    else:
        assert size_lines == [], text
    assert tree_digest(session_dir) == before  # the session is only read

    rec = Recording(out)
    frames = list(range(N_FRAMES))
    # the right image at 1/2 size (--right-step 2), unless that is too small for the codec and the full size is not
    half = (-(-width // 2), -(-height // 2))
    right_size = (width, height) if small or too_small("av1", *half) else half
    for side, entity, (w, h) in (("left", LEFT, (width, height)), ("right", RIGHT, right_size)):
        sources = [png_rgb(session_dir / side / f"{t:06d}.png") for t in frames]
        if small:
            assert rec.frames(entity, "EncodedImage:blob") == frames, side
            assert not rec.rows[(entity, "VideoStream:sample")]
            assert (entity, "VideoStream:codec") not in rec.static
            for t, value in rec.values(entity, "EncodedImage:blob").items():
                decoded = jpeg_rgb(value)
                assert decoded.shape == (height, width, 3)
                error = np.abs(decoded.astype(int) - sources[t].astype(int))
                assert error.mean() < 12 and error.max() < 32  # JPEG at quality 85 of per-pixel noise (+-40)
        else:
            assert rec.static[(entity, "VideoStream:codec")].as_py() == [rr.VideoCodec.AV1.value]
            assert rec.frames(entity, "VideoStream:sample") == frames, side
            assert not rec.rows[(entity, "EncodedImage:blob")]
            decoded = decode_logged_video(rec, entity)
            assert sorted(decoded) == frames
            assert decoded[0].shape == (*even_size(h, w), 3)
            if (w, h) == (width, height):
                for t in frames:  # AV1 at its default quality, a few random pixels: roughly the source
                    assert np.abs(decoded[t][:h, :w].astype(int) - sources[t].astype(int)).mean() < 12
    # the right camera says what the right image's size is
    assert pinhole_resolution(rec, rerun_log.ENTITY_RIGHT_CAMERA) == list(right_size)


@pytest.mark.parametrize("width,height", [(1, 1), (5, 7)])
def test_view_tiny_session_h264(tmp_path, width, height):
    """libx264 takes any even size from 2x2 px: no warning, a video stream, padded to even sizes."""
    session_dir = tmp_path / "s"
    write_tiny_session(session_dir, width, height)
    proc = view(session_dir, tmp_path / "view.rrd", "--video-codec", "h264")
    text = proc.stdout + proc.stderr
    assert proc.returncode == 0, text
    assert "warning" not in text and not any(noise in text for noise in ENCODER_NOISE), text
    rec = Recording(tmp_path / "view.rrd")
    for entity, step in ((LEFT, 1), (RIGHT, 2)):  # the right image at 1/2 size (--right-step 2)
        assert rec.frames(entity, "VideoStream:sample") == list(range(N_FRAMES))
        assert decode_logged_video(rec, entity)[0].shape == (*even_size(-(-height // step), -(-width // step)), 3)


# ------------------------------------------------------------------------------------------
# Any other failure to open the encoder: the same fallback (in process, the encoder swapped)
# ------------------------------------------------------------------------------------------


def run_in_process(session_dir: Path, out: Path, options: DebuggerOptions = DebuggerOptions()):
    session = open_session(session_dir)
    opened = open_recording(save=out, blueprint=rerun_log.default_blueprint())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        summary = run_debugger(session, opened.rec, options)
    opened.close()
    return summary, [str(w.message) for w in caught if issubclass(w.category, SessionWarning)], Recording(out)


def test_missing_codec_falls_back_to_jpeg(tmp_path, monkeypatch, capfd):
    width, height = 10, 8
    session_dir = tmp_path / "s"
    write_tiny_session(session_dir, width, height)
    monkeypatch.setitem(video.CODECS, "av1", ("libno_such_encoder", {}))
    summary, messages, rec = run_in_process(session_dir, tmp_path / "view.rrd")
    assert summary.frames == N_FRAMES and not summary.interrupted
    assert messages == [f"{session_dir / 'left'} and {session_dir / 'right'}: the av1 encoder (libno_such_encoder) "
                        "could not be opened for 10x8 and 6x4 px frames: this FFmpeg build has no libno_such_encoder "
                        "encoder; logged as JPEG images instead"], messages
    for entity, shape in ((LEFT, (height, width, 3)), (RIGHT, (height // 2, width // 2, 3))):
        assert rec.frames(entity, "EncodedImage:blob") == list(range(N_FRAMES))
        assert (entity, "VideoStream:codec") not in rec.static
        # the right image at 1/2 size (--right-step 2), as its camera says
        assert jpeg_rgb(rec.values(entity, "EncodedImage:blob")[0]).shape == shape
    assert pinhole_resolution(rec, rerun_log.ENTITY_RIGHT_CAMERA) == [width // 2, height // 2]
    out, err = capfd.readouterr()
    assert not any(noise in out + err for noise in ENCODER_NOISE), out + err


def test_refusal_past_the_size_check_falls_back_to_jpeg(tmp_path, monkeypatch, capfd):
    """A size the table lets through but SVT-AV1 refuses: one warning naming SVT's reason, nothing on fd 2."""
    session_dir = tmp_path / "s"
    write_tiny_session(session_dir, 2, 2)
    monkeypatch.setitem(FRAME_SIZES, "av1", ((2, 2), (16384, 8704)))
    summary, messages, rec = run_in_process(session_dir, tmp_path / "view.rrd")
    assert summary.frames == N_FRAMES
    assert len(messages) == 1, messages
    assert "could not be opened for 2x2 px frames: Source Width must be at least 4" in messages[0]
    assert messages[0].endswith("; logged as JPEG images instead")
    for entity in (LEFT, RIGHT):
        assert rec.frames(entity, "EncodedImage:blob") == list(range(N_FRAMES))
    out, err = capfd.readouterr()
    assert not any(noise in out + err for noise in ENCODER_NOISE), out + err


def test_jpeg_session_files_fall_back_at_half_size(tmp_path, monkeypatch):
    """JPEG session images (read reduced for the half-size right stream) fall back too: the left as its own file."""
    session_dir = tmp_path / "s"
    write_tiny_session(session_dir, 16, 12)
    for side in ("left", "right"):
        for png in sorted((session_dir / side).glob("*.png")):
            Image.open(png).save(png.with_suffix(".jpg"), quality=90)
            png.unlink()
    monkeypatch.setitem(video.CODECS, "av1", ("libno_such_encoder", {}))
    _, messages, rec = run_in_process(session_dir, tmp_path / "view.rrd")
    assert len(messages) == 1, messages
    left = rec.values(LEFT, "EncodedImage:blob")
    assert left[0].values[0].values.to_numpy(zero_copy_only=False).astype(np.uint8).tobytes() == \
        (session_dir / "left" / "000000.jpg").read_bytes()
    assert jpeg_rgb(rec.values(RIGHT, "EncodedImage:blob")[0]).shape == (6, 8, 3)


def test_video_streams_still_open_normally(tmp_path):
    """No fallback where the encoder takes the images: the size-16 session gets its two AV1 streams, no warning."""
    session_dir = tmp_path / "s"
    write_tiny_session(session_dir, 16, 12)
    summary, messages, rec = run_in_process(session_dir, tmp_path / "view.rrd")
    assert messages == []
    for entity, shape in ((LEFT, (12, 16, 3)), (RIGHT, (6, 8, 3))):
        assert rec.frames(entity, "VideoStream:sample") == list(range(N_FRAMES))
        assert decode_logged_video(rec, entity)[0].shape == shape
