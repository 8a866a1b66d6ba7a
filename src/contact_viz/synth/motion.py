"""The tool's motion and the truth of every frame (pure numpy): cycles of approach, hover, press,
hold, [pull] and retract (``plan_tool_track``), and the tissue's dent or tent (``tissue_displacement``)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from contact_viz.synth.params import SynthParams, STREAM_MOTION, stream_rng
from contact_viz.synth.scene import (
    TissueFrame, height_gradient, closest_surface_points, phantom_height, stereo_camera, surface_normals,
    surface_points, tissue_frame,
)


@dataclass(frozen=True)
class _PhantomLayout:
    """Where the tool works on a phantom and how its tissue looks."""

    target_box_m: tuple[float, float, float, float]  # (u_min, u_max, v_min, v_max) of press targets, phantom units
    target_min_height_m: float  # targets must be at least this high above the base plane, phantom units
    tool_axis: tuple[float, float, float]  # mean shaft direction toward the tip, camera frame, -
    tissue_rgb: tuple[float, float, float]  # base albedo of the phantom, linear RGB
    tray_rgb: tuple[float, float, float]  # albedo of the base plane around it, linear RGB
    vessel_rgb: tuple[float, float, float]  # albedo factor at a vessel's core, per RGB channel
    vessel_count: int  # number of main vessels drawn, count


LAYOUTS: dict[str, _PhantomLayout] = {
    "cup": _PhantomLayout(
        (-0.016, 0.02, -0.014, 0.022), 0.006, (-0.5, 0.84, 0.2),
        (0.66, 0.24, 0.23), (0.55, 0.10, 0.08), (0.55, 0.22, 0.28), 6,
    ),
    "kidney": _PhantomLayout(
        (-0.022, 0.018, -0.016, 0.02), 0.008, (-0.5, 0.84, 0.2),
        (0.50, 0.13, 0.10), (0.55, 0.10, 0.08), (0.5, 0.2, 0.25), 7,
    ),
    "liver": _PhantomLayout(
        (-0.03, 0.03, -0.022, 0.022), 0.006, (-0.5, 0.84, 0.2),
        (0.34, 0.07, 0.045), (0.55, 0.10, 0.08), (0.5, 0.2, 0.25), 8,
    ),
    "glove": _PhantomLayout(
        (0.006, 0.017, -0.01, 0.025), 0.008, (-0.62, 0.74, 0.2),
        (0.70, 0.42, 0.36), (0.55, 0.10, 0.08), (0.6, 0.35, 0.38), 3,
    ),
}


@dataclass(frozen=True, eq=False)
class ToolTrack:
    """Per-frame tool pose, tissue deformation and truth of a session; arrays over F frames.

    Points and vectors are in the left camera frame, m. The tool tip is two rounded jaws; the
    tip spheres (radius ``jaw_radius_m``) are centred at ``jaw_tips_m``.
    """

    timestamp_s: np.ndarray  # (F,) float64 frame times, s
    tip_center_m: np.ndarray  # (F, 3) hinge + jaw length along the axis (= mid jaw tip when closed), m
    axis: np.ndarray  # (F, 3) unit shaft axis, pointing from the shaft toward the tip
    hinge_m: np.ndarray  # (F, 3) jaw hinge on the axis, m
    jaw_bases_m: np.ndarray  # (F, 2, 3) base points of the two jaw capsules, m
    jaw_tips_m: np.ndarray  # (F, 2, 3) centres of the jaw-tip spheres, m
    dent_center_m: np.ndarray  # (F, 3) centre of the deformation, at the undeformed surface below the tip, m
    dent_normal: np.ndarray  # (F, 3) unit surface normal there
    dent_flat_m: np.ndarray  # (F,) radius of the flat bottom of the dent (covers both jaws), m
    press_m: np.ndarray  # (F,) depth of the dent along -dent_normal, m (0 = none)
    pull_m: np.ndarray  # (F, 3) displacement of the grasped point when pulling, m (0 = none)
    # (F,) distance of the tip surface to the undeformed tissue, 0 in contact, m (two instruments:
    # plan_tracks measures it to the tissue as the other one deforms it)
    gap_m: np.ndarray
    indentation_m: np.ndarray  # (F,) tissue displacement under the tip (dent depth or tent height), m
    force_true_n: np.ndarray  # (F, 3) true contact force on the tool, N
    contact: np.ndarray  # (F,) bool, tool touching (or grasping) the tissue
    phase: np.ndarray  # (F,) str, one of PHASES

    @property
    def frames(self) -> int:
        """Number of frames F."""
        return len(self.timestamp_s)


@dataclass
class _State:
    """A keyframe of the tool motion (see ``_tool_centres`` for the meaning of h and pull)."""

    u: float  # target on the tissue, phantom units
    v: float  # target on the tissue, phantom units
    h: float  # > 0: gap along the target normal; < 0: press depth, m
    pull: float  # distance pulled out along the pull direction, m
    jaw: float  # opening of each jaw, rad
    axis: np.ndarray  # (3,) unit shaft axis toward the tip


@dataclass
class _Segment:
    phase: str  # phase label (approach segments also carry the hover)
    frames: int  # length, frames
    start: _State
    end: _State
    attached: bool  # the jaws hold the tissue (glove grasp)
    wobble: float  # amplitude of a slow h variation that vanishes at both ends, m
    wobble_hz: float  # frequency of that variation, 1/s
    wobble_phase: float  # its phase, rad


def _ease(t: np.ndarray) -> np.ndarray:
    """Smoothstep 3t^2 - 2t^3: zero velocity at both ends."""
    return t * t * (3.0 - 2.0 * t)


def _tool_centres(
    phantom: str, frame: TissueFrame, params: SynthParams, u, v, h, pull, axis
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Tip centre (N, 3) for motion states (arrays of N), plus surface point, normal, pull direction.

    The tool touches the target point q (normal n) when h = 0. For h > 0 it backs off along its
    own axis until the gap along n is h; for h < 0 it presses along -n by |h|. ``pull`` moves it
    along the pull direction normalize(n - axis) (out of the tissue and back along the shaft).
    """
    q = surface_points(phantom, frame, u, v)
    n = surface_normals(phantom, frame, u, v)
    cos_theta = np.maximum(-np.sum(axis * n, axis=-1), _MIN_COS_AXIS)
    h = np.asarray(h, dtype=np.float64)[..., None]
    back = np.where(h >= 0, -axis * h / cos_theta[..., None], h * n)
    pull_dir = n - axis
    pull_dir /= np.linalg.norm(pull_dir, axis=-1, keepdims=True)
    c = q + n * params.jaw_radius_m + back + np.asarray(pull, dtype=np.float64)[..., None] * pull_dir
    return c, q, n, pull_dir


