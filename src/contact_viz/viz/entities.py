"""Entity paths and timelines of a contact-viz recording (no Rerun here: scripts and tests use them too).

Entity tree (the README lists it too)::

    world                          ViewCoordinates RDF, AnnotationContext of the layer classes (static)
    world/camera/left              Pinhole from K.txt (static)
    world/camera/left/image        left image: VideoStream (AV1/H.264, --images video), EncodedImage (JPEG) or Image (raw)
    world/camera/left/layers       SegmentationImage of the layer classes (full resolution)
    world/camera/left/patch        Boxes2D: the N2 window of the selected patch, in the instrument's colour
    world/camera/left/labels       Points2D: every instrument's label ("2.0 mm", "● " on the one in contact), in its
                                   colour, above its patch box and apart from the others
    world/camera/right             Transform3D (baseline along +x) + Pinhole (static)
    world/camera/right/image       right image
    world/camera/depth             Pinhole of the decimated depth grid (K / depth step, static)
    world/camera/depth/image       DepthImage (uint16, 1 unit = 1 / depth_units_per_m m)
    world/camera/depth/layers      SegmentationImage of the layer classes on the depth grid
    world/camera/depth/patch       Boxes2D: the patch window on the depth grid
    world/camera/depth/kind        SegmentationImage on the depth grid: fine (1) or coarse (2) SGBM depth, with its
                                   own AnnotationContext (static); only where the frames say (Frame.depth_fine)
    world/cloud/near               Points3D: RGB cloud around the patch (every 2nd pixel)
    world/cloud/far                Points3D: RGB cloud elsewhere, every 16th pixel merged into 4 mm voxels
    world/patch/tissue             Points3D: band pixels whose distances gave the patch distance
    world/patch/tool               Points3D: interior pixels whose depths gave the tool depth
    world/patch/gap                LineStrips3D + Points3D: the gap, tool depth -> tissue along the patch centre's
                                   ray, and its two ends
    world/patch/gap_length         Points3D: the gap's length ("2.0 mm"), a label at its middle
    series/distance                Scalars: patch distance, mm
    series/signal                  Scalars: -log10(max(|d|, eps))
    series/force/{magnitude,x,y,z} Scalars: force, N (send_columns, known up front)
    series/contact/truth           Scalars: ground-truth contact 0/1 (send_columns)
    series/contact/posterior       Scalars: causal HMM posterior (only with a model)
    series/contact/threshold       Scalars: decision threshold (send_columns, only with a model)
    series/contact/predicted       Scalars: posterior >= threshold, 0/1 (only with a model)
    series/contact_evidence        Scalars: the frame's evidence for contact, the emission log-likelihood ratio
                                   log p(signal | contact) - log p(signal | no contact) that the filter adds (mean
                                   over the model's K HMMs; > 0 favours contact; NaN without a patch; only with a
                                   model)
    series/diagnostics/invalid_depth_fraction   Scalars: share of band pixels with invalid depth
    series/diagnostics/<code>      Scalars (points): a marker at each frame where that check fired (at its score)
    series/diagnostics/score/<code>  Scalars: the check's measured value / its threshold (> 1 fires), clipped at 3
    world/camera/left/evidence/residual  EncodedImage: stereo residual |left - warped right| near the tool (fired frames)
    world/camera/left/evidence/contour   Points2D: mask contour, green on an image edge, red off (fired frames)
    contact                        TextDocument (markdown): the instrument in contact at this frame (with a model:
                                   the largest posterior at or above the threshold; without: the nearest), each
                                   instrument's distance and posterior in its colour's name, the colours' legend
    log                            TextLog: bad frames, diagnostics, the no-model hint
    config                         TextDocument (static): the run's resolved configuration (JSON)

Several instruments (object ids of SAM2 masks, :attr:`contact_viz.io.session.Frame.tool_ids`). Each
instrument has its own layers, box, patch points, gap and series (:data:`TOOL_ENTITIES`), in its colour. The
*primary* instrument (the lowest selected object id, or id 1 when none is selected: a binary mask's only
instrument) keeps the single-instrument paths above, so a session of one instrument records what it
always did; every other instrument ``k`` logs the same things one level down, at
``<entity>/tools/<k>`` (:func:`tool_entity`)::

    world/camera/left/layers/tools/<k>    SegmentationImage of instrument k's layer classes, with its own
                                          AnnotationContext (static; the instrument's colours)
    world/camera/left/patch/tools/<k>     Boxes2D: its patch window
    world/camera/depth/layers/tools/<k>   its layers on the depth grid (AnnotationContext too)
    world/camera/depth/patch/tools/<k>    its patch window on the depth grid
    world/patch/{tissue,tool,gap,gap_length}/tools/<k>  its patch points and gap
    series/distance/tools/<k>             Scalars: its patch distance, mm
    series/signal/tools/<k>               Scalars: its signal
    series/contact_evidence/tools/<k>     Scalars: its evidence for contact (with a model)
    series/contact/posterior/tools/<k>    Scalars: instrument k's own causal posterior, for every instrument
                                          (the primary's too: series/contact/posterior is the scene's, the max
                                          over the instruments in the frame); once the session has shown a
                                          second instrument, with a model

A frame without instrument ``k`` clears its entities (and breaks its series with a NaN), so a stale
layer never shows. The per-instrument series are under their plot's origin, so the default layout
plots every instrument.

Timelines: ``frame`` (sequence, the frame's index in the session) and ``time`` (duration, s).
"""

