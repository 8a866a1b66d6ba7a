"""Check what a recording shows in the stock Rerun viewers at chosen frames: the web viewer in a real Chromium
(software WebGL) and the native `rerun FILE.rrd --renderer vulkan`, each on its own virtual X display (Xvfb).

Run by hand; it is not part of the test suite, which must not depend on a browser or on software rendering's
timing. It needs Debian's chromium and xvfb (`sudo apt-get install chromium xvfb`) and, for the native viewer,
Mesa's Vulkan rasteriser (`sudo apt-get install mesa-vulkan-drivers`); scripts/bootstrap.sh installs none of them.

    .venv/bin/python benchmarks/check_viewers.py [SESSION] [--web] [--native] [--out docs/] [--view-args "..."]
    .venv/bin/python benchmarks/check_viewers.py --rrd FILE.rrd --web --frames 10,35 --size 1280x720,1920x1080 --out DIR
    .venv/bin/python benchmarks/check_viewers.py SESSION --web --frames 35 --view-args "--start 28 --end 36"
    .venv/bin/python benchmarks/check_viewers.py --rrd FILE.rrd --web --frames 10,35 --out DIR2 --compare DIR
    .venv/bin/python benchmarks/check_viewers.py --check [--size 1280x720,1920x1080] [--out DIR] [--data DIR] [--rrd FILE]

- Without ``--rrd`` it renders SESSION (default: a synthetic session, 640x360, 40 frames, one instrument): the
  web check runs `contact-viz SESSION --serve` (the recording streamed live over gRPC) and opens the URL it
  prints; the native check saves the recording with --save and opens the file. ``--view-args``: more options of
  `contact-viz SESSION`.
- ``--rrd FILE`` checks a finished recording as it is: the web check serves the file over HTTP on loopback, next
  to the stock web viewer of the installed rerun-sdk (`rerun.serve_web_viewer`, in a child process), and opens
  `http://127.0.0.1:PORT/?url=<the file's URL>`; the native check opens the file. Either way the viewer shows the
  recording with its own default blueprint.
- ``--frames 10,35``: for each frame the viewer's time cursor is put on that frame of the `frame` timeline,
  paused, and the screen is saved once the viewer has finished loading and drawing, as
  ``{web,native}_{W}x{H}_frame{NNNN}.png`` in ``--out`` (default results/check_viewers/). Without ``--frames``:
  one screenshot once the viewer has settled where it stops by itself (a file plays to its last frame and stops,
  `--serve` follows the last frame); without ``--frames`` and ``--rrd`` it is saved as before, as
  docs/screenshot_web_viewer.png and docs/screenshot_native_viewer.png (``--out``).
- ``--size 1280x720`` (repeatable or comma-separated; default 1600x900): the X display and the browser's page
  (or the native window) size; each size gets a fresh Xvfb and a fresh browser or viewer.
- ``--timeout`` (default 240 s) per screenshot; ``--compare DIR``: how much each screenshot differs from the
  same-named one in DIR (an earlier run), per pane.

``--check`` proves what a recording shows, the way a user sees it, in the web viewer, and exits 0 only if every
assertion holds (one line each: ok or FAIL, the measured figure and its threshold). It makes its own data, in a
temporary directory (``--data DIR``: there, kept, and reused once complete): a 640x360 session of 60 frames with two
instruments (CHECK_SESSION: instrument 2 presses at frames 15-23, instrument 1 at 41-57), copied with a mask failure
injected at frames 20-24 (CHECK_FAULT, `contact_viz.synth.faults.inject_fault`: mask_on_tissue fires on 20-22 and
24), and a model fitted on three one-instrument cup sessions (CHECK_TRAINING); records it (`contact-viz S2 --model
model.json --save`; ``--rrd FILE``: checks FILE instead, which must be a recording of that same session); and shows,
paused and fully drawn, at each ``--size`` (default 1280x720 and 1920x1080; screenshots in ``--out``, default
results/check_viewers/check/) three frames: (a) the first clean frame after the flagged ones (those where `contact-viz
check` fires a check with an evidence picture), (b) a flagged frame, (c) a frame where, by truth.csv and the masks,
both instruments are in view and one is in contact, away from the failure. It asserts:

- (a) no evidence overlay: the mean colour saturation (saturation) of the left image, where image_rect says the view
  draws it, within SATURATION_CLOSE of that of the frame's own file (left/<stem>.jpg); and the image is that file: the
  median pixel difference from the file (image_difference) at most IMAGE_DIFF_MAX (so is (c)'s: no stale layer);
- (b) the evidence is drawn: a flagged frame's left image (the grey still with the stereo residual in colour, at 0.7
  opacity) at most EVIDENCE_DIM times as saturated as (a)'s (measured: half);
- (c) each instrument's colour (`instrument_style(k).window`) in the left image pane (its patch box), the distance,
  signal and evidence panes (its lines), and the ground truth's yellow in the contact plot: colour_share within COLOUR_TOL
  at least MIN_SHARE of the pane (a third or so of the least share measured at both sizes; more than a legend's dot).

It takes about 2 minutes (measured 122 s: the data 17 s, 2 s reused; each size about 50 s). The assertions fail
where they must: `--rrd` of the same session recorded by the code before the viewer's stale-evidence and colour
fixes (commit a009908) gives "2 of 11 assertions hold" at 1280x720: the evidence of frame 24 stays on the clean
frame 25 (saturation 0.16 of its file's, median difference 52) and on frame 49 (54), instrument 1 is missing from
the distance and signal panes and instrument 2 from the left pane (drawn in other colours), the truth from the
contact pane (measured before the evidence plot was added, whose two assertions per size such a recording also
fails: it has no evidence plot); the current code: 26 of 26 at both sizes.

Setting the time. A `#when=frame@35` fragment (Rerun's link to a time) is ignored by the 0.41 web viewer: on a
served .rrd (`?url=http://.../s.rrd#when=frame@35`, or the fragment inside the `url=` value) the viewer plays
from frame 0 and stops at the last frame; on `contact-viz --serve` (`?url=rerun+http://.../proxy#when=...`) it
follows the last frame. A blueprint's `TimePanel(play_state="paused")` pauses wherever the cursor is when the
blueprint arrives (a few frames in), and `time_selection` only selects a range. What works, in both cases, is the
Viewer Control API (rerun/v1alpha1/viewer_control.proto): the stock page keeps the viewer's `WebHandle` in
`window._handle`, whose `viewer_control(bytes)` takes an encoded `ViewerControlRequest`. This script drives
Chromium over the DevTools protocol (`--remote-debugging-pipe`: no extra package), sends `set_time_cursor
{store_id, timeline "frame", time N, play_state PAUSED}` and reads the cursor, play state and what is still
loading back from `window._handle.viewer_state()`; the native viewer takes the same request over gRPC
(`rerun.experimental.ViewerClient.set_time`). The screenshot's time panel shows `#N` and a paused play button.

It seeks once the recording has arrived whole (paused earlier, the time series' x axes can keep the range of
the frames loaded so far). "Finished loading and drawing": the cursor is on the frame and paused, SETTLED_SHOTS
consecutive screenshots SHOT_INTERVAL_S apart are the same (at most SETTLED_CHANGED of the pixels differ: the
viewer's loading animation over a video still being decoded keeps it waiting), and the left image pane shows a
camera image (shows_image: at least MIN_COLOURS distinct colours and a standard deviation of
at least MIN_STD, which the viewer's own flat panels and text do not reach). CHECK_VIEWERS_SETTLE_S (seconds,
default 0) waits longer before the saved screenshot.

It prints, per screenshot, the viewer's state and the seconds from asking for the frame to the saved screenshot;
then, per size, the pane rectangles measured on the screenshot (measure_panes; paste them into PANES_BY_SIZE
when the layout changes) and how much the left image differs between the frames.

Time, on this 2-core machine without a GPU (shared with other work), for a 40-frame 640x360 recording: the
browser and viewer start in 3-10 s; the first frame at a size, loading the recording included, is settled after
15-25 s at 1280x720 and 30-70 s at 1920x1080, each further frame after 7-25 s (the native viewer: 7-10 s);
2 frames at 1280x720 and 1920x1080 take 1.5-2.5 minutes; the default run (a synthetic session, web and native)
about 1.5 minutes.

For other scripts, pure functions over (H, W, 3) uint8 RGB screenshots and rectangles given as fractions of the
window (x0, y0, x1, y1): crop, pane_body, inset, colour_share, image_stats, shows_image, region_difference,
changed_share, pane_drawn, measure_panes, saturation, image_rect, image_difference, and --check's
evidence_assertions and colour_assertions; and to take screenshots, screenshot_frames, or web_viewer_for_rrd /
web_viewer / native_viewer (context managers) and their .show(frame):

    sys.path.insert(0, "benchmarks"); import check_viewers as cv
    shots = cv.screenshot_frames(Path("s.rrd"), frames=[10, 35], sizes=[(1280, 720)], out=Path("/tmp/shots"))
    left = cv.crop(shots[0].image, cv.pane_body(shots[0].panes["left"], 720))
    cv.shows_image(left), cv.colour_share(left, (230, 159, 0), tol=30)  # an image; share of orange pixels

Every process it starts (Xvfb, Chromium, the web viewer server, contact-viz, rerun) is stopped when it ends,
also on an error, Ctrl-C, SIGTERM or SIGHUP. Exit status 0 when every check (with --check: every assertion) passed,
1 when one failed, 130 when interrupted, 2 for bad arguments.
"""
from __future__ import annotations

import argparse
import contextlib
import functools
import json
import os
import re
import select
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from http.server import SimpleHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import quote

import numpy as np

Rect = tuple[float, float, float, float]  # (x0, y0, x1, y1) as fractions of the window's width and height

