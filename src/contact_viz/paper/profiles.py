"""How big a study run is: the synthetic study's size, the baseline's configuration and the grid.

"full" is the paper's configuration; "quick" and "tiny" are smaller runs (for a look in minutes and
for tests) and every output of such a run says it is not the paper's configuration.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from contact_viz.baseline.params import BaselineParams
from contact_viz.paper.grid_search import DEFAULT_GRID


@dataclass(frozen=True)
class StudyProfile:
    """How big the run is: the synthetic study's size, the baseline's configuration, the grid."""

    name: str  # "full", "quick" or "tiny"
    synth_frames: int  # frames per synthetic session, count
    synth_width: int  # synthetic image width, px
    synth_height: int  # synthetic image height, px
    synth_fps: int  # synthetic frame rate, 1/s
    n_train: int  # synthetic cup training sessions, count
    test_phantoms: tuple[str, ...]  # one synthetic test session per phantom, in table order
    baseline: BaselineParams  # RGB baseline settings
    grid: tuple[tuple[int, ...], ...]  # --grid-search values of n1, n2, tau_tool, tau_patch


TINY_NET = dict(model_name="efficientnet-b0", width_coefficient=0.25, depth_coefficient=0.25)
PROFILES = {
    # The paper's baseline. The synthetic study at 960x540 (about 3 GB, most of it float32 depth) so
    # the 234 px crop is a crop around the tool tip, not the whole frame.
    "full": StudyProfile("full", 150, 960, 540, 30, 6, ("cup", "kidney", "liver", "glove"),
                         BaselineParams(), DEFAULT_GRID),
    # A few minutes on 2 CPU cores: the demo's study size, a tiny net on 64 px crops.
    "quick": StudyProfile("quick", 150, 480, 270, 30, 6, ("cup", "kidney", "liver", "glove"),
                          BaselineParams(**TINY_NET, bn_momentum=0.1, crop_px=64, epochs=2),
                          ((29, 31), (11, 17), (30,), (8,))),
    # Seconds: for tests and smoke runs. fps 10 so 40 frames hold a full press cycle.
    "tiny": StudyProfile("tiny", 40, 160, 96, 10, 3, ("cup", "glove"),
                         BaselineParams(**TINY_NET, bn_momentum=0.5, crop_px=64, epochs=1, batch_size=8,
                                        eval_batch_size=16),
                         ((31,), (11, 17), (30,), (8,))),
}


def study_profile(name: str, seed: int = 0) -> StudyProfile:
    """Profile ``name`` ("full", "quick" or "tiny") with the baseline trained from ``seed``."""
    profile = PROFILES[name]
    return replace(profile, baseline=replace(profile.baseline, seed=seed))
