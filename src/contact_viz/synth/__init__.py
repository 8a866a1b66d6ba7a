"""Synthetic stereo-endoscope sessions with known truth, rendered by open3d ray casting.

A textured tissue phantom (``cup``, ``kidney``, ``liver`` or ``glove``) and a dVRK-like instrument
(8 mm shaft, dark wrist, two rounded jaws) are seen through a rectified stereo endoscope. The tool
palpates the tissue in repeated cycles (approach with hover, press, hold, retract); on the glove
it grasps the surface and pulls it outward instead. Because the scene is synthetic, the true
tool-tissue gap, indentation, force and contact are known for every frame. With
``SynthParams.tools = 2`` a second instrument works beside the first (``second``: it presses while
the first hovers, hovers a few pixels from it and crosses in front of it); with
``SynthParams.shaft_elevation_deg`` the shafts lie at that angle above the tissue plane.

The package is layered; each module only uses the ones above it:

- ``params``: ``SynthParams`` and the seeded random streams;
- ``scene`` (pure numpy): camera, tissue frame, phantom height fields, closest points;
- ``motion`` (pure numpy): tool trajectory and truth (``plan_tool_track``), dent/tent field
  (``tissue_displacement``);
- ``tools`` (pure numpy): a tool as primitives (``tool_primitives``), exact ray casting of the
  tools alone (``cast_tools``), distances between two tools;
- ``second`` (pure numpy): the second instrument's plan around the first (``plan_tracks``);
- ``sensors`` (pure numpy/cv2): stereo depth noise and holes (``stereo_depth``), force noise
  (``measured_force``), manual-style labels (``manual_labels``);
- ``render``: open3d ray casting and shading of a stereo pair (``Renderer``);
- ``files``: file writing (``generate_session``) and what the sensors record (``sensor_streams``);
- ``live``: the same files written frame by frame at a given rate, as a recorder does (``write_live``).

Coordinates are metres in the left camera frame (OpenCV: x right, y down, z forward). The right
camera sits at (+baseline, 0, 0) with the same orientation, so true disparity = fx * B / Z.
"""

from __future__ import annotations

from contact_viz.synth.files import davis_palette, generate_session, scene_truth, sensor_streams, true_depth
from contact_viz.synth.live import LiveStats, write_live
from contact_viz.synth.motion import ToolTrack, plan_tool_track, tissue_displacement
from contact_viz.synth.second import plan_tracks
from contact_viz.synth.params import PHANTOMS, PHASES, REFERENCE_WIDTH_PX, SynthParams
from contact_viz.synth.render import tool_parts
from contact_viz.synth.scene import (
    StereoCamera,
    TissueFrame,
    closest_surface_points,
    phantom_height,
    stereo_camera,
    surface_normals,
    surface_points,
    tissue_frame,
)
from contact_viz.synth.sensors import manual_labels, measured_force, scene_force, stereo_depth
from contact_viz.synth.tools import cast_tools, tool_distance, tool_primitives

__all__ = [
    "LiveStats",
    "PHANTOMS",
    "PHASES",
    "REFERENCE_WIDTH_PX",
    "StereoCamera",
    "SynthParams",
    "TissueFrame",
    "ToolTrack",
    "cast_tools",
    "closest_surface_points",
    "davis_palette",
    "generate_session",
    "manual_labels",
    "measured_force",
    "phantom_height",
    "plan_tool_track",
    "plan_tracks",
    "scene_force",
    "scene_truth",
    "sensor_streams",
    "stereo_camera",
    "stereo_depth",
    "surface_normals",
    "surface_points",
    "tissue_displacement",
    "tissue_frame",
    "tool_distance",
    "tool_parts",
    "tool_primitives",
    "true_depth",
    "write_live",
]