SCREEN = (1600, 900)  # default virtual display and browser window size, px
TIMELINE = "frame"  # the recording's sequence timeline (contact_viz.viz.entities.TIMELINE_FRAME)
MIN_COLOURS = 3000  # distinct colours in the image pane when a video frame is drawn
MIN_STD = 12.0  # standard deviation of the image pane's pixel values when a frame is drawn
TITLE_PX = 28  # height of a view's title bar in the viewer (px at any window size, pixels_per_point 1)
SHOT_INTERVAL_S = 2.0  # between the screenshots compared to tell that the viewer has settled, s
SETTLED_CHANGED = 2e-5  # at most this share of the window's pixels may differ between two settled screenshots
SETTLED_SHOTS = 3  # this many consecutive screenshots, SHOT_INTERVAL_S apart, that do not differ: settled
SETTLED_THRESHOLD = 8  # a pixel differs when a channel differs by more than this (0-255)
SETTLE_S = float(os.environ.get("CHECK_VIEWERS_SETTLE_S", "0"))  # extra wait once settled, before the saved shot, s
POINTER_AT = (300, 8)  # where the X pointer is put (px): on the viewer's top bar, away from views and buttons
TIMEOUT_S = 240.0  # default: give up on one screenshot after this long (software rendering on 2 cores is slow), s
PLAY_STATE = {0: "unspecified", 1: "paused", 2: "playing", 3: "following"}  # rerun.viewer_control PlayState

# The panes of the default blueprint (contact_viz.viz.blueprint.default_blueprint), in the order measure_panes
# finds them (depth first: left to right, then top to bottom, as the blueprint nests its containers), by count.
PANE_NAMES: dict[int, tuple[str, ...]] = {
    # images (left | right over depth) over the 3D scene; distance, signal, force, contact, diagnostics (tabs)
    9: ("left", "right", "depth", "3d", "distance", "signal", "force", "contact", "diagnostics"),
    # the same with a text pane ("contact": which instrument is in contact) beside the 3D scene
    10: ("left", "right", "depth", "3d", "contact_text", "distance", "signal", "force", "contact", "diagnostics"),
    # with a model: the evidence for contact (each instrument's log-likelihood ratio) beneath the contact plot
    11: ("left", "right", "depth", "3d", "contact_text", "distance", "signal", "force", "contact", "evidence",
         "diagnostics"),
}
# Where the default blueprint puts its panes (each with its title bar), as fractions of the viewer window,
# measured by measure_panes on the web viewer in Chromium (this script prints them after each run; update them
# from there when the layout changes). They depend a little on the window size, as the viewer's top bar (36 px),
# time panel (30 px) and title bars (28 px) do not scale. PANES_BY_SIZE: the layout of blueprint.py with a model
# (11 panes: the contact text pane beside the 3D scene, the evidence plot beneath the contact plot; without a
# model there is no evidence plot, and measure_panes finds that layout on the screenshot); PANES_BEFORE_BY_SIZE:
# an earlier one (9 panes), which older recordings carry.
PANES_BY_SIZE: dict[tuple[int, int], dict[str, Rect]] = {
    (1280, 720): {
        "left": (0.0, 0.05, 0.3992, 0.5042), "right": (0.4, 0.05, 0.5992, 0.2764),
        "depth": (0.4, 0.2778, 0.5992, 0.5042), "3d": (0.0, 0.5056, 0.4492, 0.9597),
        "contact_text": (0.45, 0.5056, 0.5992, 0.9597), "distance": (0.6, 0.05, 1.0, 0.2306),
        "signal": (0.6, 0.2319, 1.0, 0.3681), "force": (0.6, 0.3694, 1.0, 0.4889),
        "contact": (0.6, 0.4903, 1.0, 0.6556), "evidence": (0.6, 0.6569, 1.0, 0.7778),
        "diagnostics": (0.6, 0.7792, 1.0, 0.9597),
    },
    (1920, 1080): {
        "left": (0.0, 0.0333, 0.3995, 0.5028), "right": (0.4, 0.0333, 0.5995, 0.2676),
        "depth": (0.4, 0.2685, 0.5995, 0.5028), "3d": (0.0, 0.5037, 0.4495, 0.9731),
        "contact_text": (0.45, 0.5037, 0.5995, 0.9731), "distance": (0.6, 0.0333, 1.0, 0.2204),
        "signal": (0.6, 0.2213, 1.0, 0.362), "force": (0.6, 0.363, 1.0, 0.487),
        "contact": (0.6, 0.488, 1.0, 0.6593), "evidence": (0.6, 0.6602, 1.0, 0.7852),
        "diagnostics": (0.6, 0.7861, 1.0, 0.9731),
    },
}
PANES_BEFORE_BY_SIZE: dict[tuple[int, int], dict[str, Rect]] = {
    (1280, 720): {
        "left": (0.0, 0.05, 0.3992, 0.4764), "right": (0.4, 0.05, 0.5992, 0.2625),
        "depth": (0.4, 0.2639, 0.5992, 0.4764), "3d": (0.0, 0.4778, 0.5992, 0.9597),
        "distance": (0.6, 0.05, 1.0, 0.2236), "signal": (0.6, 0.225, 1.0, 0.3819),
        "force": (0.6, 0.3833, 1.0, 0.5917), "contact": (0.6, 0.5931, 1.0, 0.7847),
        "diagnostics": (0.6, 0.7861, 1.0, 0.9597),
    },
    (1920, 1080): {
        "left": (0.0, 0.0333, 0.3995, 0.475), "right": (0.4, 0.0333, 0.5995, 0.2537),
        "depth": (0.4, 0.2546, 0.5995, 0.475), "3d": (0.0, 0.4759, 0.5995, 0.9731),
        "distance": (0.6, 0.0333, 1.0, 0.213), "signal": (0.6, 0.2139, 1.0, 0.3759),
        "force": (0.6, 0.3769, 1.0, 0.5935), "contact": (0.6, 0.5944, 1.0, 0.7926),
        "diagnostics": (0.6, 0.7935, 1.0, 0.9731),
    },
}
DEFAULT_PANES: dict[str, Rect] = PANES_BY_SIZE[(1920, 1080)]
# the part of the left image pane that the image fills (under the title bar, inside the letterboxing): used by
# pane_drawn to tell that a video frame is drawn
LEFT_PANE: Rect = (0.03, 0.10, 0.37, 0.46)


# ---------------------------------------------------------------------------------------------------------------
# Pixel assertions: pure functions over (H, W, 3) uint8 RGB screenshots


def to_pixels(rect: Rect, size: tuple[int, int]) -> tuple[int, int, int, int]:
    """A rectangle in fractions of a (width, height) window as pixel bounds (x0, y0, x1, y1), x1/y1 exclusive."""
    width, height = size
    x0, y0, x1, y1 = rect
    px0, py0 = int(round(x0 * width)), int(round(y0 * height))
    return px0, py0, max(px0 + 1, int(round(x1 * width))), max(py0 + 1, int(round(y1 * height)))


def crop(shot: np.ndarray, rect: Rect | None) -> np.ndarray:
    """The part of a screenshot inside ``rect`` (fractions of its width and height; None: all of it)."""
    if rect is None:
        return shot
    height, width = shot.shape[:2]
    x0, y0, x1, y1 = to_pixels(rect, (width, height))
    return shot[y0:y1, x0:x1]


def pane_body(rect: Rect, height_px: int, title_px: int = TITLE_PX) -> Rect:
    """A pane's rectangle without its title bar (``title_px`` pixels high in a window ``height_px`` high)."""
    x0, y0, x1, y1 = rect
    return x0, min(y1, y0 + title_px / height_px), x1, y1


def inset(rect: Rect, fraction: float) -> Rect:
    """``rect`` shrunk on every side by ``fraction`` of its own width and height."""
    x0, y0, x1, y1 = rect
    dx, dy = (x1 - x0) * fraction, (y1 - y0) * fraction
    return x0 + dx, y0 + dy, x1 - dx, y1 - dy


def colour_share(region: np.ndarray, rgb: Sequence[int], tol: int = 24) -> float:
    """Share (0-1) of the region's pixels within ``tol`` of ``rgb`` in every channel (Chebyshev distance)."""
    pixels = region.reshape(-1, 3).astype(np.int16)
    if not len(pixels):
        return 0.0
    close = np.abs(pixels - np.asarray(rgb, dtype=np.int16)).max(axis=1) <= tol
    return float(close.mean())


def image_stats(region: np.ndarray) -> tuple[int, float]:
    """(distinct colours, standard deviation of the pixel values) of a region."""
    pixels = region.reshape(-1, 3)
    if not len(pixels):
        return 0, 0.0
    codes = pixels.astype(np.int32) @ np.array([65536, 256, 1], dtype=np.int32)
    return int(len(np.unique(codes))), float(pixels.std())


