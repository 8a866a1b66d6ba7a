"""The parameters of a synthetic session (``SynthParams``) and its seeded random streams."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np




PHANTOMS: tuple[str, ...] = ("cup", "kidney", "liver", "glove")
PHASES: tuple[str, ...] = ("approach", "press", "hold", "retract", "pull")

REFERENCE_WIDTH_PX = 1920  # image width at which the px-valued noise parameters are given, px

# Independent random streams, each seeded by (seed, stream, phantom[, frame]): changing how much one
# part draws never changes another part.
STREAM_MOTION, STREAM_TEXTURE, STREAM_DEPTH, STREAM_FORCE, STREAM_LABELS = 101, 202, 303, 404, 505


def stream_rng(params: SynthParams, stream: int, *more: int) -> np.random.Generator:
    """The random generator of one stream of a session."""
    return np.random.default_rng([params.seed, stream, PHANTOMS.index(params.phantom), *more])


_RANGE_FIELDS = (
    "press_depth_m",
    "light_press_depth_m",
    "hover_gap_m",
    "start_gap_m",
    "grasp_squeeze_m",
    "pull_height_m",
    "approach_s",
    "hover_s",
    "press_s",
    "hold_s",
    "pull_s",
    "retract_s",
    "hole_blob_radius_frac",
)


@dataclass(frozen=True)
class SynthParams:
    """Everything that defines a synthetic session; the same params give the same files.

    Pairs ``(lo, hi)`` are ranges that a value is drawn from uniformly, per cycle or per blob.
    """

    phantom: str = "cup"  # tissue phantom, one of PHANTOMS ("glove" is a pulling task), -
    frames: int = 120  # number of frames, count
    seed: int = 0  # seed of every random choice, -
    width: int = 1920  # image width, px
    height: int = 1080  # image height, px
    fps: int = 30  # frame rate, 1/s
    fov_deg: float = 80.0  # horizontal field of view, deg
    baseline_m: float = 0.005  # stereo baseline (right camera at +x), m
    tissue_distance_m: float = 0.09  # distance from the camera to the tissue base plane along z, m
    tissue_tilt_deg: float = 30.0  # tilt of the base plane about the camera x axis (top recedes), deg
    shaft_diameter_m: float = 0.008  # instrument shaft diameter, m
    jaw_radius_m: float = 0.0018  # radius of each of the two rounded jaws, m
    jaw_length_m: float = 0.009  # hinge-to-tip length of the jaws, m
    wrist_radius_m: float = 0.0031  # radius of the dark wrist between jaws and shaft, m
    wrist_length_m: float = 0.009  # length of the wrist, m
    jaw_open_deg: float = 22.0  # opening of each jaw while approaching to grasp (glove), deg
    stiffness_n_per_m: float = 1400.0  # tissue stiffness under the tip: force = stiffness x indentation, N/m
    pull_stiffness_n_per_m: float = 150.0  # tension per metre of tenting when pulling the glove, N/m
    force_noise_n: float = 0.08  # force sensor noise, standard deviation per axis, N
    press_depth_m: tuple[float, float] = (0.0025, 0.0042)  # indentation of a firm press, m
    light_press_depth_m: tuple[float, float] = (0.0004, 0.0013)  # indentation of a light touch, m
    light_press_prob: float = 0.3  # chance that a press after the first is a light touch, -
    hover_gap_m: tuple[float, float] = (0.002, 0.010)  # gap while hovering before a press, m
    start_gap_m: tuple[float, float] = (0.012, 0.022)  # gap where an approach starts / a retract ends, m
    grasp_squeeze_m: tuple[float, float] = (0.0006, 0.0012)  # indentation when the jaws grasp (glove), m
    pull_height_m: tuple[float, float] = (0.005, 0.014)  # how far the grasped surface is pulled (glove), m
    dent_sigma_m: float = 0.006  # Gaussian width of the dent around the tip, m
    tent_length_m: float = 0.005  # decay length of the tent around the grasped point, m
    approach_s: tuple[float, float] = (0.5, 0.9)  # duration of the approach move, s
    hover_s: tuple[float, float] = (0.2, 0.5)  # duration of the hover, s
    press_s: tuple[float, float] = (0.25, 0.45)  # duration of the press (hover to full indentation), s
    hold_s: tuple[float, float] = (0.3, 0.8)  # duration of the hold, s
    pull_s: tuple[float, float] = (0.4, 0.7)  # duration of the pull (glove), s
    retract_s: tuple[float, float] = (0.35, 0.6)  # duration of the retract, s
    hover_wobble: float = 0.2  # amplitude of the slow gap variation while hovering, fraction of the gap
    disparity_noise_px: float = 0.25  # stereo disparity noise, std at REFERENCE_WIDTH_PX image width, px
    specular_hole_threshold: float = 0.4  # sharp specular radiance above which stereo fails (hole), -
    hole_blob_count: float = 5.0  # mean number of random hole blobs per depth frame (>= 1 if this is >= 1), count
    hole_blob_radius_frac: tuple[float, float] = (0.005, 0.018)  # radius of a hole blob, fraction of width
    edge_fattening_px: float = 2.0  # tool depth bleeding past its silhouette, at REFERENCE_WIDTH_PX, px
    occlusion_tolerance_m: float = 0.001  # depth margin for calling a left pixel occluded in the right view, m
    label_jitter_frames: int = 1  # largest shift of a manual label boundary (glove labels.csv), frames
    raycast_step_px: int = 4  # adaptive ray caster lattice at REFERENCE_WIDTH_PX (1 = ray per pixel), px
    mesh_cell_px: float = 14.0  # tissue mesh cell size as seen at tissue_distance_m (at most 2 mm), px
    jpeg_quality: int = 92  # JPEG quality of the left/right images, 0-100

    def __post_init__(self) -> None:
        for name in _RANGE_FIELDS:  # JSON round trips give lists: store tuples
            value = getattr(self, name)
            if not (isinstance(value, (tuple, list)) and len(value) == 2):
                raise ValueError(f"SynthParams.{name} must be a (lo, hi) pair, got {value!r}")
            lo, hi = float(value[0]), float(value[1])
            if not 0 <= lo <= hi:
                raise ValueError(f"SynthParams.{name} must satisfy 0 <= lo <= hi, got {value!r}")
            object.__setattr__(self, name, (lo, hi))
        if self.phantom not in PHANTOMS:
            raise ValueError(f"SynthParams.phantom must be one of {PHANTOMS}, got {self.phantom!r}")
        for name, low in (("frames", 1), ("width", 32), ("height", 32), ("fps", 1), ("raycast_step_px", 1)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"SynthParams.{name} must be an integer >= {low}, got {value!r}")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool) or self.seed < 0:
            raise ValueError(f"SynthParams.seed must be a non-negative integer, got {self.seed!r}")
        if not 30.0 <= self.fov_deg <= 120.0:
            raise ValueError(f"SynthParams.fov_deg must be in [30, 120], got {self.fov_deg!r}")
        if not 0.0 <= self.tissue_tilt_deg < 60.0:
            raise ValueError(f"SynthParams.tissue_tilt_deg must be in [0, 60), got {self.tissue_tilt_deg!r}")
        positive = (
            "baseline_m", "tissue_distance_m", "shaft_diameter_m", "jaw_radius_m", "jaw_length_m",
            "wrist_radius_m", "wrist_length_m", "stiffness_n_per_m", "pull_stiffness_n_per_m",
            "dent_sigma_m", "tent_length_m", "mesh_cell_px", "occlusion_tolerance_m",
        )
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"SynthParams.{name} must be > 0, got {getattr(self, name)!r}")
        non_negative = (
            "force_noise_n", "disparity_noise_px", "hole_blob_count", "edge_fattening_px",
            "jaw_open_deg", "hover_wobble",
        )
        for name in non_negative:
            if not getattr(self, name) >= 0:
                raise ValueError(f"SynthParams.{name} must be >= 0, got {getattr(self, name)!r}")
        if not 0.0 <= self.light_press_prob <= 1.0:
            raise ValueError(f"SynthParams.light_press_prob must be in [0, 1], got {self.light_press_prob!r}")
        if not self.specular_hole_threshold > 0:
            raise ValueError(f"SynthParams.specular_hole_threshold must be > 0, got {self.specular_hole_threshold!r}")
        if not isinstance(self.label_jitter_frames, int) or self.label_jitter_frames < 0:
            raise ValueError(
                f"SynthParams.label_jitter_frames must be an integer >= 0, got {self.label_jitter_frames!r}"
            )
        if not isinstance(self.jpeg_quality, int) or not 0 <= self.jpeg_quality <= 100:
            raise ValueError(f"SynthParams.jpeg_quality must be an integer in [0, 100], got {self.jpeg_quality!r}")
        if self.hover_gap_m[0] <= 0 or self.start_gap_m[0] < self.hover_gap_m[1]:
            raise ValueError("SynthParams needs 0 < hover_gap_m and start_gap_m >= hover_gap_m (approach moves in)")
        if self.press_depth_m[0] <= 0 or self.light_press_depth_m[0] <= 0 or self.grasp_squeeze_m[0] <= 0:
            raise ValueError("SynthParams.press_depth_m, light_press_depth_m and grasp_squeeze_m must be > 0")

    @property
    def task(self) -> str:
        """``"pulling"`` for the glove, ``"palpation"`` otherwise."""
        return "pulling" if self.phantom == "glove" else "palpation"