from __future__ import annotations

__all__ = [
    "APPLICATION_ID",
    "ENTITY_WORLD",
    "ENTITY_LEFT_CAMERA",
    "ENTITY_LEFT_IMAGE",
    "ENTITY_LEFT_LAYERS",
    "ENTITY_LEFT_PATCH",
    "ENTITY_LEFT_LABELS",
    "ENTITY_RIGHT_CAMERA",
    "ENTITY_RIGHT_IMAGE",
    "ENTITY_DEPTH_CAMERA",
    "ENTITY_DEPTH_IMAGE",
    "ENTITY_DEPTH_LAYERS",
    "ENTITY_DEPTH_PATCH",
    "ENTITY_DEPTH_KIND",
    "ENTITY_CLOUD_NEAR",
    "ENTITY_CLOUD_FAR",
    "ENTITY_PATCH_TISSUE",
    "ENTITY_PATCH_TOOL",
    "ENTITY_PATCH_GAP",
    "ENTITY_PATCH_GAP_LENGTH",
    "ENTITY_SERIES_DISTANCE",
    "ENTITY_SERIES_SIGNAL",
    "ENTITY_SERIES_FORCE",
    "ENTITY_SERIES_LAG",
    "FORCE_ENTITIES",
    "ENTITY_SERIES_CONTACT",
    "ENTITY_SERIES_TRUTH",
    "ENTITY_SERIES_POSTERIOR",
    "ENTITY_SERIES_THRESHOLD",
    "ENTITY_SERIES_PREDICTED",
    "ENTITY_SERIES_EVIDENCE",
    "ENTITY_SERIES_DIAGNOSTICS",
    "ENTITY_SERIES_INVALID_DEPTH",
    "ENTITY_SERIES_SCORES",
    "ENTITY_LEFT_EVIDENCE",
    "ENTITY_EVIDENCE_RESIDUAL",
    "ENTITY_EVIDENCE_CONTOUR",
    "ENTITY_LOG",
    "ENTITY_KINEMATIC_TIP",
    "ENTITY_KINEMATIC_AXES",
    "ENTITY_LEFT_KINEMATIC_TIP",
    "ENTITY_LEFT_MASK_TIP",
    "ENTITY_SERIES_TIP",
    "ENTITY_CONFIG",
    "ENTITY_CONTACT",
    "TIMELINE_FRAME",
    "TIMELINE_TIME",
    "PER_FRAME_ENTITIES",
    "PATCH_ENTITIES",
    "TOOL_ENTITIES",
    "TOOL_LAYER_ENTITIES",
    "TOOLS_PART",
    "tool_entity",
    "diagnostic_entity",
    "diagnostic_score_entity",
]

APPLICATION_ID = "contact_viz"  # Rerun application id of every recording