def shows_image(region: np.ndarray, min_colours: int = MIN_COLOURS, min_std: float = MIN_STD) -> bool:
    """Whether a region shows a camera image: many distinct colours, spread out (the viewer's own UI, flat panels
    and anti-aliased text, has a few hundred colours). For a small region ``min_colours`` is capped at a tenth of
    its pixels."""
    colours, std = image_stats(region)
    pixels = region.shape[0] * region.shape[1]
    return colours >= min(min_colours, pixels // 10) and std >= min_std


def region_difference(a: np.ndarray, b: np.ndarray, rect: Rect | None = None) -> float:
    """Mean absolute difference (0-255, over pixels and channels) of two screenshots of the same size in ``rect``."""
    if a.shape != b.shape:
        raise ValueError(f"screenshots of different sizes: {a.shape} and {b.shape}")
    return float(np.abs(crop(a, rect).astype(np.int16) - crop(b, rect).astype(np.int16)).mean())


def changed_share(a: np.ndarray, b: np.ndarray, rect: Rect | None = None, threshold: int = SETTLED_THRESHOLD) -> float:
    """Share (0-1) of the pixels in ``rect`` where two screenshots differ by more than ``threshold`` in a channel."""
    if a.shape != b.shape:
        raise ValueError(f"screenshots of different sizes: {a.shape} and {b.shape}")
    diff = np.abs(crop(a, rect).astype(np.int16) - crop(b, rect).astype(np.int16)).max(axis=2)
    return float((diff > threshold).mean()) if diff.size else 0.0


def pane_drawn(shot: np.ndarray, rect: Rect = LEFT_PANE) -> tuple[bool, int, float]:
    """Whether the (left image) pane of the screenshot shows an image: (drawn, distinct colours, std)."""
    region = crop(shot, rect)
    colours, std = image_stats(region)
    return shows_image(region), colours, std


def separator_colour(shot: np.ndarray) -> tuple[int, int, int] | None:
    """The colour of the 1-px lines the viewer draws between its panels: the first row from the top that is one
    colour across the window and differs from the rows above and below (the line under the top bar)."""
    height = shot.shape[0]

    def dominant(y: int) -> tuple[tuple[int, int, int], float]:
        values, counts = np.unique(shot[y].astype(np.int32) @ np.array([65536, 256, 1]), return_counts=True)
        code = int(values[np.argmax(counts)])
        return (code >> 16, (code >> 8) & 255, code & 255), float(counts.max() / shot.shape[1])

    for y in range(1, min(height - 1, 120)):
        colour, share = dominant(y)
        if share >= 0.9 and dominant(y - 1)[0] != colour and dominant(y + 1)[0] != colour:
            return colour
    return None


def _bands(flags: np.ndarray, min_size: int) -> list[tuple[int, int]]:
    """The runs of False in ``flags`` (separator lines are True) that are at least ``min_size`` long."""
    segments, start = [], None
    for i, flag in enumerate(list(flags) + [True]):
        if not flag and start is None:
            start = i
        elif flag and start is not None:
            if i - start >= min_size:
                segments.append((start, i))
            start = None
    return segments


def _xy_cut(lines: np.ndarray, box: tuple[int, int, int, int], full: float, min_size: int,
            out: list[tuple[int, int, int, int]]) -> None:
    x0, y0, x1, y1 = box
    sub = lines[y0:y1, x0:x1]
    columns = _bands(sub.mean(axis=0) >= full, min_size)
    if len(columns) > 1:
        for a, b in columns:
            _xy_cut(lines, (x0 + a, y0, x0 + b, y1), full, min_size, out)
        return
    rows = _bands(sub.mean(axis=1) >= full, min_size)
    if len(rows) > 1:
        for a, b in rows:
            _xy_cut(lines, (x0, y0 + a, x1, y0 + b), full, min_size, out)
        return
    out.append(box)


def measure_panes(shot: np.ndarray, names: Sequence[str] | None = None, tol: int = 2,
                  min_size: int = 20) -> dict[str, Rect]:
    """The viewer's panes in a screenshot, as fractions of the window, found from the 1-px separator lines.

    Cuts the window recursively at lines that span a whole box (as the blueprint nests horizontal and vertical
    containers), drops the top bar and the time panel (boxes under 60 px high at the top or bottom edge), and
    names the panes in the order found (left to right, then top to bottom, depth first): ``names``, or
    PANE_NAMES for that many panes, else pane1, pane2, ... Each rectangle includes the pane's title bar.
    """
    height, width = shot.shape[:2]
    colour = separator_colour(shot)
    if colour is None:
        return {}
    lines = np.abs(shot.astype(np.int16) - np.asarray(colour, dtype=np.int16)).max(axis=2) <= tol
    boxes: list[tuple[int, int, int, int]] = []
    _xy_cut(lines, (0, 0, width, height), 0.97, min_size, boxes)
    panes = [b for b in boxes if not ((b[1] == 0 or b[3] == height) and b[3] - b[1] < 60)]
    if names is None or len(names) != len(panes):
        names = PANE_NAMES.get(len(panes), tuple(f"pane{i + 1}" for i in range(len(panes))))
    return {name: (round(x0 / width, 4), round(y0 / height, 4), round(x1 / width, 4), round(y1 / height, 4))
            for name, (x0, y0, x1, y1) in zip(names, panes)}


def default_panes(size: tuple[int, int], before: bool = False) -> dict[str, Rect]:
    """The measured pane rectangles for this window size, or those of the nearest measured height (``before``:
    of the 9-pane layout of older recordings)."""
    table = PANES_BEFORE_BY_SIZE if before else PANES_BY_SIZE
    return table.get(size) or table[min(table, key=lambda s: abs(s[1] - size[1]))]


def left_image_rect(panes: dict[str, Rect], size: tuple[int, int]) -> Rect:
    """Where the left image is, inside its pane (under the title bar, away from the edges), for pane_drawn."""
    rect = panes.get("left") or next(iter(panes.values()), None)
    if rect is None:
        return LEFT_PANE
    return inset(pane_body(rect, size[1]), 0.06)


# ---------------------------------------------------------------------------------------------------------------
# Processes, servers, the X display


def exited(proc: subprocess.Popen) -> bool:
    """Whether a child process has exited, without reaping it: its id (and its process group's) stays ours."""
    if proc.returncode is not None:
        return True
    try:
        return os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None
    except ChildProcessError:
        return True


def stop(proc: subprocess.Popen | None, timeout: float = 15.0) -> None:
    """Stop a process started with start_new_session=True and every process of its group: SIGTERM, then SIGKILL
    for what is left (e.g. Chromium's helpers), before the leader is reaped (so the group id is still ours)."""
    if proc is None or proc.returncode is not None:
        return
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGTERM)
    deadline = time.monotonic() + timeout
    while not exited(proc) and time.monotonic() < deadline:
        time.sleep(0.1)
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    deadline = time.monotonic() + 5  # until the group's other members are gone too (signal 0 only asks)
    with contextlib.suppress(ProcessLookupError, PermissionError):
        while time.monotonic() < deadline:
            os.killpg(proc.pid, 0)
            time.sleep(0.05)


