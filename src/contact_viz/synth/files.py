"""Writing a synthetic session to disk (``generate_session``): images, masks, depth, force, truth."""

from __future__ import annotations

import io
import shutil
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
from PIL import Image

from contact_viz.io.atomic import atomic_write, reported_as, staging_path, sweep_stale
from contact_viz.io.jsonfile import write_json
from contact_viz.params import to_dict
from contact_viz.synth.camera import camera_record
from contact_viz.synth.motion import ToolTrack, tissue_displacement
from contact_viz.synth.params import SynthParams, STREAM_DEPTH, STREAM_LABELS, STREAM_TEXTURE, stream_rng
from contact_viz.synth.render import Renderer, tool_parts
from contact_viz.synth.scene import StereoCamera, stereo_camera, tissue_frame
from contact_viz.synth.second import plan_tracks
from contact_viz.synth.sensors import manual_labels, measured_force, scene_force, stereo_depth


def davis_palette() -> list[int]:
    """The DAVIS / PASCAL VOC palette (768 ints): index 0 black, 1 dark red (the tool), ..."""
    palette = []
    for index in range(256):
        r = g = b = 0
        c = index
        for bit in range(8):
            r |= ((c >> 0) & 1) << (7 - bit)
            g |= ((c >> 1) & 1) << (7 - bit)
            b |= ((c >> 2) & 1) << (7 - bit)
            c >>= 3
        palette += [r, g, b]
    return palette


_SESSION_FILES = ("session.json", "K.txt", "force.csv", "truth.csv", "labels.csv")
_SESSION_DIRS = ("left", "right", "masks", "depth")


def _check_target(out_dir: Path, overwrite: bool) -> None:
    """Refuse a file, or a non-empty directory unless ``overwrite``; changes nothing."""
    if out_dir.exists() and not out_dir.is_dir():
        raise FileExistsError(f"{out_dir}: expected a directory (or a new path), found a file")
    if out_dir.exists() and any(out_dir.iterdir()) and not overwrite:
        raise FileExistsError(
            f"{out_dir}: expected an empty or new directory; pass overwrite=True to replace a session there"
        )


def _install(work: Path, out_dir: Path) -> None:
    """Move the finished session from ``work`` to ``out_dir``, session.json last.

    A new or empty ``out_dir`` is replaced by a rename; in an existing one (overwrite) the previous
    session's own files are removed first and other files are left alone.
    """
    if out_dir.is_dir() and not any(out_dir.iterdir()):
        out_dir.rmdir()
    if not out_dir.exists():
        work.rename(out_dir)
        return
    for name in _SESSION_FILES:
        (out_dir / name).unlink(missing_ok=True)
    for name in _SESSION_DIRS:
        if (out_dir / name).is_dir():
            shutil.rmtree(out_dir / name)
    for entry in sorted(work.iterdir(), key=lambda e: e.name == "session.json"):
        entry.rename(out_dir / entry.name)
    work.rmdir()


