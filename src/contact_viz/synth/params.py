"""The parameters of a synthetic session (``SynthParams``) and its seeded random streams."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from contact_viz.params import check_fields, checked


PHANTOMS: tuple[str, ...] = ("cup", "kidney", "liver", "glove")
PHASES: tuple[str, ...] = ("approach", "press", "hold", "retract", "pull")

REFERENCE_WIDTH_PX = 1920  # image width at which the px-valued noise parameters are given, px
# Tissue distance and horizontal field of view the phantoms were designed at (the default camera's), m and
# deg: a camera that sees a narrower strip of the base plane sees them shrunk (SynthParams.scene_scale).
DESIGN_DISTANCE_M, DESIGN_FOV_DEG = 0.09, 80.0
# Tissue distance (at DESIGN_FOV_DEG) down to which the gaps keep their sizes, m: a camera that sees a
# narrower strip sees them shrunk (SynthParams.gap_scale). At 50 mm the default scene's gaps still fit
# between tissue and camera: its instruments stay 25 mm or more from the camera, as on real da Vinci frames.
GAP_DISTANCE_M = 0.05


def seen_half_width_m(distance_m: float, fov_deg: float) -> float:
    """Half the width of the plane at ``distance_m`` that a camera with this horizontal field of view
    sees on its axis, m."""
    return distance_m * math.tan(math.radians(fov_deg) / 2)

# Independent random streams, each seeded by (seed, stream, phantom[, frame]): changing how much one
# part draws never changes another part.
STREAM_MOTION, STREAM_TEXTURE, STREAM_DEPTH, STREAM_FORCE, STREAM_LABELS = 101, 202, 303, 404, 505
STREAM_MOTION_2 = 606  # the second instrument's motion (tools=2): instrument 1's streams stay as they are


def stream_rng(params: SynthParams, stream: int, *more: int) -> np.random.Generator:
    """The random generator of one stream of a session."""
    return np.random.default_rng([params.seed, stream, PHANTOMS.index(params.phantom), *more])


@dataclass(frozen=True)
class SynthParams:
    """Everything that defines a synthetic session; the same params give the same files.

    Pairs ``(lo, hi)`` are ranges that a value is drawn from uniformly, per cycle or per blob.
    """

    phantom: str = checked("cup", choices=PHANTOMS)  # tissue phantom, one of PHANTOMS ("glove" is a pulling task), -
    frames: int = checked(120, ge=1)  # number of frames, count
    seed: int = checked(0, ge=0)  # seed of every random choice, -
    width: int = checked(1920, ge=32)  # image width, px
    height: int = checked(1080, ge=32)  # image height, px
    fps: int = checked(30, ge=1)  # frame rate, 1/s
    fov_deg: float = checked(80.0, ge=30, le=120)  # horizontal field of view, deg
    baseline_m: float = checked(0.005, gt=0)  # stereo baseline (right camera at +x), m
    # distance from the camera to the tissue base plane along z (the working distance), m
    tissue_distance_m: float = checked(0.09, gt=0)
    # tilt of the base plane about the camera x axis (top recedes), deg
    tissue_tilt_deg: float = checked(30.0, ge=0, lt=60)
    shaft_diameter_m: float = checked(0.008, gt=0)  # instrument shaft diameter, m
    jaw_radius_m: float = checked(0.0018, gt=0)  # radius of each of the two rounded jaws, m
    jaw_length_m: float = checked(0.009, gt=0)  # hinge-to-tip length of the jaws, m
    wrist_radius_m: float = checked(0.0031, gt=0)  # radius of the dark wrist between jaws and shaft, m
    wrist_length_m: float = checked(0.009, gt=0)  # length of the wrist, m
    jaw_open_deg: float = checked(22.0, ge=0)  # opening of each jaw while approaching to grasp (glove), deg
    # tissue stiffness under the tip: force = stiffness x indentation, N/m
    stiffness_n_per_m: float = checked(1400.0, gt=0)
    pull_stiffness_n_per_m: float = checked(150.0, gt=0)  # tension per metre of tenting when pulling the glove, N/m
    force_noise_n: float = checked(0.08, ge=0)  # force sensor noise, standard deviation per axis, N
    press_depth_m: tuple[float, float] = checked((0.0025, 0.0042), ge=0, pair=True)  # indentation of a firm press, m
    # indentation of a light touch, m
    light_press_depth_m: tuple[float, float] = checked((0.0004, 0.0013), ge=0, pair=True)
    light_press_prob: float = checked(0.3, ge=0, le=1)  # chance that a press after the first is a light touch, -
    # gap while hovering before a press, m (times gap_scale)
    hover_gap_m: tuple[float, float] = checked((0.002, 0.010), ge=0, pair=True)
    # gap where an approach starts / a retract ends, m (times gap_scale)
    start_gap_m: tuple[float, float] = checked((0.012, 0.022), ge=0, pair=True)
    # indentation when the jaws grasp (glove), m
    grasp_squeeze_m: tuple[float, float] = checked((0.0006, 0.0012), ge=0, pair=True)
    # how far the grasped surface is pulled (glove), m (times gap_scale)
    pull_height_m: tuple[float, float] = checked((0.005, 0.014), ge=0, pair=True)
    dent_sigma_m: float = checked(0.006, gt=0)  # Gaussian width of the dent around the tip, m
    tent_length_m: float = checked(0.005, gt=0)  # decay length of the tent around the grasped point, m
    approach_s: tuple[float, float] = checked((0.5, 0.9), ge=0, pair=True)  # duration of the approach move, s
    hover_s: tuple[float, float] = checked((0.2, 0.5), ge=0, pair=True)  # duration of the hover, s
    # duration of the press (hover to full indentation), s
    press_s: tuple[float, float] = checked((0.25, 0.45), ge=0, pair=True)
    hold_s: tuple[float, float] = checked((0.3, 0.8), ge=0, pair=True)  # duration of the hold, s
    pull_s: tuple[float, float] = checked((0.4, 0.7), ge=0, pair=True)  # duration of the pull (glove), s
    retract_s: tuple[float, float] = checked((0.35, 0.6), ge=0, pair=True)  # duration of the retract, s
    hover_wobble: float = checked(0.2, ge=0)  # amplitude of the slow gap variation while hovering, fraction of the gap
    disparity_noise_px: float = checked(0.25, ge=0)  # stereo disparity noise, std at REFERENCE_WIDTH_PX image width, px
    specular_hole_threshold: float = checked(0.4, gt=0)  # sharp specular radiance above which stereo fails (hole), -
    # mean number of random hole blobs per depth frame (>= 1 if this is >= 1), count
    hole_blob_count: float = checked(5.0, ge=0)
    # radius of a hole blob, fraction of width
    hole_blob_radius_frac: tuple[float, float] = checked((0.005, 0.018), ge=0, pair=True)
    edge_fattening_px: float = checked(2.0, ge=0)  # tool depth bleeding past its silhouette, at REFERENCE_WIDTH_PX, px
    # depth margin for calling a left pixel occluded in the right view, m
    occlusion_tolerance_m: float = checked(0.001, gt=0)
    label_jitter_frames: int = checked(1, ge=0)  # largest shift of a manual label boundary (glove labels.csv), frames
    raycast_step_px: int = checked(4, ge=1)  # adaptive ray caster lattice at REFERENCE_WIDTH_PX (1 = ray per pixel), px
    mesh_cell_px: float = checked(14.0, gt=0)  # tissue mesh cell size as seen at tissue_distance_m (at most 2 mm), px
    jpeg_quality: int = checked(92, ge=0, le=100)  # JPEG quality of the left/right images, 0-100
    # instruments in the scene: 1, or 2 (the second one works beside the first; see synth.second), count
    tools: int = checked(1, ge=1, le=2)
    # angle of every shaft above the tissue base plane (e.g. 8 = lying nearly flat), deg; None: drawn per
    # cycle around the phantom's mean tool axis (about 35-40 deg)
    shaft_elevation_deg: float | None = checked(None, gt=0, lt=90)

    def __post_init__(self) -> None:
        check_fields(self)
        if self.hover_gap_m[0] <= 0 or self.start_gap_m[0] < self.hover_gap_m[1]:
            raise ValueError("SynthParams needs 0 < hover_gap_m and start_gap_m >= hover_gap_m (approach moves in)")
        if self.press_depth_m[0] <= 0 or self.light_press_depth_m[0] <= 0 or self.grasp_squeeze_m[0] <= 0:
            raise ValueError("SynthParams.press_depth_m, light_press_depth_m and grasp_squeeze_m must be > 0")

    @property
    def scene_scale(self) -> float:
        """Size of the phantom relative to its design: the width of the base plane the camera sees on its
        axis, ``tissue_distance_m tan(fov_deg / 2)``, over the design camera's (DESIGN_DISTANCE_M,
        DESIGN_FOV_DEG), at most 1. The phantom (its shape, texture and where the tool works on it) scales
        by it, so a nearer or narrower camera sees the same phantom filling the same part of the image;
        the instruments, the press depths and the tissue's give keep their sizes."""
        seen = seen_half_width_m(self.tissue_distance_m, self.fov_deg)
        return min(1.0, seen / seen_half_width_m(DESIGN_DISTANCE_M, DESIGN_FOV_DEG))

    @property
    def gap_scale(self) -> float:
        """Size of the gaps relative to the fields: the width of the base plane the camera sees on its
        axis over what the design's field of view sees at GAP_DISTANCE_M, at most 1. ``hover_gap_m``,
        ``start_gap_m``, ``pull_height_m`` and the second instrument's heights above the tissue scale
        by it: nearer, there is no room for them between tissue and camera, and in a narrower view an
        instrument backing off that far leaves it."""
        seen = seen_half_width_m(self.tissue_distance_m, self.fov_deg)
        return min(1.0, seen / seen_half_width_m(GAP_DISTANCE_M, DESIGN_FOV_DEG))

    @property
    def task(self) -> str:
        """``"pulling"`` for the glove, ``"palpation"`` otherwise."""
        return "pulling" if self.phantom == "glove" else "palpation"
