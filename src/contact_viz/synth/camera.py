"""Named stereo cameras for synthetic sessions (``contact-viz synth --camera NAME``): field of view,
baseline and working distance, and what a session records of its camera.

``default`` is the camera of a session made without camera options (80 deg, 5 mm, 90 mm).
``davinci`` is measured from the calibration of real da Vinci stereo frames (the public repository
LauraCruciani/DaVinci_project, ``CalibrationParameters.xml``, 1920x1080 frames):

- focal length: M_l[0, 0] = 1103.43 px at 1920 px wide (M_r: 1102.75 px), so the horizontal field of
  view is 2 atan(960 / 1103.43) = 82.05 deg (at another image width the focal length scales with it:
  1103.4 px at 1920, 735.6 px at 1280, 183.9 px at 320);
- baseline: |T| = |(-4.1082, -0.1444, 0.0093)| mm = 4.1107 mm;
- working distance 50 mm: on those frames (depth from their disparities, 33-203 px) the instruments are
  25-50 mm from the camera and the tissue 40-150 mm.

``close`` is the same endoscope at 30 mm, the near end of that range.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Mapping

from contact_viz.params import MM_PER_M
from contact_viz.synth.params import SynthParams

# The da Vinci calibration (CalibrationParameters.xml of LauraCruciani/DaVinci_project):
_DAVINCI_WIDTH_PX = 1920  # image width of the calibrated frames, px
_DAVINCI_FX_PX = 1103.4302694252408  # M_l[0, 0], the left camera's focal length, px
_DAVINCI_T_MM = (-4.1081855448335531, -0.14437844278862857, 0.0092522573362769783)  # T, right camera from left, mm
_DAVINCI_FOV_DEG = 2.0 * math.degrees(math.atan(_DAVINCI_WIDTH_PX / 2.0 / _DAVINCI_FX_PX))  # 82.047 deg
_DAVINCI_BASELINE_M = math.hypot(*_DAVINCI_T_MM) / MM_PER_M  # 0.0041107 m


@dataclass(frozen=True)
class CameraPreset:
    """A stereo endoscope as ``SynthParams`` fields."""

    fov_deg: float  # horizontal field of view, deg
    baseline_m: float  # stereo baseline, m
    tissue_distance_m: float  # working distance: camera to the tissue base plane along the optical axis, m
    source: str  # where the figures come from, text

    def fields(self) -> dict[str, float]:
        """The ``SynthParams`` fields of this camera."""
        return {"fov_deg": self.fov_deg, "baseline_m": self.baseline_m, "tissue_distance_m": self.tissue_distance_m}


_DEFAULT = SynthParams()
CAMERAS: Mapping[str, CameraPreset] = MappingProxyType({
    "default": CameraPreset(_DEFAULT.fov_deg, _DEFAULT.baseline_m, _DEFAULT.tissue_distance_m,
                            "the camera of a session made without camera options"),
    "davinci": CameraPreset(_DAVINCI_FOV_DEG, _DAVINCI_BASELINE_M, 0.05,
                            "da Vinci stereo endoscope: fx 1103.43 px at 1920 px, |T| 4.111 mm, 50 mm"),
    "close": CameraPreset(_DAVINCI_FOV_DEG, _DAVINCI_BASELINE_M, 0.03, "the da Vinci endoscope at 30 mm"),
})


def camera_fields(name: str = "default", *, fov_deg: float | None = None, baseline_mm: float | None = None,
                  working_distance_mm: float | None = None) -> dict[str, float]:
    """The ``SynthParams`` camera fields of preset ``name`` with any of its values replaced (None: the
    preset's). An unknown name is a ValueError naming the presets."""
    if name not in CAMERAS:
        raise ValueError(f"--camera must be one of {', '.join(CAMERAS)}; got {name!r}")
    fields = CAMERAS[name].fields()
    if fov_deg is not None:
        fields["fov_deg"] = float(fov_deg)
    if baseline_mm is not None:
        fields["baseline_m"] = float(baseline_mm) / MM_PER_M
    if working_distance_mm is not None:
        fields["tissue_distance_m"] = float(working_distance_mm) / MM_PER_M
    return fields


def camera_record(params: SynthParams, fx_px: float) -> dict[str, Any]:
    """What session.json says of the camera: the preset whose values these are exactly (``custom`` if
    none), field of view (deg), focal length at the session's width (px), baseline and working distance
    (mm)."""
    here = {"fov_deg": params.fov_deg, "baseline_m": params.baseline_m, "tissue_distance_m": params.tissue_distance_m}
    preset = next((name for name, cam in CAMERAS.items() if cam.fields() == here), "custom")
    return {
        "preset": preset,
        "fov_deg": params.fov_deg,
        "fx_px": fx_px,
        "baseline_mm": params.baseline_m * MM_PER_M,
        "working_distance_mm": params.tissue_distance_m * MM_PER_M,
    }