def _write_frame(out_dir: Path, stem: str, views, depth: np.ndarray, jpeg_quality: int, palette: list[int]) -> None:
    """The frame's files, each encoded in memory and written with one ordinary write, so that a full disk
    is an OSError with its errno (cv2.imwrite says only False, np.save "N requested and M written")."""
    for name in ("left", "right"):
        path = out_dir / name / f"{stem}.jpg"
        ok, data = cv2.imencode(".jpg", views[name]["image"], [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
        if not ok:
            raise RuntimeError(f"{path}: OpenCV could not encode the JPEG image")
        path.write_bytes(data.tobytes())
    mask = Image.fromarray(views["left"]["tool_id"])
    mask.putpalette(palette)
    buffer = io.BytesIO()
    mask.save(buffer, format="PNG", compress_level=1)
    (out_dir / "masks" / f"{stem}.png").write_bytes(buffer.getvalue())
    buffer = io.BytesIO()
    np.save(buffer, depth.astype(np.float32))
    (out_dir / "depth" / f"{stem}.npy").write_bytes(buffer.getvalue())


def _as_tracks(tracks: ToolTrack | Sequence[ToolTrack]) -> tuple[ToolTrack, ...]:
    return (tracks,) if isinstance(tracks, ToolTrack) else tuple(tracks)


def sensor_streams(params: SynthParams,
                   tracks: ToolTrack | Sequence[ToolTrack]) -> tuple[np.ndarray, np.ndarray | None]:
    """What a session records beside its images: the force sensor's readings (F, 3), N (force.csv),
    and for the pulling task the manual labels (F,) 0/1 (labels.csv; None for palpation).

    ``tracks``: every instrument's track (``plan_tracks(params)``; one ToolTrack for one instrument).
    The force sensor reads the scene's total force, the labels mark contact of any instrument.
    """
    tracks = _as_tracks(tracks)
    force = measured_force(tracks, params)
    if params.task != "pulling":
        return force, None
    contact = np.logical_or.reduce([t.contact for t in tracks])
    return force, manual_labels(contact, params.label_jitter_frames, stream_rng(params, STREAM_LABELS))


def scene_truth(tracks: ToolTrack | Sequence[ToolTrack]) -> dict[str, np.ndarray]:
    """The truth of the scene per frame: ``gap_m`` the smallest gap of the instruments, ``indentation_m``
    the largest indentation, ``force_true_n`` the magnitude of the total contact force, ``contact``
    any instrument in contact, ``phase`` instrument 1's phase. (One track: its own values.)"""
    tracks = _as_tracks(tracks)
    return {
        "gap_m": np.min([t.gap_m for t in tracks], axis=0),
        "indentation_m": np.max([t.indentation_m for t in tracks], axis=0),
        "force_true_n": np.linalg.norm(scene_force(tracks), axis=1),
        "contact": np.logical_or.reduce([t.contact for t in tracks]),
        "phase": tracks[0].phase,
    }


def _write_tables(out_dir: Path, params: SynthParams, camera: StereoCamera, tracks: tuple[ToolTrack, ...]) -> None:
    with atomic_write(out_dir / "K.txt") as f:
        f.write(" ".join(f"{x:.10g}" for x in camera.K.ravel()) + "\n")
        f.write(f"{camera.baseline_m:.10g}\n")
    force, labels = sensor_streams(params, tracks)
    with atomic_write(out_dir / "force.csv") as f:
        f.write("frame,fx,fy,fz\n")
        for i, (fx, fy, fz) in enumerate(force):
            f.write(f"{i},{fx:.6f},{fy:.6f},{fz:.6f}\n")
    truth = scene_truth(tracks)
    per_tool = len(tracks) > 1
    with atomic_write(out_dir / "truth.csv") as f:
        header = "frame,timestamp,gap_m,indentation_m,force_true_n,contact,phase"
        if per_tool:
            header += "".join(f",gap_m_{k},contact_{k}" for k in range(1, len(tracks) + 1))
        f.write(header + "\n")
        for i in range(tracks[0].frames):
            row = (
                f"{i},{tracks[0].timestamp_s[i]:.6f},{truth['gap_m'][i]:.6f},{truth['indentation_m'][i]:.6f},"
                f"{truth['force_true_n'][i]:.6f},{int(truth['contact'][i])},{truth['phase'][i]}"
            )
            if per_tool:
                row += "".join(f",{t.gap_m[i]:.6f},{int(t.contact[i])}" for t in tracks)
            f.write(row + "\n")
    if labels is not None:
        with atomic_write(out_dir / "labels.csv") as f:
            f.write("frame,contact\n")
            for i, label in enumerate(labels):
                f.write(f"{i},{label}\n")


def generate_session(
    out_dir: str | Path,
    params: SynthParams = SynthParams(),
    *,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> Path:
    """Render a synthetic session into ``out_dir`` (created) and return its path.

    Writes session.json, K.txt (9 numbers of K row-major, then the baseline in m), left/ and
    right/ JPEGs, masks/ (palettized PNG, 1 = tool in the left view; with two instruments 1 and 2,
    the nearer one's id where they overlap), depth/ (float32 z-depth in m, 0 = hole, left view;
    every instrument and the tissue), force.csv (frame,fx,fy,fz in N; the scene's sensor: the total
    force of all instruments), truth.csv (frame,timestamp,gap_m,indentation_m,force_true_n,contact,
    phase: the scene's, see ``scene_truth``; with two instruments also gap_m_1,contact_1,gap_m_2,
    contact_2, each instrument's own) and, for the glove (pulling task), labels.csv (frame,contact).
    Frame stems are 000000, 000001, ... ``progress(done, total)``
    is called after each frame. Raises FileExistsError for a non-empty ``out_dir`` unless
    ``overwrite`` (then the session files there are replaced; other files are left alone).
    """
    if not isinstance(params, SynthParams):
        raise TypeError(f"params must be a SynthParams, got {type(params).__name__}")
    out_dir = Path(out_dir)
    _check_target(out_dir, overwrite)
    # Everything is written into a hidden sibling folder (.NAME.PID-NS.partial) and moved into place
    # when complete, so an interrupted run never leaves a partial session that reads like a whole one;
    # the folder of a run killed with SIGKILL is removed by the next run to the same place. An OSError
    # (a full disk, a read-only place) names out_dir, not the hidden folder.
    with reported_as(out_dir):
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        sweep_stale(out_dir)
        work = staging_path(out_dir, "partial")
        work.mkdir()
    try:
        with reported_as(out_dir, work):
            _render_session(work, out_dir.resolve().name, params, progress)
            _install(work, out_dir)
    except BaseException:
        shutil.rmtree(work, ignore_errors=True)
        raise
    return out_dir


def true_depth(params: SynthParams, indices: Sequence[int]) -> dict[int, np.ndarray]:
    """The exact left-view z-depth (H, W) float32 m, 0 = miss, of frames ``indices`` of the session
    ``params`` makes (re-rendered: depth/ holds the stereo-like depth, with noise, bled tool edges
    and holes). For measuring a depth source against the truth (recipes/sgbm_study.py)."""
    camera, frame = stereo_camera(params), tissue_frame(params)
    tracks = plan_tracks(params)
    renderer = Renderer(params, camera, frame, stream_rng(params, STREAM_TEXTURE))
    out = {}
    for i in indices:
        i = int(i)
        out[i] = renderer.render(*_frame_scene(renderer, tracks, i, params))["left"]["z"].astype(np.float32)
    return out


def _frame_scene(renderer: Renderer, tracks: tuple[ToolTrack, ...], i: int, params: SynthParams):
    """What ``Renderer.render`` needs for frame i: the tissue displacement (None: undeformed), the
    primitives of every instrument and the instrument id of each."""
    displacement = None
    for track in tracks:
        if track.press_m[i] > 0 or bool(np.any(track.pull_m[i])):
            moved = tissue_displacement(renderer.rest, track, i, params)
            displacement = moved if displacement is None else displacement + moved
    parts, ids = [], []
    for k, track in enumerate(tracks):
        own = tool_parts(track, i, params)
        parts += own
        ids += [k + 1] * len(own)
    return displacement, parts, ids


def _render_session(out_dir: Path, name: str, params: SynthParams,
                    progress: Callable[[int, int], None] | None) -> None:
    """Write the whole session into the (new, empty) folder ``out_dir``."""
    for sub in _SESSION_DIRS:
        (out_dir / sub).mkdir()
    camera, frame = stereo_camera(params), tissue_frame(params)
    tracks = plan_tracks(params)
    renderer = Renderer(params, camera, frame, stream_rng(params, STREAM_TEXTURE))
    palette = davis_palette()
    _write_tables(out_dir, params, camera, tracks)

    pending: list[Future] = []
    with ThreadPoolExecutor(max_workers=1) as writer:
        for i in range(params.frames):
            views = renderer.render(*_frame_scene(renderer, tracks, i, params))
            left = views["left"]
            depth = stereo_depth(
                left["z"], views["right"]["z"], left["tool"], left["specular"], camera, params,
                stream_rng(params, STREAM_DEPTH, i),
            )
            pending.append(writer.submit(_write_frame, out_dir, f"{i:06d}", views, depth, params.jpeg_quality, palette))
            while pending and pending[0].done():
                pending.pop(0).result()
            if len(pending) > 2:  # bound memory: wait for the writer
                pending.pop(0).result()
            if progress is not None:
                progress(i + 1, params.frames)
        for fut in pending:
            fut.result()

    write_json(out_dir / "session.json", session_description(name, params))


def session_description(name: str, params: SynthParams) -> dict:
    """session.json of the session ``params`` makes under the name ``name``: name, phantom, task, fps, the
    camera (``synth.camera.camera_record``: preset, fov_deg, fx_px, baseline_mm, working_distance_mm)
    and every generator option (``generator``: the SynthParams fields)."""
    return {
        "name": name,
        "phantom": params.phantom,
        "task": params.task,
        "fps": params.fps,
        "camera": camera_record(params, stereo_camera(params).fx),
        "generator": to_dict(params),
    }
