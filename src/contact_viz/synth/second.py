"""The second instrument (``SynthParams.tools = 2``): its motion, planned around instrument 1's
(``plan_tracks``; pure numpy).

Instrument 1's track is planned first, exactly as with one tool (its random streams are untouched:
every file of a one-tool session stays the same); instrument 2 draws from its own stream
(``STREAM_MOTION_2``). It is the same kind of tool (shaft, wrist and two jaws of the same sizes, the
same ``shaft_elevation_deg`` if set), entering from the other side of the image (the mirror image of
the phantom's mean shaft axis) and pressing over the mirrored target area. It palpates on every
phantom (presses and holds with closed jaws; on the glove it pushes, it does not grasp).

The plan follows instrument 1's contact runs (press, hold, retract; on the glove press, pull, hold).
For each run k:

1. Before it, instrument 2 presses the tissue at least ``_TARGET_AWAY_M`` from instrument 1's tip
   (it comes down from its lift height, hovers, presses, holds and retracts), starting as early as it
   can, so that its contact falls while instrument 1 retracts, approaches or hovers: *instrument 2
   touches the tissue while instrument 1 hovers*. (A press that does not fit before the visit is
   shortened, or left out; the two are never in contact at the same time.)
2. During instrument 1's hold, a visit (*instrument 1 touches while instrument 2 hovers*), alternating
   between the runs (a visit that cannot be placed is tried again at the next run):

   - runs 0, 2, ...: **near miss**. Instrument 2 hovers beside instrument 1's tip with the two
     silhouettes ``_NEAR_MISS_PX`` (4) px apart in the left image at the session's resolution (the
     smallest distance from an instrument-2 pixel to an instrument-1 pixel), found by bisection of its
     offset from instrument 1's tip (along the first of ``_SIDES`` that works: image left, its own
     side, first) on exact ray casts of both tools (``synth.tools.cast_tools``). While there it
     follows instrument 1's small movements (the hold tremor), so the gap stays for the whole hold;
     the rendered masks show 3-5 px.
   - runs 1, 3, ...: **crossing**. Instrument 2, raised above the tissue, sweeps across instrument 1
     near its jaws (``_CROSS_PATHS``) from its own side to the far side, nearer the camera than
     instrument 1 wherever the two overlap in the image (checked on ray casts of every frame of the
     sweep; the lowest of ``_CROSS_HEIGHT_M`` that passes is taken), so it hides part of instrument 1
     in the masks (id 2 over id 1).

   Hover heights are above the tissue as instrument 1 deforms it (the glove's tent when it pulls).
3. After the hold it lifts away along its shaft and goes on to its next press.

A session needs two contact runs of instrument 1 (about 100-200 frames at 30 fps) to show both
kinds of visit; a shorter one shows the first part of this plan. Every frame of instrument 2 is
checked before it is kept: its wrist and shaft clear the tissue, its jaws touch it only while it
presses, it is never in contact together with instrument 1, its capsules stay at least
``_TOOL_CLEARANCE_M`` from instrument 1's, and no visible part of it comes nearer the camera than
``synth.motion.near_limit_m``. Its heights scale with ``SynthParams.gap_scale``; the offsets between
the two instruments keep their sizes, as the instruments do. A press target or a visit that fails is redrawn a few
times and then left out (instrument 2 waits where it is, or lifts out of the way).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from types import SimpleNamespace

import cv2
import numpy as np

from contact_viz.synth.motion import (
    _AXIS_JITTER, _CLEARANCE_M, _JAW_CLEARANCE_M, LAYOUTS, ToolTrack, _State, _draw_target, _ease,
    _height_clearance, _jaw_geometry, _tool_centres, _tool_samples, mean_tool_axis, near_limit_m, nearest_in_view_m,
    plan_tool_track, scaled, tissue_displacement_frames, track_from_states, with_elevation,
)
from contact_viz.synth.params import STREAM_MOTION_2, SynthParams, stream_rng
from contact_viz.synth.scene import (
    StereoCamera, TissueFrame, closest_surface_points, stereo_camera, surface_normals, surface_points,
    tissue_frame,
)
from contact_viz.synth.tools import cast_tools, tool_distance, tool_primitives

_NEAR_MISS_PX = 4.0  # image gap between the two silhouettes during a near miss (analytic), px
_BAND_PX = 12  # the near-miss search looks at pixels this close to instrument 1, px
_TOOL_CLEARANCE_M = 0.001  # smallest 3D distance between the two instruments (their capsules), m
# Heights above the tissue, m (times SynthParams.gap_scale, like the gaps of SynthParams):
_LIFT_M = 0.02  # gap along its axis at which instrument 2 moves between places, m
_NEAR_HOVER_M = (0.004, 0.007, 0.010, 0.014, 0.019, 0.025)  # hover heights tried for a near miss, m
_CROSS_HEIGHT_M = (0.008, 0.011, 0.014, 0.018, 0.022, 0.026, 0.030)  # heights tried for a crossing, m
# Sweeps of a crossing, tried in turn: (forward, start, end) offsets (m) of instrument 2's tip from
# instrument 1's, forward along instrument 1's axis, sideways across it (> 0: instrument 2's side).
# Crossing near instrument 1's jaws keeps instrument 2's shaft off instrument 1's rising shaft.
_CROSS_PATHS = ((0.004, 0.012, -0.009), (0.009, 0.012, -0.009), (0.0, 0.012, -0.012))
_CROSS_DEPTH_MARGIN_M = 0.0005  # instrument 2 nearer than instrument 1 by at least this where they overlap, m
_CROSS_GRID_PX = 240  # width of the coarse pixel grid the crossing's depth order is checked on, px
_OFFSET_MAX_M = 0.03  # largest sideways offset tried for a near miss, m
# Directions (u, v) in the base plane, from instrument 1's tip toward where instrument 2 is put for a
# visit, tried in turn: image left (instrument 2's own side), down-left, down, up-left, right.
_SIDES = ((-1.0, 0.0), (-math.sqrt(0.5), math.sqrt(0.5)), (0.0, 1.0), (-math.sqrt(0.5), -math.sqrt(0.5)), (1.0, 0.0))
_PRESS_TRIES = 4  # press targets tried per press, count
# a press target of instrument 2 stays this far from instrument 1's tip in the plane, phantom units (it scales
# with the phantom: the 3D clearance check keeps the instruments apart)
_TARGET_AWAY_M = 0.012
_VIEW_MARGIN = 0.05  # instrument 2's tip stays this fraction of the image size inside it during visits, -
# Durations of instrument 2's moves (s): nominal and shortest (a press squeezed into a short slot).
_MOVE_S, _DESCEND_S, _HOVER_S, _PRESS_S, _HOLD_S, _RETRACT_S = 0.35, 0.25, 0.1, 0.25, (0.2, 0.5), 0.25
_MIN_FRAMES = {"move": 4, "descend": 3, "hover": 1, "press": 3, "hold": 3, "retract": 3}
_ARRIVE_S, _DEPART_S = 0.35, 0.25  # moving to a visit (from the lift height) and lifting away after it, s


@dataclass
class _Key:
    """A keyframe of instrument 2: its state at frame t; the segment to the next key has this phase."""

    t: int
    state: _State
    phase: str


@dataclass(frozen=True)
class _Follow:
    """Instrument 2 moves with instrument 1's tip relative to frame ``ref``: weight rising over
    [t0, t1), 1 over [t1, t2), falling over [t2, t3)."""

    t0: int
    t1: int
    t2: int
    t3: int
    ref: int


class _Planner:
    """Builds instrument 2's keyframes episode by episode, checking each against instrument 1."""

    def __init__(self, params: SynthParams, first: ToolTrack):
        self.params, self.first = params, first
        self.phantom = params.phantom
        self.frame: TissueFrame = tissue_frame(params)
        self.camera: StereoCamera = stereo_camera(params)
        self.rng = stream_rng(params, STREAM_MOTION_2)
        self.fps = params.fps
        self.mean_axis = mean_tool_axis(self.phantom, mirrored=True)
        u_min, u_max, v_min, v_max = LAYOUTS[self.phantom].target_box_m
        self.box = (-u_max, -u_min, v_min, v_max)
        self.keys: list[_Key] = []
        self.follows: list[_Follow] = []
        tu, tv, _ = self.frame.to_tissue(first.tip_center_m)
        self.first_foot = np.stack([tu, tv], axis=1)  # instrument 1's tip over the base plane, (F, 2) phantom units
        self.first_target = None  # (u, v, axis) instrument 2 starts above (its first press)
        # Heights at the session's gap_scale, m; the offsets between the instruments keep their sizes (the
        # instruments do): a camera-frame length in the base plane is 1 / frame.scale phantom units.
        g = params.gap_scale
        self.lift_m = _LIFT_M * g
        self.near_hover_m = tuple(h * g for h in _NEAR_HOVER_M)
        self.cross_height_m = tuple(h * g for h in _CROSS_HEIGHT_M)
        self.hover_gap_m = scaled(params.hover_gap_m, params)
        self.near_m = near_limit_m(params)  # no visible part of instrument 2 nearer the camera, m

    # -- states and checks -------------------------------------------------------------------------
    def frames_of(self, seconds: float) -> int:
        return max(1, round(seconds * self.fps))

    def centre(self, s: _State) -> np.ndarray:
        c, _, _, _ = _tool_centres(self.phantom, self.frame, self.params, np.array(s.u), np.array(s.v),
                                   np.array(s.h), np.array(s.pull), s.axis)
        return c

    def lifted(self, s: _State, h: float | None = None) -> _State:
        return replace(s, h=max(self.lift_m if h is None else h, s.h))

    def target_for_foot(self, foot: np.ndarray, h: float, axis: np.ndarray) -> tuple[float, float]:
        """The target (u, v) whose state at gap h puts the tip centre over ``foot`` (u, v) of the plane."""
        uv = np.array(foot, dtype=np.float64)
        for _ in range(6):
            c = self.centre(_State(float(uv[0]), float(uv[1]), h, 0.0, 0.0, axis))
            cu, cv, _ = self.frame.to_tissue(c)
            uv = uv + (np.asarray(foot) - np.array([cu, cv]))
        return float(uv[0]), float(uv[1])

    def rise(self, points: np.ndarray, m: int) -> np.ndarray:
        """How far instrument 1 raises the tissue below ``points`` (..., 3) in frame m (its pull; a
        dent counts as 0), along the base-plane normal, m."""
        pts = np.asarray(points, dtype=np.float64).reshape(1, -1, 3)
        u, v, _ = self.frame.to_tissue(pts)
        below = surface_points(self.phantom, self.frame, u, v)
        up = tissue_displacement_frames(below, self.first, np.array([m]), self.params) @ self.frame.normal
        return np.maximum(up, 0.0).reshape(np.shape(points)[:-1])

    def pose_ok(self, s: _State, m: int) -> bool:
        """A hover state for a visit in frame m: jaws, wrist and shaft clear of the tissue (raised where
        instrument 1 pulls it), the far end of the shaft outside the image, the tip inside it
        (``_VIEW_MARGIN``) and in the camera's line of sight. (Unlike a press target, the surface below
        need not face the tool or the camera.)"""
        c = self.centre(s)
        n = surface_normals(self.phantom, self.frame, np.array(s.u), np.array(s.v))
        _, _, tips = _jaw_geometry(self.params, c, s.axis, n, np.array(s.jaw))
        if np.any(_height_clearance(self.phantom, self.frame, tips) - self.rise(tips, m)
                  < self.params.jaw_radius_m + _JAW_CLEARANCE_M):
            return False
        pts, radius = _tool_samples(self.params, c, s.axis)
        if np.any(_height_clearance(self.phantom, self.frame, pts) - self.rise(pts, m) < radius + _CLEARANCE_M):
            return False
        size = np.array([self.camera.width, self.camera.height])
        far_end = pts[-1]
        if far_end[2] > 0.01:
            end_px = self.camera.project(far_end)
            if np.all(end_px >= 0) and np.all(end_px < size):
                return False
        px = self.camera.project(c)
        if np.any(px < _VIEW_MARGIN * size) or np.any(px > (1 - _VIEW_MARGIN) * size):
            return False
        if nearest_in_view_m(self.params, self.camera, c, s.axis, False) < self.near_m:
            return False
        sight = np.linspace(0.0, 1.0 - 0.004 / np.linalg.norm(c), 40)[1:, None] * c
        return bool(np.all(_height_clearance(self.phantom, self.frame, sight) >= 0))

    def raised(self, u: float, v: float, h: float, axis: np.ndarray, m: int) -> _State:
        """The hover state at target (u, v) with gap h above the tissue as instrument 1 raises it in frame m."""
        s = _State(u, v, h, 0.0, 0.0, axis)
        if not np.any(self.first.pull_m[m]):  # a dent only lowers the tissue
            return s
        target = surface_points(self.phantom, self.frame, np.array(u), np.array(v))
        lift = float(max(self.rise(target, m), self.rise(self.centre(s), m)))
        return s if lift <= 0 else _State(u, v, h + lift, 0.0, 0.0, axis)

    def sample(self, keys: list[_Key], follows: list[_Follow], frames: np.ndarray) -> dict[str, np.ndarray]:
        """Per-frame states of instrument 2 at ``frames`` (sorted ints) from ``keys`` (eased like
        instrument 1's segments; the last key's state holds), plus the follow offset."""
        ts = np.array([k.t for k in keys])
        j = np.searchsorted(ts, frames, side="right") - 1
        last = j + 1 >= len(keys)
        nxt = np.where(last, j, j + 1)
        span = np.where(last, 1, ts[nxt] - ts[j])
        s = _ease(np.where(last, 0.0, (frames - ts[j]) / span))
        st: dict[str, np.ndarray] = {}
        for name in ("u", "v", "h", "pull", "jaw"):
            values = np.array([getattr(k.state, name) for k in keys])
            st[name] = values[j] + (values[nxt] - values[j]) * s
        axes = np.stack([k.state.axis for k in keys])
        axis = axes[j] * (1 - s[:, None]) + axes[nxt] * s[:, None]
        axis /= np.linalg.norm(axis, axis=1, keepdims=True)
        st["axis"] = with_elevation(axis, self.frame, self.params.shaft_elevation_deg)
        st["attached"] = np.zeros(len(frames), bool)
        st["phase"] = np.array([keys[i].phase for i in j], dtype=object)
        offset = np.zeros((len(frames), 3))
        for f in follows:
            w = np.zeros(len(frames))
            rise = (frames >= f.t0) & (frames < f.t1)
            w[rise] = _ease((frames[rise] - f.t0) / max(f.t1 - f.t0, 1))
            w[(frames >= f.t1) & (frames < f.t2)] = 1.0
            fall = (frames >= f.t2) & (frames < f.t3)
            w[fall] = 1.0 - _ease((frames[fall] - f.t2) / max(f.t3 - f.t2, 1))
            offset += w[:, None] * (self.first.tip_center_m[frames] - self.first.tip_center_m[f.ref])
        st["offset"] = offset
        return st

    def track(self, st: dict[str, np.ndarray]) -> ToolTrack:
        return track_from_states(self.params, st, st["offset"])

    def frames_ok(self, keys: list[_Key], follows: list[_Follow], t0: int, t1: int) -> bool:
        """Whether instrument 2 is acceptable over frames [t0, t1) with these keys: apart from
        instrument 1, never in contact at the same time as it, jaws off the tissue (as instrument 1
        deforms it) except while pressing, wrist and shaft clear of it."""
        t1 = min(t1, self.params.frames)
        if t1 <= t0:
            return True
        frames = np.arange(t0, t1)
        st = self.sample(keys, follows, frames)
        track = self.track(st)
        first = _subtrack(self.first, frames)
        if np.any(tool_distance(first, track, self.params) < _TOOL_CLEARANCE_M):
            return False
        if np.any(track.contact & first.contact):
            return False
        if np.any(nearest_in_view_m(self.params, self.camera, track.tip_center_m, track.axis, False) < self.near_m):
            return False
        free = st["h"] > 0.001  # not pressing: the jaws keep off the tissue, the shaft and wrist clear it
        if not np.any(free):
            return True
        if np.any(track.contact[free]) or np.any(gap_beside(self.params, track, first)[free] < _JAW_CLEARANCE_M / 2):
            return False
        pts, radius = _tool_samples(self.params, track.tip_center_m[free][:, None, :], track.axis[free][:, None, :])
        clearance = _height_clearance(self.phantom, self.frame, pts)
        u, v, _ = self.frame.to_tissue(pts)  # the tissue below, raised where instrument 1 pulls it
        below = surface_points(self.phantom, self.frame, u, v)
        rise = tissue_displacement_frames(below, first, np.flatnonzero(free), self.params) @ self.frame.normal
        return not np.any(clearance - np.maximum(rise, 0.0) < radius[None, :] + _CLEARANCE_M)

    def commit_if_ok(self, new_keys: list[_Key], new_follows: list[_Follow] = ()) -> bool:
        keys, follows = self.keys + new_keys, self.follows + list(new_follows)
        if not self.frames_ok(keys, follows, self.keys[-1].t, new_keys[-1].t + 1):
            return False
        self.keys, self.follows = keys, follows
        return True

    @property
    def now(self) -> int:
        return self.keys[-1].t

    @property
    def current(self) -> _State:
        return self.keys[-1].state

    # -- presses -----------------------------------------------------------------------------------
    def draw_press_target(self, frames: np.ndarray, hover: float, lift: float):
        """A target (u, v, axis) for a press, away from instrument 1's tip over ``frames``."""
        feet = self.first_foot[frames]

        def away(u: float, v: float) -> bool:
            return bool(np.min(np.hypot(feet[:, 0] - u, feet[:, 1] - v)) >= _TARGET_AWAY_M)

        checks = [(lift, 0.0, 0.0, False), (hover, 0.0, 0.0, True), (-self.params.press_depth_m[1], 0.0, 0.0, True)]
        try:
            return _draw_target(self.rng, self.phantom, self.frame, self.camera, self.params, checks,
                                mean_axis=self.mean_axis, box=self.box, accept=away)
        except RuntimeError:
            return None

    def start(self) -> None:
        """Instrument 2 at frame 0: lifted above the target of its first press."""
        hover = float(self.rng.uniform(*self.hover_gap_m))
        window = np.arange(min(self.params.frames, self.frames_of(1.0)))
        for _ in range(_PRESS_TRIES):
            drawn = self.draw_press_target(window, hover, self.lift_m)
            if drawn is None:
                continue
            u, v, axis = drawn
            keys = [_Key(0, _State(u, v, self.lift_m, 0.0, 0.0, axis), "approach")]
            if self.frames_ok(keys, [], 0, 1):
                self.keys, self.first_target = keys, drawn
                return
        raise RuntimeError(f"synth: found no place to start instrument 2 on phantom {self.phantom!r}")

    def press(self, end: int, deadline: int | None) -> bool:
        """A press by instrument 2 from now, lifted again by frame ``end``, its contact over before frame
        ``deadline`` (instrument 1's next contact; None: no limit)."""
        hold_s = float(self.rng.uniform(*_HOLD_S))
        light = self.rng.uniform() < self.params.light_press_prob
        depth = float(self.rng.uniform(*(self.params.light_press_depth_m if light else self.params.press_depth_m)))
        hover = float(self.rng.uniform(*self.hover_gap_m))
        nominal = {"move": _MOVE_S, "descend": _DESCEND_S, "hover": _HOVER_S, "press": _PRESS_S, "hold": hold_s,
                   "retract": _RETRACT_S}
        frames = {k: self.frames_of(v) for k, v in nominal.items()}
        if self.first_target is not None:  # already above the first target
            frames["move"] = 0
        # Squeeze into the slot (not below the shortest durations): lifted by `end`, contact over (it
        # ends just after the retract starts) before `deadline`.
        slot = end - self.now
        to_retract = sum(frames[k] for k in ("move", "descend", "hover", "press", "hold"))
        scale = min(1.0, slot / sum(frames.values()))
        if deadline is not None:
            scale = min(scale, (deadline - 2 - self.now) / to_retract)
        if scale < 1.0:
            frames = {k: 0 if v == 0 else max(_MIN_FRAMES[k], int(v * scale)) for k, v in frames.items()}
            to_retract = sum(frames[k] for k in ("move", "descend", "hover", "press", "hold"))
            if sum(frames.values()) > slot or (deadline is not None and self.now + to_retract + 2 > deadline):
                return False
        window = np.arange(self.now, min(self.now + sum(frames.values()), self.params.frames))
        for attempt in range(_PRESS_TRIES):
            if self.first_target is not None and attempt == 0:
                drawn = self.first_target
            else:
                frames["move"] = frames["move"] or _MIN_FRAMES["move"]
                drawn = self.draw_press_target(window, hover, self.lift_m)
            if drawn is None:
                break
            u, v, axis = drawn
            lift = _State(u, v, self.lift_m, 0.0, 0.0, axis)
            hovering = _State(u, v, hover, 0.0, 0.0, axis)
            pressed = _State(u, v, -depth, 0.0, 0.0, axis)
            t = self.now
            keys = []
            up = self.lifted(self.current)
            if up.h != self.current.h:  # lift first where it is
                t += max(1, frames["move"] // 3)
                keys.append(_Key(t, up, "approach"))
            for state, phase, name in ((lift, "approach", "move"), (hovering, "approach", "descend"),
                                       (hovering, "press", "hover"), (pressed, "hold", "press"),
                                       (pressed, "retract", "hold"), (lift, "approach", "retract")):
                if frames[name]:
                    t += frames[name]
                    keys.append(_Key(t, state, phase))
            if t > end or (deadline is not None and keys[-2].t + 2 > deadline):
                continue
            if self.commit_if_ok(keys):
                self.first_target = None
                return True
        self.first_target = None
        return False

    # -- visits ------------------------------------------------------------------------------------
    def visit(self, kind: str, hold_start: int, hold_end: int) -> bool:
        """A near miss or a crossing (``kind`` "near" or "cross") during instrument 1's hold
        [hold_start, hold_end): tries hover heights from low to high, and for each the sides of
        instrument 1 in ``_SIDES``, until one passes every check."""
        arrive = self.frames_of(_ARRIVE_S)
        if hold_start - arrive <= self.now:
            arrive = hold_start - self.now - 1
            if arrive < 4:
                return False
        depart = self.frames_of(_DEPART_S)
        m = hold_start
        band = self.near_band(tool_primitives(self.first, m, self.params)) if kind == "near" else None
        if kind == "near" and band is None:
            return False
        for h in self.near_hover_m if kind == "near" else self.cross_height_m:
            for side in _SIDES if kind == "near" else _CROSS_PATHS:
                axis = self.mean_axis + self.rng.normal(0.0, _AXIS_JITTER, 3)
                axis /= np.linalg.norm(axis)
                axis = with_elevation(axis, self.frame, self.params.shaft_elevation_deg)
                poses = (self.near_pose(band, m, h, axis, np.asarray(side)) if kind == "near"
                         else self.cross_poses(m, h, axis, side))
                if poses is None:
                    continue
                a, b = poses
                t_arrive = hold_start - arrive
                keys = []
                if t_arrive > self.now:
                    keys.append(_Key(t_arrive, self.current, "approach"))
                keys += [
                    _Key(hold_start - arrive // 2, self.lifted(a), "approach"),
                    _Key(hold_start, a, "approach"),
                    _Key(hold_end, b, "approach"),
                    _Key(hold_end + depart, self.lifted(b, b.h + self.lift_m), "approach"),
                ]
                follows = [_Follow(hold_start - arrive // 2, hold_start, hold_end, hold_end + depart, m)] \
                    if kind == "near" else []
                if kind == "cross" and not self.crossing_in_front(keys, hold_start, hold_end):
                    continue
                if self.commit_if_ok(keys, follows):
                    return True
        return False

    def near_band(self, first_parts):
        """The pixels where instrument 2 can come within _BAND_PX of instrument 1 (exact silhouette at
        the visit): the ring up to _BAND_PX outside it and 2 px inside it, as (rows, cols, distance to
        the nearest instrument-1 pixel, 0 inside); None if instrument 1 is not in the image."""
        cam = self.camera
        ids, _ = cast_tools([first_parts], cam, *_image_grid(cam))
        mask = (ids.reshape(cam.height, cam.width) > 0).astype(np.uint8)
        if not mask.any():
            return None
        outside = cv2.distanceTransform(1 - mask, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        inside = cv2.distanceTransform(np.pad(mask, 1), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
        rows, cols = np.nonzero((outside <= _BAND_PX) & (inside <= 2))
        return rows, cols, outside[rows, cols]

    def pose_parts(self, state: _State) -> list:
        """The primitives of instrument 2 in ``state`` (no follow offset)."""
        c = self.centre(state)
        n = surface_normals(self.phantom, self.frame, np.array(state.u), np.array(state.v))
        hinge, bases, tips = _jaw_geometry(self.params, c, state.axis, n, np.array(state.jaw))
        pose = SimpleNamespace(axis=state.axis[None], hinge_m=hinge[None], jaw_bases_m=bases[None],
                               jaw_tips_m=tips[None])
        return tool_primitives(pose, 0, self.params)

    def image_gap(self, band, state: _State) -> float:
        """Smallest distance, px, from an instrument-2 pixel to an instrument-1 pixel (0: they overlap;
        inf: farther than _BAND_PX)."""
        rows, cols, dist = band
        ids, _ = cast_tools([self.pose_parts(state)], self.camera, cols, rows)
        hit = ids > 0
        return float(dist[hit].min()) if hit.any() else math.inf

    def near_pose(self, band, m: int, h: float, axis: np.ndarray, side: np.ndarray):
        """Instrument 2 hovering at gap h beside instrument 1's tip (frame m), moved away from it along
        ``side`` (a unit direction in the base plane) until the image gap is _NEAR_MISS_PX."""
        u0, v0 = self.target_for_foot(self.first_foot[m], h, axis)

        def state(d: float) -> _State:
            return self.raised(u0 + d * side[0], v0 + d * side[1], h, axis, m)

        # Scan the offset for the farthest step from a gap below _NEAR_MISS_PX to one at or above it
        # (instrument 2 on the ``side`` side of instrument 1), then bisect that step.
        offsets = np.linspace(-_OFFSET_MAX_M, _OFFSET_MAX_M, 9) / self.frame.scale
        above = [self.image_gap(band, state(d)) >= _NEAR_MISS_PX for d in offsets]
        steps = [i for i in range(len(offsets) - 1) if not above[i] and above[i + 1]]
        if not steps:
            return None
        lo, hi = offsets[steps[-1]], offsets[steps[-1] + 1]
        for _ in range(16):  # the smallest offset there with gap >= _NEAR_MISS_PX
            mid = 0.5 * (lo + hi)
            if self.image_gap(band, state(mid)) >= _NEAR_MISS_PX:
                hi = mid
            else:
                lo = mid
        s = state(hi)
        return (s, s) if self.pose_ok(s, m) else None

    def cross_poses(self, m: int, h: float, axis: np.ndarray, path: tuple[float, float, float]):
        """Start and end of a sweep at gap h across instrument 1's tip (frame m): ``path`` = (forward,
        start, end) offsets (m) in the base plane, forward along instrument 1's axis (beyond its tip) and
        sideways across it (> 0: instrument 2's side, image left)."""
        ahead = np.array([self.first.axis[m] @ self.frame.e_u, self.first.axis[m] @ self.frame.e_v])
        ahead /= np.linalg.norm(ahead)
        across = np.array([-ahead[1], ahead[0]])
        if across[0] > 0:
            across = -across
        forward, start, end = path
        states = []
        for sideways in (start, end):
            foot = self.first_foot[m] + (forward * ahead + sideways * across) / self.frame.scale
            u, v = self.target_for_foot(foot, h, axis)
            s = self.raised(u, v, h, axis, m)
            if not self.pose_ok(s, m):
                return None
            states.append(s)
        return states[0], states[1]

    def crossing_in_front(self, keys: list[_Key], t0: int, t1: int) -> bool:
        """Over the sweep [t0, t1): the tools overlap in the image in some frame, and wherever they
        overlap instrument 2 is nearer (coarse pixel grid, exact ray casts)."""
        frames = np.arange(t0, min(t1, self.params.frames))
        st = self.sample(self.keys + keys, self.follows, frames)
        track = self.track(st)
        cam = self.camera
        step = max(1, math.ceil(cam.width / _CROSS_GRID_PX))
        rows, cols = np.mgrid[step // 2: cam.height: step, step // 2: cam.width: step]
        rows, cols = rows.ravel(), cols.ravel()
        overlapping = 0
        for k, i in enumerate(frames):
            _, z1 = cast_tools([tool_primitives(self.first, int(i), self.params)], cam, cols, rows)
            _, z2 = cast_tools([tool_primitives(track, k, self.params)], cam, cols, rows)
            both = np.isfinite(z1) & np.isfinite(z2)
            if np.any(z2[both] > z1[both] - _CROSS_DEPTH_MARGIN_M):
                return False
            overlapping += int(both.sum() > 0)
        return overlapping >= 2

    def wait_until(self, t: int) -> None:
        """Stay where it is until frame t (checked; if instrument 1 comes too close, lift first)."""
        t = min(t, self.params.frames)
        if t <= self.now:
            return
        if self.commit_if_ok([_Key(t, self.current, "approach")]):
            return
        up = self.lifted(self.current, self.current.h + self.lift_m)
        step = min(self.frames_of(_DEPART_S), t - self.now)
        keys = [_Key(self.now + step, up, "approach")] + ([_Key(t, up, "approach")] if t > self.now + step else [])
        if self.commit_if_ok(keys):
            return
        # Nothing better: keep still (instrument 2 may come closer to instrument 1 than planned).
        self.keys.append(_Key(t, self.current, "approach"))


def _image_grid(camera: StereoCamera) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.mgrid[: camera.height, : camera.width]
    return cols.ravel(), rows.ravel()


def _subtrack(track: ToolTrack, frames: np.ndarray) -> ToolTrack:
    """The frames ``frames`` of a track."""
    return ToolTrack(**{name: getattr(track, name)[frames] for name in track.__dataclass_fields__})


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    edges = np.flatnonzero(np.diff(np.concatenate([[0], flags.astype(np.int8), [0]])))
    return list(zip(edges[0::2].tolist(), edges[1::2].tolist()))


def plan_second_track(params: SynthParams, first: ToolTrack) -> ToolTrack:
    """Instrument 2's track around instrument 1's ``first`` (see the module docstring); its gap_m
    is still to the undeformed tissue (``plan_tracks`` measures it to the deformed one)."""
    planner = _Planner(params, first)
    planner.start()
    frames = params.frames
    visits = 0
    for a, b in _runs(first.contact):
        hold = np.flatnonzero(first.phase[a:b] == "hold") + a
        if len(hold) < 3:
            continue
        hold_start, hold_end = int(hold[0]), int(hold[-1]) + 1
        planner.press(hold_start - planner.frames_of(_ARRIVE_S), a)
        kind = "near" if visits % 2 == 0 else "cross"
        if planner.visit(kind, hold_start, hold_end):
            visits += 1
        else:
            planner.wait_until(max(planner.now, b))
    if planner.now < frames:
        later = np.flatnonzero(first.contact[planner.now:])
        planner.press(frames, planner.now + int(later[0]) if len(later) else None)
    planner.wait_until(frames)
    st = planner.sample(planner.keys, planner.follows, np.arange(frames))
    return planner.track(st)


def gap_beside(params: SynthParams, track: ToolTrack, other: ToolTrack) -> np.ndarray:
    """The gap (F,) of ``track``'s jaw tips to the tissue as ``other`` (the other instrument, same
    frames) deforms it, m, 0 in contact: the signed distance to the undeformed surface minus the
    other's displacement of the closest surface point along its normal (first order in the slope of
    the dent or tent). Where the other does not deform the tissue this is ``track.gap_m``."""
    gap = track.gap_m.copy()
    frames = np.flatnonzero(~track.contact & ((other.press_m > 0) | np.any(other.pull_m != 0, axis=1)))
    if not len(frames):
        return gap
    tips = track.jaw_tips_m[frames]
    closest, normals, signed, _ = closest_surface_points(params.phantom, tissue_frame(params), tips.reshape(-1, 3))
    moved = tissue_displacement_frames(closest.reshape(-1, 2, 3), other, frames, params)
    sd = signed.reshape(-1, 2) - np.sum(moved * normals.reshape(-1, 2, 3), axis=-1)
    gap[frames] = np.maximum(sd.min(axis=1) - params.jaw_radius_m, 0.0)
    return gap


def plan_tracks(params: SynthParams) -> tuple[ToolTrack, ...]:
    """The tracks of every instrument of the session: (instrument 1,) or (instrument 1, instrument 2).

    Instrument 1's motion is ``plan_tool_track(params)`` whatever ``params.tools`` is. With two
    instruments each one's ``gap_m`` is measured to the tissue as the other one deforms it
    (``gap_beside``): the dent of a press next to a hovering instrument lowers the tissue under it.
    The two are never in contact at the same time (the plan sees to it).
    """
    first = plan_tool_track(params)
    if params.tools == 1:
        return (first,)
    second = plan_second_track(params, first)
    return (replace(first, gap_m=gap_beside(params, first, second)),
            replace(second, gap_m=gap_beside(params, second, first)))