ENTITY_WORLD = "world"
ENTITY_LEFT_CAMERA = "world/camera/left"
ENTITY_LEFT_IMAGE = "world/camera/left/image"
ENTITY_LEFT_LAYERS = "world/camera/left/layers"
ENTITY_LEFT_PATCH = "world/camera/left/patch"
ENTITY_LEFT_LABELS = "world/camera/left/labels"  # Points2D: every instrument's label, in its colour, kept apart
ENTITY_RIGHT_CAMERA = "world/camera/right"
ENTITY_RIGHT_IMAGE = "world/camera/right/image"
ENTITY_DEPTH_CAMERA = "world/camera/depth"
ENTITY_DEPTH_IMAGE = "world/camera/depth/image"
ENTITY_DEPTH_LAYERS = "world/camera/depth/layers"
ENTITY_DEPTH_PATCH = "world/camera/depth/patch"
ENTITY_DEPTH_KIND = "world/camera/depth/kind"  # fine / coarse depth (rerun_log.DepthKindLayer logs and clears it)
ENTITY_CLOUD_NEAR = "world/cloud/near"
ENTITY_CLOUD_FAR = "world/cloud/far"
ENTITY_PATCH_TISSUE = "world/patch/tissue"
ENTITY_PATCH_TOOL = "world/patch/tool"
ENTITY_PATCH_GAP = "world/patch/gap"
ENTITY_PATCH_GAP_LENGTH = "world/patch/gap_length"  # Points3D: the gap's length as a label at its middle
ENTITY_SERIES_DISTANCE = "series/distance"
ENTITY_SERIES_SIGNAL = "series/signal"
ENTITY_SERIES_FORCE = "series/force"
FORCE_ENTITIES = {  # force series entity -> SERIES_STYLES key
    "series/force/magnitude": "force_n",
    "series/force/x": "force_x_n",
    "series/force/y": "force_y_n",
    "series/force/z": "force_z_n",
}
ENTITY_SERIES_CONTACT = "series/contact"
ENTITY_SERIES_TRUTH = "series/contact/truth"
ENTITY_SERIES_POSTERIOR = "series/contact/posterior"
ENTITY_SERIES_THRESHOLD = "series/contact/threshold"
ENTITY_SERIES_PREDICTED = "series/contact/predicted"
ENTITY_SERIES_EVIDENCE = "series/contact_evidence"  # Scalars: the emission log-likelihood ratio of the signal
ENTITY_SERIES_DIAGNOSTICS = "series/diagnostics"
ENTITY_SERIES_LAG = "series/lag_ms"  # --follow: a frame's files complete -> its data logged, ms
ENTITY_SERIES_INVALID_DEPTH = "series/diagnostics/invalid_depth_fraction"
ENTITY_SERIES_SCORES = "series/diagnostics/score"
ENTITY_LEFT_EVIDENCE = "world/camera/left/evidence"
ENTITY_EVIDENCE_RESIDUAL = "world/camera/left/evidence/residual"
ENTITY_EVIDENCE_CONTOUR = "world/camera/left/evidence/contour"
ENTITY_LOG = "log"
ENTITY_KINEMATIC_TIP = "world/kinematics/tip"  # Points3D: the robot's tool tip (hand-eye x kinematics.csv)
ENTITY_KINEMATIC_AXES = "world/kinematics/axes"  # Arrows3D: the tool frame's x, y, z axes at the tip
ENTITY_LEFT_KINEMATIC_TIP = "world/camera/left/kinematic_tip"  # Points2D: its projection on the left image
ENTITY_LEFT_MASK_TIP = "world/camera/left/mask_tip"  # Points2D: the tool tip estimated from the mask
ENTITY_SERIES_TIP = "series/tip"  # Scalars error_px, error_mm: kinematic tip vs mask tip
ENTITY_CONFIG = "config"  # TextDocument (static): the resolved configuration of the run, JSON
ENTITY_CONTACT = "contact"  # TextDocument per frame: which instrument is in contact (or nearest), in words

TIMELINE_FRAME = "frame"  # sequence timeline: frame index in the session
TIMELINE_TIME = "time"  # duration timeline: session time, s

# Per-frame entities, cleared at a bad frame so the viewer does not show the previous frame's data.
PER_FRAME_ENTITIES = (
    ENTITY_LEFT_IMAGE, ENTITY_LEFT_LAYERS, ENTITY_LEFT_PATCH, ENTITY_RIGHT_IMAGE, ENTITY_DEPTH_IMAGE,
    ENTITY_DEPTH_LAYERS, ENTITY_DEPTH_PATCH, ENTITY_CLOUD_NEAR, ENTITY_CLOUD_FAR, ENTITY_PATCH_TISSUE,
    ENTITY_PATCH_TOOL, ENTITY_PATCH_GAP, ENTITY_PATCH_GAP_LENGTH,
)
PATCH_ENTITIES = (ENTITY_LEFT_PATCH, ENTITY_DEPTH_PATCH, ENTITY_PATCH_TISSUE, ENTITY_PATCH_TOOL, ENTITY_PATCH_GAP,
                  ENTITY_PATCH_GAP_LENGTH)

TOOLS_PART = "tools"  # the path part before an instrument's object id (tool_entity)
TOOL_LAYER_ENTITIES = (ENTITY_LEFT_LAYERS, ENTITY_DEPTH_LAYERS)  # each instrument's SegmentationImages
TOOL_ENTITIES = TOOL_LAYER_ENTITIES + PATCH_ENTITIES  # what every instrument has of its own in the images and 3D


def tool_entity(entity: str, tool: int) -> str:
    """The path of instrument ``tool``'s (object id) own ``entity``: ``<entity>/tools/<tool>`` (the primary
    instrument's layers and series are ``entity`` itself: see the module docstring)."""
    return f"{entity}/{TOOLS_PART}/{int(tool)}"


def diagnostic_entity(code: str) -> str:
    """Entity path of the marker series of diagnostic ``code``."""
    return f"{ENTITY_SERIES_DIAGNOSTICS}/{code}"


def diagnostic_score_entity(code: str) -> str:
    """Entity path of the score series (measured value / threshold) of diagnostic ``code``."""
    return f"{ENTITY_SERIES_SCORES}/{code}"