@contextlib.contextmanager
def started(args: list[str], **kwargs) -> Iterator[subprocess.Popen]:
    """A process in its own session (so Ctrl-C in a terminal reaches only this script), stopped on exit."""
    proc = subprocess.Popen(args, start_new_session=True, **kwargs)
    try:
        yield proc
    finally:
        stop(proc)


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for_port(port: int, proc: subprocess.Popen | None, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc is not None and exited(proc):
            raise RuntimeError(f"{proc.args[0]} exited before listening on port {port}")
        with socket.socket() as sock:
            if sock.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise TimeoutError(f"nothing listens on port {port} after {timeout:.0f} s")


def free_display() -> int:
    for number in range(90, 200):
        if not Path(f"/tmp/.X11-unix/X{number}").exists() and not Path(f"/tmp/.X{number}-lock").exists():
            return number
    raise RuntimeError("no free X display number between :90 and :199")


@contextlib.contextmanager
def xvfb(size: tuple[int, int]) -> Iterator[int]:
    """A virtual X display of ``size`` (24-bit), its number.

    Without the Composite extension: with it Xvfb offers a 32-bit ARGB visual, the native viewer asks for a
    transparent window, and its Vulkan (lavapipe) frames never reach the screen (the window stays black).
    """
    if shutil.which("Xvfb") is None:
        raise RuntimeError("Xvfb is not installed (Debian: apt-get install xvfb)")
    display = free_display()
    with started(["Xvfb", f":{display}", "-screen", "0", f"{size[0]}x{size[1]}x24", "-nolisten", "tcp", "-noreset",
                  "-extension", "COMPOSITE"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) as proc:
        deadline = time.monotonic() + 20
        while not Path(f"/tmp/.X11-unix/X{display}").exists():
            if exited(proc) or time.monotonic() > deadline:
                raise RuntimeError(f"Xvfb :{display} did not start")
            time.sleep(0.1)
        time.sleep(0.5)
        # the pointer on the viewer's top bar, right of its menu and badges, where hovering shows nothing
        park_pointer(display, min(POINTER_AT[0], size[0] - 1), POINTER_AT[1])
        yield display


def park_pointer(display: int, x: int, y: int) -> None:
    """Move the X pointer to (x, y) (libX11's XWarpPointer), away from the views: under the screen's centre a
    viewer shows hover tooltips over whatever pane is there."""
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("X11")
    if name is None:
        return
    x11 = ctypes.CDLL(name)
    x11.XOpenDisplay.restype = ctypes.c_void_p
    x11.XOpenDisplay.argtypes = [ctypes.c_char_p]
    x11.XDefaultRootWindow.restype = ctypes.c_ulong
    x11.XDefaultRootWindow.argtypes = [ctypes.c_void_p]
    x11.XWarpPointer.argtypes = [ctypes.c_void_p, ctypes.c_ulong, ctypes.c_ulong, ctypes.c_int, ctypes.c_int,
                                 ctypes.c_uint, ctypes.c_uint, ctypes.c_int, ctypes.c_int]
    x11.XFlush.argtypes = x11.XCloseDisplay.argtypes = [ctypes.c_void_p]
    connection = x11.XOpenDisplay(f":{display}".encode())
    if not connection:
        return
    try:
        x11.XWarpPointer(connection, 0, x11.XDefaultRootWindow(connection), 0, 0, 0, 0, x, y)
        x11.XFlush(connection)
    finally:
        x11.XCloseDisplay(connection)


def grab(display: int) -> np.ndarray:
    """Screenshot of the whole X display as (H, W, 3) uint8 RGB (Pillow's X11 grab)."""
    from PIL import ImageGrab

    return np.asarray(ImageGrab.grab(xdisplay=f":{display}").convert("RGB"))


def save_png(image: np.ndarray, path: Path) -> None:
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp")
    Image.fromarray(image).save(tmp, format="PNG")
    os.replace(tmp, path)


class _CorsHandler(SimpleHTTPRequestHandler):
    """Static files, readable by the web viewer's page on another port (CORS), without a request log."""

    def end_headers(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Cache-Control", "no-store")
        super().end_headers()

    def log_message(self, format: str, *args) -> None:  # noqa: A002 (the base class's name)
        pass


class _QuietServer(ThreadingHTTPServer):
    daemon_threads = True

    def handle_error(self, request, client_address) -> None:
        if not isinstance(sys.exc_info()[1], (ConnectionError, TimeoutError)):  # (a closed browser: nothing to say)
            super().handle_error(request, client_address)


@contextlib.contextmanager
def serve_file(path: Path) -> Iterator[str]:
    """Serve one file over HTTP on loopback (in a thread of this process); its URL."""
    path = path.resolve()
    if not path.is_file():
        raise FileNotFoundError(f"no such recording: {path}")
    with tempfile.TemporaryDirectory(prefix="check-viewers-http-") as tmp:
        name = re.sub(r"[^A-Za-z0-9._-]", "_", path.name)
        (Path(tmp) / name).symlink_to(path)
        server = _QuietServer(("127.0.0.1", 0), functools.partial(_CorsHandler, directory=tmp))
        thread = threading.Thread(target=server.serve_forever, name="check-viewers-http", daemon=True)
        thread.start()
        try:
            yield f"http://127.0.0.1:{server.server_address[1]}/{name}"
        finally:
            server.shutdown()
            server.server_close()


@contextlib.contextmanager
def web_viewer_server() -> Iterator[str]:
    """The stock web viewer of the installed rerun-sdk (rerun.serve_web_viewer) in a child process; its base URL."""
    port = free_port()
    code = ("import sys, time, rerun as rr\n"
            "rr.serve_web_viewer(web_port=int(sys.argv[1]), open_browser=False)\n"
            "while True: time.sleep(3600)\n")
    with started([sys.executable, "-c", code, str(port)], stdout=subprocess.DEVNULL,
                 stderr=subprocess.DEVNULL) as proc:
        wait_for_port(port, proc)
        yield f"http://127.0.0.1:{port}/"


# ---------------------------------------------------------------------------------------------------------------
# Chromium over the DevTools protocol (--remote-debugging-pipe: JSON messages ended by NUL on fds 3 and 4)


class DevTools:
    """A minimal Chrome DevTools protocol client over Chromium's --remote-debugging-pipe."""

    def __init__(self, read_fd: int, write_fd: int) -> None:
        self._read_fd, self._write_fd = read_fd, write_fd
        self._buffer = b""
        self._next_id = 0
        self.session: str | None = None

    def close(self) -> None:
        for fd in (self._read_fd, self._write_fd):
            with contextlib.suppress(OSError):
                os.close(fd)

    def _message(self, deadline: float) -> dict:
        while b"\0" not in self._buffer:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise TimeoutError("no answer from Chromium's DevTools")
            ready, _, _ = select.select([self._read_fd], [], [], remaining)
            if ready:
                chunk = os.read(self._read_fd, 1 << 16)
                if not chunk:
                    raise ConnectionError("Chromium closed its DevTools pipe (it exited)")
                self._buffer += chunk
        message, self._buffer = self._buffer.split(b"\0", 1)
        return json.loads(message)

    def call(self, method: str, params: dict | None = None, *, browser: bool = False, timeout: float = 60.0) -> dict:
        self._next_id += 1
        request = {"id": self._next_id, "method": method, "params": params or {}}
        if not browser and self.session is not None:
            request["sessionId"] = self.session
        os.write(self._write_fd, json.dumps(request).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            message = self._message(deadline)
            if message.get("id") == self._next_id:  # (events, without an id, are ignored)
                if "error" in message:
                    raise RuntimeError(f"DevTools {method}: {message['error']}")
                return message.get("result", {})

    def attach(self, url_prefix: str, timeout: float = 30.0) -> None:
        """Attach to the page whose URL starts with ``url_prefix``."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            pages = [t for t in self.call("Target.getTargets", browser=True)["targetInfos"]
                     if t["type"] == "page" and t["url"].startswith(url_prefix)]
            if pages:
                self.session = self.call("Target.attachToTarget", {"targetId": pages[0]["targetId"], "flatten": True},
                                         browser=True)["sessionId"]
                return
            time.sleep(0.2)
        raise TimeoutError(f"Chromium shows no page at {url_prefix}")

    def evaluate(self, expression: str, *, await_promise: bool = False, timeout: float = 60.0):
        result = self.call("Runtime.evaluate", {"expression": expression, "awaitPromise": await_promise,
                                                "returnByValue": True}, timeout=timeout)
        if "exceptionDetails" in result:
            details = result["exceptionDetails"]
            raise RuntimeError(details.get("exception", {}).get("description") or details.get("text"))
        return result.get("result", {}).get("value")


def chromium_path() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        raise RuntimeError("chromium is not installed (Debian: apt-get install chromium)")
    return path


@contextlib.contextmanager
def chromium(url: str, size: tuple[int, int], display: int, profile: Path) -> Iterator[DevTools]:
    """Chromium showing ``url`` alone in a ``size`` window at the top left of the X display, with DevTools."""
    to_chrome_r, to_chrome_w = os.pipe()
    from_chrome_r, from_chrome_w = os.pipe()
    args = [chromium_path(), "--no-sandbox", "--test-type",  # (--test-type: no "unsupported flag" infobar)
            "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
            "--disable-background-networking", "--disable-component-update", "--no-first-run",
            "--disable-background-timer-throttling", "--disable-renderer-backgrounding",
            "--disable-backgrounding-occluded-windows", f"--user-data-dir={profile}",
            # (one pixel larger than the screen: see web_viewer)
            f"--window-size={size[0] + 1},{size[1] + 1}", "--window-position=0,0", "--remote-debugging-pipe",
            "--app=" + url]
    # fds 3 and 4 of the browser are its DevTools pipe: a small Python puts them there and execs the browser (no
    # preexec_fn: this process runs threads); through fds >= 10 first, as the pipe's own fds may be 3 or 4
    placer = ("import fcntl, os, sys\n"
              "high = [fcntl.fcntl(int(fd), fcntl.F_DUPFD, 10) for fd in sys.argv[1:3]]\n"
              "for fd in sys.argv[1:3]: os.close(int(fd))\n"
              "for target, fd in zip((3, 4), high): os.dup2(fd, target); os.close(fd)\n"
              "os.execv(sys.argv[3], sys.argv[3:])\n")
    env = dict(os.environ, DISPLAY=f":{display}")
    env.pop("WAYLAND_DISPLAY", None)
    try:
        with started([sys.executable, "-I", "-c", placer, str(to_chrome_r), str(from_chrome_w), *args],
                     pass_fds=(to_chrome_r, from_chrome_w), env=env,
                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL):
            os.close(to_chrome_r)
            os.close(from_chrome_w)
            to_chrome_r = from_chrome_w = -1
            devtools = DevTools(from_chrome_r, to_chrome_w)
            try:
                yield devtools
            finally:
                devtools.close()
                from_chrome_r = to_chrome_w = -1
    finally:
        for fd in (to_chrome_r, to_chrome_w, from_chrome_r, from_chrome_w):
            if fd >= 0:
                with contextlib.suppress(OSError):
                    os.close(fd)


# ---------------------------------------------------------------------------------------------------------------
# The Viewer Control API, encoded by hand (protobuf wire format; rerun/v1alpha1/viewer_control.proto of 0.41)


def _pb_varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def _pb_field(number: int, value: int | str | bytes) -> bytes:
    if isinstance(value, int):
        return _pb_varint(number << 3) + _pb_varint(value)
    data = value.encode() if isinstance(value, str) else value
    return _pb_varint(number << 3 | 2) + _pb_varint(len(data)) + data


def _pb_parse(data: bytes) -> list[tuple[int, int | bytes]]:
    """(field number, value) of a protobuf message: varints as int, length-delimited as bytes."""
    fields, i = [], 0

    def varint(i: int) -> tuple[int, int]:
        shift = value = 0
        while True:
            byte = data[i]
            i += 1
            value |= (byte & 0x7F) << shift
            shift += 7
            if not byte & 0x80:
                return value, i

    while i < len(data):
        key, i = varint(i)
        number, wire = key >> 3, key & 7
        if wire == 0:
            value, i = varint(i)
        elif wire == 2:
            length, i = varint(i)
            value, i = data[i:i + length], i + length
        elif wire == 1:
            value, i = data[i:i + 8], i + 8
        elif wire == 5:
            value, i = data[i:i + 4], i + 4
        else:
            raise ValueError(f"unsupported protobuf wire type {wire}")
        fields.append((number, value))
    return fields


def _pb_first(data: bytes, number: int, default=None):
    return next((value for n, value in _pb_parse(data) if n == number), default)


def set_time_cursor_request(store_id: str | None, timeline: str, time_value: int, paused: bool = True) -> bytes:
    """ViewerControlRequest{set_time_cursor (6): {store_id (1), timeline (2): {name (1)}, time (3): {time (1)},
    play_state (5): PAUSED (1) / PLAYING (2)}}."""
    body = (_pb_field(1, store_id) if store_id else b"") + _pb_field(2, _pb_field(1, timeline)) + \
        _pb_field(3, _pb_field(1, time_value)) + _pb_field(5, 1 if paused else 2)
    return _pb_field(6, body)


@dataclass
class ViewerState:
    """What the viewer reports (GetViewerStateResponse): its first recording's cursor, play state and timelines."""

    store_id: str | None = None
    timeline: str | None = None  # the timeline the cursor is on
    time: int | None = None  # the cursor's time on it (a frame index on `frame`)
    play_state: str = "unspecified"  # paused, playing, following
    timelines: dict[str, tuple[int, int]] = field(default_factory=dict)  # name -> (first, last) time
    loading: list[str] = field(default_factory=list)  # sources still loading
    version: str | None = None

    def describe(self) -> str:
        where = f"{self.timeline}={self.time}" if self.timeline else "no cursor"
        frames = self.timelines.get(TIMELINE)
        return (f"{where}, {self.play_state}" + (f", {TIMELINE} {frames[0]}-{frames[1]}" if frames else "")
                + (f", loading {', '.join(self.loading)}" if self.loading else ""))


def parse_viewer_state(data: bytes) -> ViewerState:
    """A GetViewerStateResponse (url 1, active_store_id 2, recordings 3 {store_id 1, timelines 2 {timeline 1
    {name 1}, time_type 2, time_range 3 {start 1, end 2}}, current_time 3 {timeline 1 {name 1}, time 3 {time 1}},
    location 4, play_state 5}, catalog_url 4, views 5, viewer_version 6, loading 7 {name 1, status 2})."""
    state = ViewerState()
    active = _pb_first(data, 2)
    recordings = [value for number, value in _pb_parse(data) if number == 3]
    for number, value in _pb_parse(data):
        if number == 6:
            state.version = value.decode()
        elif number == 7:
            state.loading.append((_pb_first(value, 1) or b"").decode())
    chosen = next((r for r in recordings if active and _pb_first(r, 1) == active), recordings[0] if recordings else None)
    if chosen is None:
        return state
    for number, value in _pb_parse(chosen):
        if number == 1:
            state.store_id = value.decode()
        elif number == 2:
            name = (_pb_first(_pb_first(value, 1, b""), 1) or b"").decode()
            time_range = _pb_first(value, 3)
            if time_range is not None:
                state.timelines[name] = (_signed(_pb_first(time_range, 1, 0)), _signed(_pb_first(time_range, 2, 0)))
        elif number == 3:
            state.timeline = (_pb_first(_pb_first(value, 1, b""), 1) or b"").decode() or None
            cursor = _pb_first(value, 3)
            state.time = None if cursor is None else _signed(_pb_first(cursor, 1, 0))
        elif number == 5:
            state.play_state = PLAY_STATE.get(value, str(value))
    return state


def _signed(value: int) -> int:
    return value - (1 << 64) if value >= 1 << 63 else value


# ---------------------------------------------------------------------------------------------------------------
# A viewer to drive: the web viewer in Chromium (DevTools) or the native one (gRPC)


@dataclass
class Shot:
    """One screenshot of a viewer: what it shows and how long it took."""

    viewer: str  # "web" or "native"
    size: tuple[int, int]
    frame: int | None  # None: wherever the viewer stopped by itself
    image: np.ndarray
    state: ViewerState
    seconds: float  # from asking for the frame (or from opening the viewer) to the settled screenshot
    path: Path | None = None
    panes: dict[str, Rect] = field(default_factory=dict)  # measured on this screenshot


class Viewer:
    """A running viewer on an X display: its state, the time cursor, screenshots."""

    name = "viewer"

    def __init__(self, display: int, size: tuple[int, int], alive: Callable[[], bool]) -> None:
        self.display, self.size, self._alive = display, size, alive

    def state(self) -> ViewerState:
        raise NotImplementedError

    def set_frame(self, frame: int, store_id: str | None, timeline: str) -> None:
        raise NotImplementedError

    def grab(self) -> np.ndarray:
        return grab(self.display)

    def wait_recording(self, timeline: str, timeout: float) -> ViewerState:
        """Wait until the recording has data on ``timeline``."""
        deadline = time.monotonic() + timeout
        while True:
            self._check_alive()
            with contextlib.suppress(Exception):
                state = self.state()
                if timeline in state.timelines:
                    return state
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.name}: no recording with a {timeline!r} timeline after {timeout:.0f} s")
            time.sleep(0.5)

    def _check_alive(self) -> None:
        if not self._alive():
            raise RuntimeError(f"{self.name}: the viewer exited")

    def show(self, frame: int | None, timeline: str = TIMELINE, timeout: float = TIMEOUT_S,
             log: Callable[[str], None] = print) -> Shot:
        """Put the cursor on ``frame`` (paused; None: leave the viewer be), wait until the viewer has finished loading
        and drawing, and return the screenshot. Raises TimeoutError (with the last screenshot in ``.shot``)."""
        started_at = time.monotonic()
        deadline = started_at + timeout
        state = self.wait_recording(timeline, timeout)
        # seek once everything has arrived (nothing listed as loading, and for a stream, which is not listed, the
        # timeline's range unchanged for 2 s): paused while the recording still loads, the time series' x axes can
        # keep the range of the frames loaded so far (seen once at 1920x1080: #0-#29 of #0-#39)
        unchanged_since, last_range = time.monotonic(), state.timelines.get(timeline)
        while frame is not None and (state.loading or time.monotonic() - unchanged_since < 2.0):
            if time.monotonic() > deadline:
                raise TimeoutError(f"{self.name}: still loading after {timeout:.0f} s ({state.describe()})")
            time.sleep(0.5)
            self._check_alive()
            state = self.state()
            if state.loading or state.timelines.get(timeline) != last_range:
                unchanged_since, last_range = time.monotonic(), state.timelines.get(timeline)
        if frame is not None:
            first, last = state.timelines[timeline]
            if not first <= frame <= last:
                raise ValueError(f"frame {frame} is not in the recording ({timeline} {first}-{last})")
            self.set_frame(frame, state.store_id, timeline)
        shot = self.grab()
        still = 1  # consecutive screenshots without a change
        rect = left_image_rect(default_panes(self.size), self.size)
        while True:
            time.sleep(SHOT_INTERVAL_S)
            self._check_alive()
            state = self.state()
            if frame is not None and (state.timeline != timeline or state.time != frame
                                      or state.play_state != "paused"):
                log(f"  {self.name}: the cursor moved ({state.describe()}); back to {timeline}={frame}, paused")
                self.set_frame(frame, state.store_id, timeline)
                still = 0
                continue
            previous, shot = shot, self.grab()
            if previous.shape == shot.shape:
                panes = measure_panes(shot)
                if "left" in panes:
                    rect = left_image_rect(panes, self.size)
                changed = changed_share(previous, shot)
                still = still + 1 if changed <= SETTLED_CHANGED else 1
                drawn, colours, std = pane_drawn(shot, rect)
                elapsed = time.monotonic() - started_at
                if not state.loading and still >= SETTLED_SHOTS and drawn and (
                        frame is not None or state.play_state != "playing"):
                    if SETTLE_S > 0:
                        time.sleep(SETTLE_S)
                        shot = self.grab()
                    state = self.state()  # (still there after the screenshot?)
                    if frame is not None and (state.time != frame or state.play_state != "paused"):
                        continue
                    return Shot(self.name, self.size, frame, shot, state, time.monotonic() - started_at,
                                panes=measure_panes(shot))
                log(f"  {self.name} {self.size[0]}x{self.size[1]} {frame_label(frame)}: {elapsed:.0f} s, "
                    f"{state.describe()}; {changed:.2%} of the window changed, left image {colours} colours, "
                    f"std {std:.1f}")
            if time.monotonic() > deadline:
                error = TimeoutError(f"{self.name}: {frame_label(frame)} not settled within {timeout:.0f} s "
                                     f"({state.describe()})")
                error.shot = Shot(self.name, self.size, frame, shot, state, time.monotonic() - started_at)
                raise error


class WebViewer(Viewer):
    """The web viewer's page in Chromium, driven through window._handle (the viewer's WebHandle)."""

    name = "web"

    def __init__(self, devtools: DevTools, display: int, size: tuple[int, int], alive: Callable[[], bool]) -> None:
        super().__init__(display, size, alive)
        self.devtools = devtools

    def wait_ready(self, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not self.devtools.evaluate("typeof window._handle === 'object' && window._handle !== null"):
            self._check_alive()
            if time.monotonic() > deadline:
                raise TimeoutError(f"web: the viewer did not start within {timeout:.0f} s")
            time.sleep(0.5)

    def viewport(self) -> tuple[int, int]:
        return tuple(self.devtools.evaluate("[window.innerWidth, window.innerHeight]"))

    def state(self) -> ViewerState:
        return parse_viewer_state(bytes(self.devtools.evaluate("Array.from(window._handle.viewer_state())")))

    def control(self, request: bytes, timeout: float = 60.0) -> bytes:
        """One ViewerControlRequest; the encoded ViewerControlResponse (answered at the viewer's next frame)."""
        expression = (f"window._handle.viewer_control(new Uint8Array({list(request)}))"
                      ".then(response => Array.from(response))")
        return bytes(self.devtools.evaluate(expression, await_promise=True, timeout=timeout))

    def set_frame(self, frame: int, store_id: str | None, timeline: str) -> None:
        response = _pb_first(self.control(set_time_cursor_request(store_id, timeline, frame)), 6, b"")
        moved_to = _pb_first(_pb_first(response, 4, b""), 1)
        if moved_to != frame:
            raise RuntimeError(f"web: set_time_cursor to {timeline}={frame} answered time {moved_to}")


class NativeViewer(Viewer):
    """The native viewer, driven over gRPC with rerun.experimental.ViewerClient."""

    name = "native"

    def __init__(self, url: str, display: int, size: tuple[int, int], alive: Callable[[], bool]) -> None:
        super().__init__(display, size, alive)
        from rerun.experimental import ViewerClient

        deadline = time.monotonic() + 60
        while True:  # (the viewer listens a moment before its gRPC service answers)
            try:
                self.client = ViewerClient(url)
                self.client.get_state()
                break
            except (ConnectionError, RuntimeError):
                self._check_alive()
                if time.monotonic() > deadline:
                    raise
                time.sleep(1)

    def state(self) -> ViewerState:
        # the GetViewerState answer as protobuf JSON: ViewerClient.get_state() leaves out the play state
        raw = self.client._viewer_control("get_state", {})
        state = ViewerState(version=raw.get("viewer_version"),
                            loading=[source.get("name", "") for source in raw.get("loading", [])])
        recordings = raw.get("recordings", [])
        recording = next((r for r in recordings if r.get("store_id") == raw.get("active_store_id")),
                         recordings[0] if recordings else None)
        if recording is not None:
            state.store_id = recording.get("store_id")
            cursor = recording.get("current_time") or {}
            state.timeline = cursor.get("timeline", {}).get("name")
            state.time = int(cursor["time"].get("time", 0)) if "time" in cursor else None
            state.timelines = {t["timeline"]["name"]: (int(t["time_range"].get("start", 0)),
                                                       int(t["time_range"].get("end", 0)))
                               for t in recording.get("timelines", []) if "time_range" in t}
            state.play_state = recording.get("play_state", "PLAY_STATE_UNSPECIFIED").replace("PLAY_STATE_", "").lower()
        return state

    def set_frame(self, frame: int, store_id: str | None, timeline: str) -> None:
        self.client.set_time(timeline, sequence=frame, play_state="paused", recording=store_id)


# ---------------------------------------------------------------------------------------------------------------
# Opening a recording


@contextlib.contextmanager
def web_viewer(url: str, size: tuple[int, int], timeout: float = TIMEOUT_S) -> Iterator[WebViewer]:
    """The web viewer page ``url`` in Chromium on its own Xvfb of ``size``; stopped on exit."""
    with contextlib.ExitStack() as stack:
        display = stack.enter_context(xvfb(size))
        profile = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="check-viewers-chromium-")))
        devtools = stack.enter_context(chromium(url, size, display, profile))
        devtools.attach(url.split("?")[0])
        # the page exactly size: Chromium makes a window as large as the screen one pixel smaller, so the window is
        # one pixel larger than the screen (its last row and column off screen) and the page's viewport set to size
        devtools.call("Emulation.setDeviceMetricsOverride", {"width": size[0], "height": size[1],
                                                             "deviceScaleFactor": 1, "mobile": False})
        browser_exited = [False]

        def alive() -> bool:
            if browser_exited[0]:
                return False
            try:
                devtools.call("Browser.getVersion", browser=True, timeout=30)
                return True
            except (ConnectionError, OSError, TimeoutError):
                browser_exited[0] = True
                return False

        viewer = WebViewer(devtools, display, size, alive)
        viewer.wait_ready(timeout)
        inner = viewer.viewport()
        if tuple(inner) != tuple(size):
            print(f"  web: the page is {inner[0]}x{inner[1]} in a {size[0]}x{size[1]} window")
        yield viewer


@contextlib.contextmanager
def web_viewer_for_rrd(rrd: Path, size: tuple[int, int], timeout: float = TIMEOUT_S) -> Iterator[WebViewer]:
    """A finished .rrd file in the stock web viewer: the file served over HTTP, opened with ?url=."""
    with web_viewer_server() as base, serve_file(rrd) as rrd_url:
        with web_viewer(f"{base}?url={quote(rrd_url, safe='')}", size, timeout) as viewer:
            yield viewer


@contextlib.contextmanager
def native_viewer(rrd: Path, size: tuple[int, int], timeout: float = TIMEOUT_S) -> Iterator[NativeViewer]:
    """The native viewer (`rerun FILE --renderer vulkan`) on its own Xvfb of ``size``; stopped on exit."""
    rerun = Path(sys.executable).with_name("rerun")
    port = free_port()
    with xvfb(size) as display:
        env = dict(os.environ, DISPLAY=f":{display}")
        env.pop("WAYLAND_DISPLAY", None)
        with tempfile.TemporaryDirectory(prefix="check-viewers-native-") as runtime:
            env["XDG_RUNTIME_DIR"] = runtime
            with started([str(rerun) if rerun.exists() else "rerun", str(rrd), "--renderer", "vulkan", "--port",
                          str(port), "--window-size", f"{size[0]}x{size[1]}"], env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) as proc:
                wait_for_port(port, proc, timeout=timeout)
                yield NativeViewer(f"rerun+http://127.0.0.1:{port}/proxy", display, size,
                                   lambda: not exited(proc))


def frame_label(frame: int | None) -> str:
    return f"frame {frame}" if frame is not None else "where it stopped"


def shot_name(viewer: str, size: tuple[int, int], frame: int | None) -> str:
    return f"{viewer}_{size[0]}x{size[1]}_" + (f"frame{frame:04d}.png" if frame is not None else "settled.png")


def take_shots(viewer: Viewer, frames: Sequence[int | None], out: Path | None, timeout: float,
               names: Callable[[int | None], str] | None = None) -> tuple[list[Shot], list[str]]:
    """Screenshots of ``frames`` in an open viewer, saved in ``out``; (shots, failures)."""
    shots, failures = [], []
    for frame in frames:
        name = (names or (lambda f: shot_name(viewer.name, viewer.size, f)))(frame)
        try:
            shot = viewer.show(frame, timeout=timeout)
        except (TimeoutError, ValueError, RuntimeError, ConnectionError) as error:
            failures.append(f"{viewer.name} {viewer.size[0]}x{viewer.size[1]} {frame_label(frame)}: {error}")
            print(f"{viewer.name}: FAILED: {error}")
            failed = getattr(error, "shot", None)
            if failed is not None and out is not None:
                save_png(failed.image, out / ("FAILED_" + name))
                print(f"  last screenshot: {out / ('FAILED_' + name)}")
            continue
        if out is not None:
            shot.path = out / name
            save_png(shot.image, shot.path)
        drawn, colours, std = pane_drawn(shot.image, left_image_rect(shot.panes or default_panes(shot.size), shot.size))
        print(f"{viewer.name} {viewer.size[0]}x{viewer.size[1]} {frame_label(frame)}: {shot.state.describe()}; settled in "
              f"{shot.seconds:.1f} s; left image {colours} colours, std {std:.1f}; {shot.path or '(not saved)'}",
              flush=True)
        shots.append(shot)
    return shots, failures


def screenshot_frames(rrd: Path, frames: Sequence[int | None], sizes: Sequence[tuple[int, int]] = (SCREEN,),
                      out: Path | None = None, viewer: str = "web", timeout: float = TIMEOUT_S) -> list[Shot]:
    """Screenshots of a finished recording at ``frames`` (paused there, fully drawn) at each window size, saved in
    ``out`` as {viewer}_{W}x{H}_frame{NNNN}.png. Raises RuntimeError if any frame failed."""
    shots, failures = [], []
    for size in sizes:
        opened = web_viewer_for_rrd(rrd, size, timeout) if viewer == "web" else native_viewer(rrd, size, timeout)
        with opened as running:
            got, failed = take_shots(running, frames, out, timeout)
        shots += got
        failures += failed
    if failures:
        raise RuntimeError("; ".join(failures))
    return shots


# ---------------------------------------------------------------------------------------------------------------
# --check: what a recording shows, asserted on screenshots of the web viewer

CHECK_SIZES = ((1280, 720), (1920, 1080))  # --check's default window sizes
# the check's session: two instruments, both in view on most frames (instrument 2 presses at 15-23, instrument 1 at
# 41-57), and the model: fitted on three one-instrument cup sessions
CHECK_SESSION = ("--tools", "2", "--frames", "60", "--size", "640x360", "--seed", "7")
CHECK_TRAINING = tuple(("--phantom", "cup", "--seed", str(seed), "--frames", "90", "--size", "320x180")
                       for seed in (1, 2, 3))
# the mask failure injected (kind, frames, severity, seed): instrument 1's mask bleeds onto the tissue, and
# mask_on_tissue fires on frames 20-22 and 24, so those frames show the evidence picture
CHECK_FAULT = ("mask_bleed", tuple(range(20, 25)), 12.0, 1)
CHECK_DATA_TIMEOUT_S = 900.0  # making the session and the model (about 1 minute), recording it (10 s), s
IMAGE_MARGIN = 0.03  # the left image's border left out of its measurements (the viewer's edges), share of its size
SATURATION_CLOSE = 0.15  # (a): the left image's mean saturation within this share of its file's (measured 1-4 %)
EVIDENCE_DIM = 0.75  # (b): a flagged frame's left image at most this times (a)'s saturation (measured 0.50)
IMAGE_DIFF_MAX = 8.0  # (a), (c): median |screen - file| of the left image at most this, 0-255 (measured 2)
COLOUR_TOL = 30  # tolerance of colour_share for the instrument and truth colours (anti-aliased edges), 0-255
# (c): the least share of a pane's pixels (under its title bar) in an instrument's colour (left image: its patch
# box; distance, signal and evidence: its line) and in the truth's yellow (contact plot): about a third of the least measured
# at 1280x720 and 1920x1080, and above what a legend's colour dot alone covers
MIN_SHARE = {"left": 0.00006, "distance": 0.003, "signal": 0.004, "evidence": 0.003, "contact": 0.006}
MIN_IN_VIEW = 0.005  # (c): an instrument is in view when its mask covers at least this share of the image


@dataclass
class Assertion:
    """One assertion on the screenshots: what it says, the measured figure against its threshold, the outcome."""

    what: str
    figure: str
    passed: bool

    def line(self, size: tuple[int, int]) -> str:
        return f"{'ok  ' if self.passed else 'FAIL'} {size[0]}x{size[1]} {self.what}: {self.figure}"


def saturation(region: np.ndarray) -> float:
    """Mean colour saturation (HSV's S, 0-1) of a region's pixels: 0 for greys, 1 for pure hues."""
    pixels = region.reshape(-1, 3).astype(np.float32)
    if not len(pixels):
        return 0.0
    top = pixels.max(axis=1)
    spread = top - pixels.min(axis=1)
    return float(np.divide(spread, top, out=np.zeros_like(top), where=top > 0).mean())


def image_rect(pane: Rect, size: tuple[int, int], image_wh: tuple[int, int], margin: float = 0.0) -> Rect:
    """Where a 2D view draws an image ``image_wh`` (width, height) px in ``pane`` (its title bar included) of a
    ``size`` window: as large as fits under the title bar, centred; shrunk by ``margin`` of its size on each side."""
    x0, y0, x1, y1 = pane_body(pane, size[1])
    scale = min((x1 - x0) * size[0] / image_wh[0], (y1 - y0) * size[1] / image_wh[1])
    half_w, half_h = image_wh[0] * scale / size[0] / 2, image_wh[1] * scale / size[1] / 2
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    return inset((cx - half_w, cy - half_h, cx + half_w, cy + half_h), margin)


def image_difference(region: np.ndarray, image: np.ndarray) -> float:
    """Median over the pixels of the largest channel difference (0-255) between a region of a screenshot and an
    image resized to it: small where the region shows that image (video coding and scaling leave a few levels),
    and not moved by overlays on a minority of the pixels."""
    from PIL import Image

    resized = np.asarray(Image.fromarray(image).resize((region.shape[1], region.shape[0]), Image.BILINEAR))
    return float(np.median(np.abs(region.astype(np.int16) - resized.astype(np.int16)).max(axis=2)))


def clean_frame_after(flagged: Sequence[int], injected: Sequence[int], n_frames: int) -> int:
    """The first frame after the last flagged one that is neither flagged nor injected."""
    excluded = set(flagged) | set(injected)
    frame = max(flagged) + 1
    while frame in excluded:
        frame += 1
    if frame >= n_frames:
        raise ValueError(f"no clean frame after the flagged frames {list(flagged)} ({n_frames} frames)")
    return frame


def contact_frame(contact: np.ndarray, in_view: np.ndarray, excluded: Sequence[int]) -> int:
    """A frame where every instrument is in view and exactly one is in contact (``contact``, ``in_view``: (frames,
    instruments) bool), not in ``excluded``: the middle of the longest run of such frames."""
    good = in_view.all(axis=1) & (contact.sum(axis=1) == 1)
    good[[f for f in excluded if 0 <= f < len(good)]] = False
    runs = _bands(~good, 1)
    if not runs:
        raise ValueError("no frame with every instrument in view and one in contact")
    start, end = max(runs, key=lambda run: run[1] - run[0])
    return (start + end - 1) // 2


def evidence_assertions(shots: dict[str, np.ndarray], frames: dict[str, int], files: dict[str, np.ndarray],
                        panes: dict[str, Rect], size: tuple[int, int]) -> list[Assertion]:
    """(a) the clean frame's left image is its file's, without the evidence overlay; (b) the flagged frame's is
    the evidence (a grey still at 0.7 opacity: much less saturated); (c) the frame in contact's is its file's too.
    ``shots``, ``frames``, ``files``: the screenshot, frame and left image file of "a", "b" and "c"."""
    height, width = files["a"].shape[:2]
    inner = image_rect(panes["left"], size, (width, height), IMAGE_MARGIN)
    whole = image_rect(panes["left"], size, (width, height))
    s_a, s_b = saturation(crop(shots["a"], inner)), saturation(crop(shots["b"], inner))
    s_file = saturation(crop(files["a"], inset((0.0, 0.0, 1.0, 1.0), IMAGE_MARGIN)))
    ratio = s_a / s_file if s_file else float("inf")
    difference = {key: image_difference(crop(shots[key], whole), files[key]) for key in ("a", "c")}
    return [
        Assertion(f"(a) frame {frames['a']}: left image as saturated as its file (no evidence)",
                  f"saturation {s_a:.3f} vs the file's {s_file:.3f}: ratio {ratio:.2f}, allowed 1 +- {SATURATION_CLOSE}",
                  abs(ratio - 1) <= SATURATION_CLOSE),
        Assertion(f"(b) frame {frames['b']}: the evidence greys the left image",
                  f"saturation {s_b:.3f} = {s_b / s_a if s_a else float('inf'):.2f} x (a)'s, at most {EVIDENCE_DIM}",
                  s_b <= EVIDENCE_DIM * s_a),
    ] + [Assertion(f"({key}) frame {frames[key]}: left image is its file (no stale overlay)",
                   f"median difference {difference[key]:.1f} (0-255), at most {IMAGE_DIFF_MAX:g}",
                   difference[key] <= IMAGE_DIFF_MAX) for key in ("a", "c")]


def colour_assertions(shot: np.ndarray, frame: int, colours: Sequence[tuple[str, Sequence[int], Sequence[str]]],
                      panes: dict[str, Rect], size: tuple[int, int]) -> list[Assertion]:
    """(c) each colour (name, RGB, the panes it must be in) covers at least MIN_SHARE of each of its panes."""
    out = []
    for name, rgb, where in colours:
        for pane in where:
            if pane not in panes:  # a recording without that plot (the evidence plot of an older recording)
                out.append(Assertion(f"(c) frame {frame}: {name} in the {pane} pane", "no such pane", False))
                continue
            share = colour_share(crop(shot, pane_body(panes[pane], size[1])), rgb, COLOUR_TOL)
            out.append(Assertion(f"(c) frame {frame}: {name} in the {pane} pane",
                                 f"share {share:.5f}, at least {MIN_SHARE[pane]:g} (tolerance {COLOUR_TOL})",
                                 share >= MIN_SHARE[pane]))
    return out


def expected_colours(n_tools: int) -> list[tuple[str, tuple[int, ...], tuple[str, ...]]]:
    """The colours (c) looks for: each instrument's (its patch box in the left image, its distance and signal
    lines, with the model --check records with its evidence line) and the ground truth's yellow (the contact plot),
    from contact_viz.viz.style."""
    from contact_viz.viz.style import SERIES_STYLES, instrument_style

    colours = [(f"instrument {k} ({instrument_style(k).colour_name})", instrument_style(k).window[:3],
                ("left", "distance", "signal", "evidence")) for k in range(1, n_tools + 1)]
    return colours + [("truth (yellow)", SERIES_STYLES["contact_truth"].rgba[:3], ("contact",))]


def run_commands(commands: Sequence[list[str]], env: dict, log: Path, timeout: float, parallel: int = 2) -> None:
    """Run ``commands``, at most ``parallel`` at once, each in its own process group (stopped on an error or
    Ctrl-C), their output appended to ``log``; RuntimeError naming the first that failed."""
    pending, running = list(commands), []
    deadline = time.monotonic() + timeout
    with contextlib.ExitStack() as stack, log.open("ab") as output:
        while pending or running:
            while pending and len(running) < parallel:
                command = pending.pop(0)
                running.append(stack.enter_context(started(command, env=env, stdout=output, stderr=output)))
            time.sleep(0.2)
            for proc in [p for p in running if p.poll() is not None]:
                running.remove(proc)
                if proc.returncode != 0:
                    raise RuntimeError(f"exit status {proc.returncode}: {' '.join(proc.args)} (output in {log})")
            if time.monotonic() > deadline:
                raise TimeoutError(f"not done after {timeout:.0f} s: {' '.join(running[0].args)}")


def make_check_data(root: Path, env: dict) -> tuple[Path, Path]:
    """The check's session, with CHECK_FAULT injected (root/S2), and model (root/model.json): made under ``root``,
    or reused when an earlier run completed them there."""
    session, model, done = root / "S2", root / "model.json", root / "complete"
    if done.exists() and session.is_dir() and model.is_file():
        return session, model
    for name in ("S", "S2", "T1", "T2", "T3", "model.json"):
        path = root / name
        shutil.rmtree(path) if path.is_dir() else path.unlink(missing_ok=True)
    root.mkdir(parents=True, exist_ok=True)
    log = root / "commands.log"
    run_commands([contact_viz() + ["synth", str(root / "S"), *CHECK_SESSION]]
                 + [contact_viz() + ["synth", str(root / f"T{i}"), *options]
                    for i, options in enumerate(CHECK_TRAINING, 1)], env, log, CHECK_DATA_TIMEOUT_S)
    from contact_viz.synth.faults import inject_fault

    kind, frames, severity, seed = CHECK_FAULT
    inject_fault(root / "S", session, kind, frames, severity=severity, seed=seed)
    run_commands([contact_viz() + ["fit", *(str(root / f"T{i}") for i in (1, 2, 3)), "-o", str(model)]], env, log,
                 CHECK_DATA_TIMEOUT_S)
    done.write_text("made by benchmarks/check_viewers.py --check\n")
    return session, model


def evidence_frames(session: Path, env: dict, log: Path) -> list[int]:
    """The frames where a check with an evidence picture fires (`contact-viz check SESSION --json`)."""
    from contact_viz.viz.rerun_log import EVIDENCE_CHECKS

    report_path = log.with_name("checks.json")
    run_commands([contact_viz() + ["check", str(session), "--json", str(report_path)]], env, log,
                 CHECK_DATA_TIMEOUT_S)
    checks = json.loads(report_path.read_text())["sessions"][0]["checks"]
    return sorted({frame for code in EVIDENCE_CHECKS for start, end in checks.get(code, {}).get("ranges", [])
                   for frame in range(start, end + 1)})


def session_truth(session: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The session's frame stems, and per frame and instrument whether it is in contact (truth.csv's contact_k)
    and in view (its mask covers MIN_IN_VIEW of the image): (stems, contact, in_view)."""
    import csv

    from PIL import Image

    stems = sorted((p.stem for p in (session / "left").iterdir() if not p.name.startswith(".")), key=int)
    with (session / "truth.csv").open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    tools = sorted(int(name.split("_")[1]) for name in rows[0] if re.fullmatch(r"contact_\d+", name))
    contact = np.array([[row[f"contact_{k}"] == "1" for k in tools] for row in rows], dtype=bool)
    in_view = np.zeros_like(contact)
    for i, stem in enumerate(stems):
        mask = np.asarray(Image.open(session / "masks" / f"{stem}.png"))
        in_view[i] = [(mask == k).mean() >= MIN_IN_VIEW for k in tools]
    return stems, contact, in_view


def left_file(session: Path, stem: str) -> np.ndarray:
    from PIL import Image

    path = next(p for p in (session / "left").iterdir() if p.stem == stem and not p.name.startswith("."))
    return np.asarray(Image.open(path).convert("RGB"))


def run_check(rrd: Path | None, sizes: Sequence[tuple[int, int]], out: Path, timeout: float,
              data: Path | None) -> int:
    """--check: make the session and model, record it (or take ``rrd``), screenshot the three frames at each
    size, print every assertion; 0 when every one holds."""
    started_at = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="contact-viz-check-") as tmp:
        env = dict(os.environ, CONTACT_VIZ_CACHE=str(Path(tmp) / "cache"))
        session, model = make_check_data(data or Path(tmp) / "data", env)
        log = Path(tmp) / "commands.log"
        flagged = evidence_frames(session, env, log)
        stems, contact, in_view = session_truth(session)
        if not flagged:
            print(f"FAIL no check with an evidence picture fired on {session}")
            return 1
        frames = {"a": clean_frame_after(flagged, CHECK_FAULT[1], len(stems)), "b": flagged[len(flagged) // 2]}
        frames["c"] = contact_frame(contact, in_view, [*flagged, *CHECK_FAULT[1], frames["a"]])
        print(f"data ready in {time.monotonic() - started_at:.0f} s: {session}, fault {CHECK_FAULT[0]} at "
              f"{CHECK_FAULT[1][0]}-{CHECK_FAULT[1][-1]}, evidence on {flagged}; frames: (a) clean {frames['a']}, "
              f"(b) flagged {frames['b']}, (c) in contact {frames['c']}", flush=True)
        if rrd is None:
            rrd = Path(tmp) / "check.rrd"
            run_commands([contact_viz() + [str(session), "--model", str(model), "--save", str(rrd)]], env, log,
                         CHECK_DATA_TIMEOUT_S)
        files = {key: left_file(session, stems[frame]) for key, frame in frames.items()}
        results: list[tuple[tuple[int, int], Assertion]] = []
        for size in sizes:
            results += [(size, a) for a in check_size(rrd, size, frames, files, contact.shape[1], out, timeout)]
    print("\n".join(assertion.line(size) for size, assertion in results))
    passed = sum(a.passed for _, a in results)
    print(f"check: {passed} of {len(results)} assertions hold; total {time.monotonic() - started_at:.0f} s")
    return 0 if results and passed == len(results) else 1


def check_size(rrd: Path, size: tuple[int, int], frames: dict[str, int], files: dict[str, np.ndarray],
               n_tools: int, out: Path, timeout: float) -> list[Assertion]:
    """The assertions at one window size: a fresh web viewer, the three frames shown paused and fully drawn."""
    order = list(frames.values())
    try:
        with web_viewer_for_rrd(rrd, size, timeout) as viewer:
            shots, failures = take_shots(viewer, order, out, timeout)
    except (TimeoutError, RuntimeError, OSError) as error:
        shots, failures = [], [f"web {size[0]}x{size[1]}: {error}"]
    if failures:
        return [Assertion("screenshots", failure, False) for failure in failures]
    by_frame = {shot.frame: shot for shot in shots}
    images = {key: by_frame[frame].image for key, frame in frames.items()}
    panes = by_frame[frames["c"]].panes
    if "left" not in panes:
        print(f"  {size[0]}x{size[1]}: panes not measured ({len(panes)} found); the table's are used")
        panes = default_panes(size)
    return (evidence_assertions(images, frames, files, panes, size)
            + colour_assertions(images["c"], frames["c"], expected_colours(n_tools), panes, size))


# ---------------------------------------------------------------------------------------------------------------
# Command line


def contact_viz() -> list[str]:
    return [sys.executable, "-m", "contact_viz.cli"]


@contextlib.contextmanager
def served_session(session: Path, view_args: list[str], env: dict) -> Iterator[str]:
    """`contact-viz SESSION --serve` (the recording streamed over gRPC); the web viewer URL it prints."""
    grpc_port, web_port = free_port(), free_port()
    with started(contact_viz() + [str(session), "--serve", "--grpc-port", str(grpc_port), "--web-port",
                                  str(web_port)] + view_args,
                 stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env) as server:
        url = None
        for line in server.stdout:
            print(f"  contact-viz: {line.rstrip()}", flush=True)
            match = re.search(r"web viewer: (\S+)", line)
            if match:
                url = match.group(1).replace("//localhost:", "//127.0.0.1:")
            if "serving" in line:
                break
        if url is None:
            raise RuntimeError("contact-viz --serve printed no URL")
        # keep reading its output, so that it never blocks on a full pipe
        threading.Thread(target=lambda: [None for _ in server.stdout], daemon=True).start()
        yield url


def parse_sizes(values: list[str]) -> list[tuple[int, int]]:
    sizes = []
    for value in values:
        for item in value.split(","):
            match = re.fullmatch(r"\s*(\d+)x(\d+)\s*", item)
            if not match:
                raise argparse.ArgumentTypeError(f"--size: expected WIDTHxHEIGHT, e.g. 1280x720, got {item!r}")
            sizes.append((int(match.group(1)), int(match.group(2))))
    return sizes


def parse_frames(value: str) -> list[int]:
    try:
        return [int(item) for item in value.split(",") if item.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--frames: expected frame numbers like 10,35, got {value!r}") from None


def report(shots: list[Shot], compare: Path | None) -> None:
    """The pane rectangles measured at each size, the left image's change between frames, repeatability."""
    by_size: dict[tuple[str, tuple[int, int]], list[Shot]] = {}
    for shot in shots:
        by_size.setdefault((shot.viewer, shot.size), []).append(shot)
    for (viewer, size), group in by_size.items():
        panes = group[0].panes
        print(f"{viewer} {size[0]}x{size[1]}: {len(panes)} panes measured (fractions x0, y0, x1, y1; "
              f"for PANES_BY_SIZE[{size}]):")
        print("    " + json.dumps(panes).replace("[", "(").replace("]", ")"))
        framed = [s for s in group if s.frame is not None]
        left = left_image_rect(panes or default_panes(size), size)
        for a, b in zip(framed, framed[1:]):
            print(f"  left image, frame {a.frame} vs {b.frame}: mean difference {region_difference(a.image, b.image, left):.1f}"
                  f" (0-255), {changed_share(a.image, b.image, left):.0%} of its pixels changed")
        print("  time per screenshot: " + ", ".join(f"{frame_label(s.frame)}: {s.seconds:.1f} s" for s in group))
    if compare is not None:
        from PIL import Image

        for shot in shots:
            if shot.path is None or not (compare / shot.path.name).exists():
                continue
            other = np.asarray(Image.open(compare / shot.path.name).convert("RGB"))
            if other.shape != shot.image.shape:
                print(f"  {shot.path.name}: {compare} has another size")
                continue
            per_pane = {name: round(changed_share(shot.image, other, rect), 4) for name, rect in shot.panes.items()}
            print(f"  {shot.path.name} vs {compare / shot.path.name}: {changed_share(shot.image, other):.2%} of the "
                  f"window changed (mean {region_difference(shot.image, other):.2f}); changed share per pane {per_pane}")


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt(f"signal {signum}")


def check_main(args: argparse.Namespace, parser: argparse.ArgumentParser, sizes: list[tuple[int, int]]) -> int:
    """The --check mode of main."""
    if args.session is not None or args.frames is not None or args.native or args.view_args:
        parser.error("--check makes its own session and frames: no SESSION, --frames, --native or --view-args")
    if args.rrd is not None and not args.rrd.is_file():
        parser.error(f"--rrd: no such file: {args.rrd}")
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, _raise_interrupt)
    try:
        return run_check(args.rrd, sizes, args.out or Path("results/check_viewers/check"), args.timeout, args.data)
    except KeyboardInterrupt as interrupt:
        print(f"interrupted ({interrupt or 'Ctrl-C'}); every process this script started is stopped")
        return 130
    except (RuntimeError, TimeoutError, OSError, ValueError) as error:
        print(f"FAIL check: {error}")
        return 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=" ".join(__doc__.split("\n\n")[0].split()),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("session", nargs="?", type=Path, help="session directory (default: a synthetic one)")
    parser.add_argument("--rrd", type=Path, help="check this recording as it is (instead of rendering a session)")
    parser.add_argument("--web", action="store_true", help="check the web viewer (default: both)")
    parser.add_argument("--native", action="store_true", help="check the native viewer (default: both)")
    parser.add_argument("--frames", type=parse_frames, default=None,
                        help="frames of the `frame` timeline to show, paused, and screenshot, e.g. 10,35")
    parser.add_argument("--size", action="append", default=[], metavar="WxH",
                        help=f"window size, repeatable or comma-separated (default {SCREEN[0]}x{SCREEN[1]})")
    parser.add_argument("--out", type=Path, default=None,
                        help="directory for the screenshots (default: docs/ without --frames and --rrd, "
                             "else results/check_viewers/)")
    parser.add_argument("--timeout", type=float, default=TIMEOUT_S, help="seconds allowed per screenshot")
    parser.add_argument("--compare", type=Path, default=None,
                        help="a directory of earlier screenshots: print how much each new one differs")
    parser.add_argument("--view-args", default="", help='more options of `contact-viz SESSION`, e.g. "--start 28 --end 36"')
    parser.add_argument("--check", action="store_true",
                        help="assert what a recording of the check's own session shows at three frames (web viewer; "
                             "with --rrd: that recording of the same session)")
    parser.add_argument("--data", type=Path, default=None,
                        help="with --check: make the session and model here and keep them (reused when complete)")
    args = parser.parse_args(argv)
    try:
        sizes = parse_sizes(args.size) or ([*CHECK_SIZES] if args.check else [SCREEN])
    except argparse.ArgumentTypeError as error:
        parser.error(str(error))
    if args.check:
        return check_main(args, parser, sizes)
    if args.rrd is not None and args.session is not None:
        parser.error("give SESSION or --rrd, not both")
    if args.rrd is not None and not args.rrd.is_file():
        parser.error(f"--rrd: no such file: {args.rrd}")
    if args.session is not None and not args.session.is_dir():
        parser.error(f"SESSION: no such directory: {args.session}")
    both = not (args.web or args.native)
    legacy = args.frames is None and args.rrd is None
    out = args.out or (Path("docs") if legacy else Path("results/check_viewers"))
    frames: list[int | None] = list(args.frames) if args.frames else [None]
    for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP):  # (SIGINT too: a background job ignores it)
        signal.signal(sig, _raise_interrupt)

    def legacy_name(viewer: str, size: tuple[int, int]) -> Callable[[int | None], str]:
        def name(frame: int | None) -> str:
            if frame is None and legacy:
                suffix = "" if len(sizes) == 1 else f"_{size[0]}x{size[1]}"
                return f"screenshot_{viewer}_viewer{suffix}.png"
            return shot_name(viewer, size, frame)
        return name

    results: dict[str, bool] = {}
    shots: list[Shot] = []
    started_at = time.monotonic()
    try:
        with tempfile.TemporaryDirectory(prefix="contact-viz-check-") as tmp:
            workdir = Path(tmp)
            env = dict(os.environ, CONTACT_VIZ_CACHE=str(workdir / "cache"))
            view_args = args.view_args.split()
            session, rrd = args.session, args.rrd
            if rrd is None and session is None:
                session = workdir / "session"
                subprocess.run(contact_viz() + ["synth", str(session), "--frames", "40", "--size", "640x360",
                                                "--seed", "2"], check=True, stdout=subprocess.DEVNULL, env=env)
            if args.web or both:
                failures: list[str] = []
                try:
                    with contextlib.ExitStack() as stack:
                        if rrd is not None:
                            base = stack.enter_context(web_viewer_server())
                            url = f"{base}?url={quote(stack.enter_context(serve_file(rrd)), safe='')}"
                        else:
                            url = stack.enter_context(served_session(session, view_args, env))
                        print(f"web viewer: {url}", flush=True)
                        for size in sizes:
                            try:
                                opened_at = time.monotonic()
                                with web_viewer(url, size, args.timeout) as viewer:
                                    print(f"web {size[0]}x{size[1]}: viewer {viewer.state().version} started in "
                                          f"{time.monotonic() - opened_at:.1f} s", flush=True)
                                    got, failed = take_shots(viewer, frames, out, args.timeout,
                                                             legacy_name("web", size))
                                shots += got
                                failures += failed
                            except (TimeoutError, RuntimeError, OSError) as error:
                                failures.append(f"web {size[0]}x{size[1]}: {error}")
                                print(f"web {size[0]}x{size[1]}: FAILED: {error}", flush=True)
                except (TimeoutError, RuntimeError, OSError) as error:
                    failures.append(f"web: {error}")
                    print(f"web: FAILED: {error}", flush=True)
                results["web"] = not failures
            if args.native or both:
                failures = []
                if rrd is None:
                    rrd = workdir / "check.rrd"
                    subprocess.run(contact_viz() + [str(session), "--save", str(rrd)] + view_args, check=True,
                                   env=env, stdout=subprocess.DEVNULL)
                for size in sizes:
                    try:
                        with native_viewer(rrd, size, args.timeout) as viewer:
                            got, failed = take_shots(viewer, frames, out, args.timeout, legacy_name("native", size))
                        shots += got
                        failures += failed
                    except (TimeoutError, RuntimeError, OSError) as error:
                        failures.append(f"native {size[0]}x{size[1]}: {error}")
                        print(f"native {size[0]}x{size[1]}: FAILED: {error}", flush=True)
                results["native"] = not failures
    except KeyboardInterrupt as interrupt:
        print(f"interrupted ({interrupt or 'Ctrl-C'}); every process this script started is stopped")
        return 130
    report(shots, args.compare)
    print(f"total {time.monotonic() - started_at:.0f} s; "
          + "; ".join(f"{k}: {'ok' if v else 'FAILED'}" for k, v in results.items()))
    return 0 if results and all(results.values()) else 1


if __name__ == "__main__":
    raise SystemExit(main())