def _jaw_geometry(params: SynthParams, c: np.ndarray, axis: np.ndarray, n: np.ndarray, jaw: np.ndarray):
    """Hinge (N, 3), jaw bases (N, 2, 3) and jaw-tip sphere centres (N, 2, 3).

    The two jaws are capsules of radius ``jaw_radius_m`` side by side (touching when closed, with
    the tips at c -/+ jaw_radius_m along the spread direction, which is parallel to the tissue), each
    turning by ``jaw`` (rad) about its base to open.
    """
    spread = np.cross(axis, n)
    spread /= np.linalg.norm(spread, axis=-1, keepdims=True)
    hinge = c - axis * params.jaw_length_m
    bases, tips = [], []
    for side in (-1.0, 1.0):
        base = hinge + side * params.jaw_radius_m * spread
        beta = side * np.asarray(jaw, dtype=np.float64)[..., None]
        bases.append(base)
        tips.append(base + params.jaw_length_m * (np.cos(beta) * axis + np.sin(beta) * spread))
    return hinge, np.stack(bases, axis=-2), np.stack(tips, axis=-2)


def _tool_samples(params: SynthParams, c: np.ndarray, axis: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points along the wrist and shaft axis behind the jaws (S, 3) and the tool radius there (S,), m."""
    start = params.jaw_length_m - 0.0015
    end = params.jaw_length_m + params.wrist_length_m + SHAFT_LENGTH_M
    s = np.linspace(start, end, 80)
    on_wrist = s < params.jaw_length_m + params.wrist_length_m
    radius = np.where(on_wrist, params.wrist_radius_m, params.shaft_diameter_m / 2)
    return c - s[:, None] * axis, radius


SHAFT_LENGTH_M = 0.14  # rendered shaft length (reaches past the image border), m
_CLEARANCE_M = 0.001  # smallest allowed gap between wrist/shaft and the undeformed tissue, m
_JAW_CLEARANCE_M = 0.0005  # smallest gap of any jaw tip while hovering (h > 0), m
_MIN_COS_AXIS = 0.35  # tool axis at most ~70 deg from the surface normal at the target, -
_MIN_COS_VIEW = 0.4  # the target surface faces the camera: at most ~66 deg between normal and view ray, -
_TIP_VIEW_MARGIN = 0.2  # the tip stays this fraction of the image size away from the border, -
_MAX_TARGET_TRIES = 400  # attempts to draw a reachable target, count
_AXIS_JITTER = 0.08  # per-cycle random change of the tool axis (std per component of a unit vector), -
_WOBBLE_HZ = (0.6, 1.4)  # range of the frequency of the slow hover / hold variation, 1/s
_HOLD_TREMOR = 0.05  # amplitude of the indentation variation while holding, fraction of the depth
# Nearest z-depth any visible part of an instrument may have, m, and as a fraction of the tissue distance
# (the smaller of the two holds), where the camera sees less than the design's view (scene_scale < 1). On
# real da Vinci frames (LauraCruciani/DaVinci_project) the nearest instrument is 25 mm from the camera at a
# 50 mm working distance; the default camera's stay 25 mm or more away without a limit (nearest_in_view_m,
# 12 seeds x 4 phantoms x 200 frames with two instruments, 20 x 4 x 300 with one).
NEAR_M, NEAR_FRACTION = 0.02, 0.4
_GAP_STEPS = 16  # gaps checked from the deepest press to the largest gap at a target (near_limit_m), count
_MOVE_STEPS = 12  # states checked along a move between two targets (near_limit_m), count
_GAP_HALVINGS = 2  # times a cycle's gaps are halved when no target has room for them, count
_JAW_SPHERES = 4  # spheres along the jaws in nearest_in_view_m, count


def near_limit_m(params: SynthParams) -> float:
    """The nearest z-depth a visible part of an instrument may have in this session, m; -inf (no limit)
    where the camera sees at least the design's view (``scene_scale`` 1: the scene as designed)."""
    if params.scene_scale >= 1.0:
        return -math.inf
    return min(NEAR_M, NEAR_FRACTION * params.tissue_distance_m)


def nearest_in_view_m(params: SynthParams, camera, c: np.ndarray, axis: np.ndarray,
                      open_jaws: bool | None = None) -> np.ndarray:
    """Smallest z-depth (...) of the tools with tip centres c (..., 3) and axes (..., 3) over their parts
    whose outline reaches into the left image, m (inf: none does). The parts are spheres along the axis:
    along the jaws, each holding both (opened by ``jaw_open_deg`` if ``open_jaws``; None: on the glove),
    then the wrist and the shaft (``_tool_samples``); a sphere's nearest depth is its centre's minus its
    radius."""
    c, axis = np.asarray(c, dtype=np.float64), np.asarray(axis, dtype=np.float64)
    pts, radius = _tool_samples(params, c[..., None, :], axis[..., None, :])
    r, length = params.jaw_radius_m, params.jaw_length_m  # a jaw tip's centre: see _jaw_geometry
    if open_jaws is None:
        open_jaws = params.task == "pulling"
    beta = math.radians(params.jaw_open_deg) if open_jaws else 0.0
    jaws = r + math.hypot(length * (1.0 - math.cos(beta)), r + length * math.sin(beta))
    along = np.linspace(0.0, length, _JAW_SPHERES)
    pts = np.concatenate([c[..., None, :] - along[:, None] * axis[..., None, :], pts], axis=-2)
    radius = np.concatenate([np.full(_JAW_SPHERES, jaws), radius])
    # A sphere is in view when it reaches into the image's frustum: in front of the camera, and on the inner
    # side of (or crossing) each of the four planes through the optical centre and an image edge.
    x, y, z = pts[..., 0], pts[..., 1], pts[..., 2]
    inside = z + radius > 0
    for along, centre, focal, edges in ((x, camera.K[0, 2], camera.fx, (-0.5, camera.width - 0.5)),
                                        (y, camera.K[1, 2], camera.K[1, 1], (-0.5, camera.height - 0.5))):
        low, high = ((edge - centre) / focal for edge in edges)  # slopes x/z (or y/z) of the two edges
        inside &= (along - low * z) / math.hypot(1.0, low) >= -radius
        inside &= (high * z - along) / math.hypot(1.0, high) >= -radius
    return np.where(inside, z - radius, np.inf).min(axis=-1)


def _height_clearance(phantom: str, frame: TissueFrame, points: np.ndarray) -> np.ndarray:
    """First-order signed distance (m) of points (..., 3) above the undeformed surface."""
    u, v, w = frame.to_tissue(points)
    du, dv = height_gradient(phantom, u, v)
    return frame.scale * (w - phantom_height(phantom, u, v)) / np.sqrt(1.0 + du * du + dv * dv)


def _placement_ok(phantom, frame, camera, params, u, v, axis, checks, far_h: float = 0.0) -> bool:
    """Whether the tool at target (u, v) with this axis is clear of the tissue in every checked state.

    The target surface must face the camera. ``checks`` is a list of (h, pull, jaw, in_view):
    while hovering (h > 0) no jaw tip comes within ``_JAW_CLEARANCE_M`` of the tissue; in every
    state the wrist and shaft keep ``_CLEARANCE_M`` from the tissue (the undeformed surface,
    lowered by the dent when pressing) and the far end of the shaft lies outside the image; states
    with in_view also keep the tip inside the central image region and, when not pressing, in the
    camera's line of sight. In every state, at every gap from the deepest press up to ``far_h`` (the
    largest the tool backs off to there) and along the pull, no visible part of the tool comes nearer
    the camera than ``near_limit_m``.
    """
    n = surface_normals(phantom, frame, u, v)
    if -float(axis @ n) < _MIN_COS_AXIS:
        return False
    q = surface_points(phantom, frame, u, v)
    if -float(n @ q) / float(np.linalg.norm(q)) < _MIN_COS_VIEW:
        return False
    size = np.array([camera.width, camera.height])
    for h, pull, jaw, in_view in checks:
        c, q, _, _ = _tool_centres(phantom, frame, params, np.array(u), np.array(v), np.array(h), np.array(pull), axis)
        if h > 0:  # not touching yet: no jaw (open or not) may reach the tissue
            _, _, tips = _jaw_geometry(params, c, axis, n, np.array(jaw))
            if np.any(_height_clearance(phantom, frame, tips) < params.jaw_radius_m + _JAW_CLEARANCE_M):
                return False
        pts, radius = _tool_samples(params, c, axis)
        clearance = _height_clearance(phantom, frame, pts)
        if h < 0:  # the dent lowers the tissue around the tip
            rel = pts - q
            lateral = np.linalg.norm(rel - np.outer(rel @ n, n), axis=1)
            beyond = np.maximum(lateral - params.jaw_radius_m, 0.0)
            clearance = clearance + (-h) * np.exp(-0.5 * (beyond / params.dent_sigma_m) ** 2)
        if np.any(clearance < radius + _CLEARANCE_M):
            return False
        far_end = pts[-1]
        if far_end[2] > 0.01:
            end_px = camera.project(far_end)
            if np.all(end_px >= 0) and np.all(end_px < size):
                return False
        if in_view:
            px = camera.project(c)
            if np.any(px < _TIP_VIEW_MARGIN * size) or np.any(px > (1 - _TIP_VIEW_MARGIN) * size):
                return False
            if h >= 0:
                sight = np.linspace(0.0, 1.0 - 0.004 / np.linalg.norm(c), 40)[1:, None] * c  # camera -> tip
                if np.any(_height_clearance(phantom, frame, sight) < 0):
                    return False
        if nearest_in_view_m(params, camera, c, axis) < near_limit_m(params):
            return False
    # What parts are in view changes along the way: every gap from the deepest press to far_h, every pull.
    gaps = [h for h, _, _, _ in checks] + [far_h]
    h = np.concatenate([np.linspace(min(gaps), max(gaps), _GAP_STEPS), np.zeros(_GAP_STEPS)])
    pull = np.concatenate([np.zeros(_GAP_STEPS), np.linspace(0.0, max(p for _, p, _, _ in checks), _GAP_STEPS)])
    c, _, _, _ = _tool_centres(phantom, frame, params, np.full_like(h, u), np.full_like(h, v), h, pull, axis[None, :])
    return bool(np.all(nearest_in_view_m(params, camera, c, axis[None, :]) >= near_limit_m(params)))


def _move_near_ok(phantom, frame, camera, params, start: _State, end: _State) -> bool:
    """Whether no visible part of the tool comes nearer the camera than ``near_limit_m`` while it moves
    from ``start`` to ``end`` (eased as ``_sample_segments`` moves it)."""
    s = _ease(np.linspace(0.0, 1.0, _MOVE_STEPS + 1)[1:])
    at = {k: getattr(start, k) + (getattr(end, k) - getattr(start, k)) * s for k in ("u", "v", "h", "pull")}
    axis = start.axis[None, :] * (1 - s[:, None]) + end.axis[None, :] * s[:, None]
    axis = with_elevation(axis / np.linalg.norm(axis, axis=1, keepdims=True), frame, params.shaft_elevation_deg)
    c, _, _, _ = _tool_centres(phantom, frame, params, at["u"], at["v"], at["h"], at["pull"], axis)
    return bool(np.all(nearest_in_view_m(params, camera, c, axis) >= near_limit_m(params)))


def with_elevation(axis: np.ndarray, frame: TissueFrame, elevation_deg: float | None) -> np.ndarray:
    """Unit shaft axes (..., 3) turned about the base plane so that the shaft rises ``elevation_deg``
    above the tissue base plane (toward the camera side) while keeping its direction within the plane;
    None returns ``axis`` unchanged."""
    if elevation_deg is None:
        return axis
    axis = np.asarray(axis, dtype=np.float64)
    level = axis - (axis @ frame.normal)[..., None] * frame.normal
    level /= np.linalg.norm(level, axis=-1, keepdims=True)
    angle = math.radians(elevation_deg)
    return math.cos(angle) * level - math.sin(angle) * frame.normal  # toward the tip: into the tissue


def mean_tool_axis(phantom: str, mirrored: bool = False) -> np.ndarray:
    """The phantom's mean unit shaft axis (toward the tip); ``mirrored``: its mirror image about the image's
    vertical midline (a second instrument entering from the other side)."""
    mean_axis = np.asarray(LAYOUTS[phantom].tool_axis, dtype=np.float64)
    mean_axis /= np.linalg.norm(mean_axis)
    if mirrored:
        mean_axis = mean_axis * np.array([-1.0, 1.0, 1.0])
    return mean_axis


def _draw_target(rng, phantom, frame, camera, params, checks, mean_axis=None, box=None, accept=None, far_h=0.0,
                 arrive=None):
    """A reachable target (u, v) and tool axis for one cycle (``_placement_ok`` with ``checks`` and ``far_h``).

    ``mean_axis`` and ``box`` (u_min, u_max, v_min, v_max) default to the phantom's; ``accept(u, v)``
    (optional) can veto a target before the placement checks; ``arrive`` = (state, h) (optional): the
    move from that state to gap h above the target keeps the tool as far from the camera as
    ``_placement_ok`` does (``_move_near_ok``). With ``params.shaft_elevation_deg`` the drawn axis is
    turned to that elevation.
    """
    layout = LAYOUTS[phantom]
    if mean_axis is None:
        mean_axis = mean_tool_axis(phantom)
    u_min, u_max, v_min, v_max = layout.target_box_m if box is None else box
    for _ in range(_MAX_TARGET_TRIES):
        u = float(rng.uniform(u_min, u_max))
        v = float(rng.uniform(v_min, v_max))
        axis = mean_axis + rng.normal(0.0, _AXIS_JITTER, 3)
        axis /= np.linalg.norm(axis)
        axis = with_elevation(axis, frame, params.shaft_elevation_deg)
        if phantom_height(phantom, np.array(u), np.array(v)) < layout.target_min_height_m:
            continue
        if accept is not None and not accept(u, v):
            continue
        if _placement_ok(phantom, frame, camera, params, u, v, axis, checks, far_h) and (
                arrive is None or _move_near_ok(phantom, frame, camera, params, arrive[0],
                                                _State(u, v, arrive[1], 0.0, arrive[0].jaw, axis))):
            return u, v, axis
    flat = ""
    if params.shaft_elevation_deg is not None:
        flat = (f" with the shaft {params.shaft_elevation_deg:g} deg above the tissue plane (a flat shaft only reaches "
                f"slopes facing it; the broad liver needs about 30 deg)")
    near = ""
    if params.scene_scale < 1:
        near = (f" with the camera's {params.fov_deg:.3g} deg at {params.tissue_distance_m * 1e3:.3g} mm (the phantom "
                f"shrinks to {params.scene_scale:.2f} of its size, the instruments keep theirs and stay "
                f"{near_limit_m(params) * 1e3:.3g} mm from the camera; a wider view or a longer working distance "
                f"leaves more room)")
    raise RuntimeError(
        f"synth: found no reachable tool target on phantom {phantom!r}{flat}{near} in {_MAX_TARGET_TRIES} tries")


def scaled(span: tuple[float, float], params: SynthParams) -> tuple[float, float]:
    """A range of gaps or heights (m) at the session's ``gap_scale``, m."""
    return span[0] * params.gap_scale, span[1] * params.gap_scale


def _plan_segments(params: SynthParams, rng: np.random.Generator) -> list[_Segment]:
    """Motion segments (cycles of approach/hover/press/hold/[pull]/retract) covering all frames."""
    phantom, fps = params.phantom, params.fps
    frame, camera = tissue_frame(params), stereo_camera(params)
    grasping = params.task == "pulling"
    open_rad = math.radians(params.jaw_open_deg) if grasping else 0.0

    def frames_of(span: tuple[float, float]) -> int:
        return max(1, round(rng.uniform(*span) * fps))

    def wobble_args(amplitude: float) -> dict:
        hz, phase = float(rng.uniform(*_WOBBLE_HZ)), float(rng.uniform(0, 2 * np.pi))
        return {"wobble": amplitude, "wobble_hz": hz, "wobble_phase": phase}

    def checks_of(start_gap: float, hover: float, pull: float) -> list[tuple[float, float, float, bool]]:
        if grasping:
            return [(start_gap, 0.0, open_rad, False), (hover, 0.0, open_rad, True),
                    (-params.grasp_squeeze_m[1], 0.0, 0.0, True), (0.0, pull, 0.0, True)]
        return [(start_gap, 0.0, 0.0, False), (hover, 0.0, 0.0, True), (-params.press_depth_m[1], 0.0, 0.0, True)]

    start_gaps, hover_gaps = scaled(params.start_gap_m, params), scaled(params.hover_gap_m, params)
    segments: list[_Segment] = []
    total, cycle, prev = 0, 0, None
    while total < params.frames:
        start_gap = float(rng.uniform(*start_gaps))
        hover = float(rng.uniform(*hover_gaps))
        if grasping:
            depth = float(rng.uniform(*params.grasp_squeeze_m))
            pull = float(rng.uniform(*scaled(params.pull_height_m, params)))
        else:
            light = cycle > 0 and rng.uniform() < params.light_press_prob
            depth = float(rng.uniform(*(params.light_press_depth_m if light else params.press_depth_m)))
            pull = 0.0
        shrink = 1.0  # where no target has room for the gaps drawn (a close camera), they are halved
        while True:
            try:
                u, v, axis = _draw_target(rng, phantom, frame, camera, params, checks_of(start_gap, hover, pull),
                                          far_h=start_gaps[1] * shrink, arrive=None if prev is None else (prev, hover))
                break
            except RuntimeError:
                if shrink < 0.5 ** (_GAP_HALVINGS - 1):
                    raise
                shrink, start_gap, hover, pull = 0.5 * shrink, 0.5 * start_gap, 0.5 * hover, 0.5 * pull
        if prev is None:
            prev = _State(u, v, start_gap, 0.0, open_rad, axis)
        hover_state = _State(u, v, hover, 0.0, open_rad, axis)
        pressed = _State(u, v, -depth, 0.0, 0.0, axis)
        segs = [
            _Segment("approach", frames_of(params.approach_s), prev, hover_state, False, 0.0, 0.0, 0.0),
            _Segment("approach", frames_of(params.hover_s), hover_state, hover_state, False,
                     **wobble_args(params.hover_wobble * hover)),
            _Segment("press", frames_of(params.press_s), hover_state, pressed, grasping, 0.0, 0.0, 0.0),
        ]
        if grasping:
            pulled = _State(u, v, 0.0, pull, 0.0, axis)
            segs += [
                _Segment("pull", frames_of(params.pull_s), pressed, pulled, True, 0.0, 0.0, 0.0),
                _Segment("hold", frames_of(params.hold_s), pulled, pulled, True, 0.0, 0.0, 0.0),
            ]
            last = pulled
        else:
            hold_frames = frames_of(params.hold_s)
            segs.append(_Segment("hold", hold_frames, pressed, pressed, False, **wobble_args(_HOLD_TREMOR * depth)))
            last = pressed
        retracted = _State(u, v, float(rng.uniform(*start_gaps)) * shrink, 0.0, open_rad, axis)
        segs.append(_Segment("retract", frames_of(params.retract_s), last, retracted, False, 0.0, 0.0, 0.0))
        segments += segs
        total += sum(s.frames for s in segs)
        prev, cycle = retracted, cycle + 1
    return segments


def _sample_segments(segments: list[_Segment], frames: int, fps: int) -> dict[str, np.ndarray]:
    """Per-frame motion state arrays from the segments (first ``frames`` frames)."""
    keys = ("u", "v", "h", "pull", "jaw")
    out: dict[str, list] = {k: [] for k in (*keys, "axis", "attached", "phase")}
    for seg in segments:
        tau = np.arange(seg.frames) / seg.frames
        s = _ease(tau)
        for k in keys:
            a, b = getattr(seg.start, k), getattr(seg.end, k)
            out[k].append(a + (b - a) * s)
        out["h"][-1] = out["h"][-1] + seg.wobble * np.sin(np.pi * tau) * np.sin(
            2 * np.pi * seg.wobble_hz * tau * seg.frames / fps + seg.wobble_phase
        )
        axis = seg.start.axis[None, :] * (1 - s[:, None]) + seg.end.axis[None, :] * s[:, None]
        out["axis"].append(axis / np.linalg.norm(axis, axis=1, keepdims=True))
        out["attached"].append(np.full(seg.frames, seg.attached))
        out["phase"].append(np.full(seg.frames, seg.phase, dtype=object))
    return {k: np.concatenate(v)[:frames] for k, v in out.items()}


def plan_tool_track(params: SynthParams) -> ToolTrack:
    """The tool motion, tissue deformation and truth of every frame (pure: depends on params only).

    Truth: the gap is the distance from the lower jaw-tip sphere to the undeformed surface; the
    indentation is how far the tip sits below it (palpation), or the tissue displacement while
    grasped (pulling, where the tissue follows the jaws and the gap is 0). Contact is
    indentation > 0, and then the gap is exactly 0.
    """
    rng = stream_rng(params, STREAM_MOTION)
    st = _sample_segments(_plan_segments(params, rng), params.frames, params.fps)
    if params.shaft_elevation_deg is not None:  # exact at every frame, not only at the keyframes
        st["axis"] = with_elevation(st["axis"], tissue_frame(params), params.shaft_elevation_deg)
    return track_from_states(params, st)


def track_from_states(params: SynthParams, st: dict[str, np.ndarray], offset_m: np.ndarray | None = None) -> ToolTrack:
    """The ToolTrack of per-frame motion states ``st`` (arrays u, v, h, pull, jaw, axis, attached, phase
    over F frames, as ``_sample_segments`` gives them); ``offset_m`` (F, 3) optionally moves the whole
    tool (used to make instrument 2 follow instrument 1). Truth as in ``plan_tool_track``."""
    phantom, frame = params.phantom, tissue_frame(params)
    axis = st["axis"]
    c, q, n, pull_dir = _tool_centres(phantom, frame, params, st["u"], st["v"], st["h"], st["pull"], axis)
    if offset_m is not None:
        c = c + offset_m
    hinge, bases, tips = _jaw_geometry(params, c, axis, n, st["jaw"])

    # Geometry of contact: where the tool would be without the pull (the grasped tissue moves with it).
    attached = st["attached"]
    pull_vec = np.where(attached[:, None], st["pull"][:, None] * pull_dir, 0.0)
    tips_rest = tips - pull_vec[:, None, :]
    closest, normals, signed, _ = closest_surface_points(phantom, frame, tips_rest.reshape(-1, 3))
    signed = signed.reshape(-1, 2)
    low = np.argmin(signed, axis=1)
    rows = np.arange(len(low))
    sd = signed[rows, low]
    q_low = closest.reshape(-1, 2, 3)[rows, low]
    n_low = normals.reshape(-1, 2, 3)[rows, low]
    press = np.maximum(params.jaw_radius_m - sd, 0.0)
    gap_geo = np.maximum(sd - params.jaw_radius_m, 0.0)

    # Centre the dent below the midpoint of the jaws so both tips sit in its flat bottom.
    offset = (c - pull_vec) - tips_rest[rows, low]
    offset -= np.sum(offset * n_low, axis=1, keepdims=True) * n_low
    dent_center = q_low + offset
    dent_flat = np.linalg.norm(offset, axis=1) + 0.5 * params.jaw_radius_m

    held = attached & ((press > 0) | (st["pull"] > 0))
    pull_vec = np.where(held[:, None], pull_vec, 0.0)
    contact = (press > 0) | held
    disp = -press[:, None] * n_low + pull_vec
    indentation = np.where(contact, np.linalg.norm(disp, axis=1), 0.0)
    gap = np.where(contact, 0.0, gap_geo)
    force = params.stiffness_n_per_m * press[:, None] * n_low - params.pull_stiffness_n_per_m * pull_vec

    phase = st["phase"].copy()
    phase[(phase == "press") & ~contact] = "approach"
    return ToolTrack(
        timestamp_s=np.arange(len(c), dtype=np.float64) / params.fps,
        tip_center_m=c,
        axis=axis,
        hinge_m=hinge,
        jaw_bases_m=bases,
        jaw_tips_m=tips,
        dent_center_m=dent_center,
        dent_normal=n_low,
        dent_flat_m=dent_flat,
        press_m=press,
        pull_m=pull_vec,
        gap_m=gap,
        indentation_m=indentation,
        force_true_n=force,
        contact=contact,
        phase=phase.astype(str),
    )


def tissue_displacement(points_m: np.ndarray, track: ToolTrack, index: int, params: SynthParams) -> np.ndarray:
    """Displacement (N, 3), m, of undeformed tissue points (N, 3) in frame ``index``.

    Pressing: a dent along -normal with a flat bottom (radius ``dent_flat_m``, holding both jaws)
    and a Gaussian flank of width ``dent_sigma_m``. Pulling: a tent along the pull vector,
    (1 + x) exp(-x) with x = distance beyond the flat bottom / ``tent_length_m``.
    """
    p = np.asarray(points_m, dtype=np.float64)
    press = float(track.press_m[index])
    pull = track.pull_m[index]
    out = np.zeros_like(p)
    if press <= 0 and not np.any(pull):
        return out
    rho = np.linalg.norm(p - track.dent_center_m[index], axis=-1)
    beyond = np.maximum(rho - track.dent_flat_m[index], 0.0)
    if press > 0:
        out -= (press * np.exp(-0.5 * (beyond / params.dent_sigma_m) ** 2))[:, None] * track.dent_normal[index]
    if np.any(pull):
        x = beyond / params.tent_length_m
        out += ((1.0 + x) * np.exp(-x))[:, None] * pull
    return out


def tissue_displacement_frames(points_m: np.ndarray, track: ToolTrack, frames: np.ndarray,
                               params: SynthParams) -> np.ndarray:
    """``tissue_displacement`` for many frames at once: points (N, P, 3) of frames ``frames`` (N,)
    -> displacements (N, P, 3), m (the same dent and tent)."""
    p = np.asarray(points_m, dtype=np.float64)
    frames = np.asarray(frames)
    press = track.press_m[frames][:, None]
    pull = track.pull_m[frames][:, None, :]
    rho = np.linalg.norm(p - track.dent_center_m[frames][:, None, :], axis=-1)
    beyond = np.maximum(rho - track.dent_flat_m[frames][:, None], 0.0)
    dent = press * np.exp(-0.5 * (beyond / params.dent_sigma_m) ** 2)
    out = -dent[..., None] * track.dent_normal[frames][:, None, :]
    x = beyond / params.tent_length_m
    return out + ((1.0 + x) * np.exp(-x))[..., None] * pull
