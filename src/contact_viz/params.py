"""Parameters of the pipeline as frozen, typed dataclasses.

Every field carries its unit. ``to_dict`` / ``from_dict`` give the JSON form that is saved
with every result, so a result can always be traced back to the parameters that made it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from contact_viz.io.jsonfile import read_json

T = TypeVar("T")
PATCH_PARAMS_EXPECTED = 'expected a JSON object of PatchParams fields or {"patch_params": {...}}'


def to_dict(params: Any) -> dict[str, Any]:
    """The dataclass ``params`` as a plain JSON-ready dict."""
    return dataclasses.asdict(params)


def read_patch_params(path: str | Path) -> "PatchParams":
    """PatchParams from a JSON file: an object of PatchParams fields, or {"patch_params": {...}}
    (as grid_search.py and features.csv.json write it). Any problem is one ValueError naming the file."""
    return patch_params_from_json(read_json(path, PATCH_PARAMS_EXPECTED), path)


def patch_params_from_json(data: Any, path: str | Path) -> "PatchParams":
    """PatchParams from the parsed JSON ``data`` of the file ``path``, in either form
    :func:`read_patch_params` reads; any problem is one ValueError naming the file."""
    if isinstance(data, dict) and "patch_params" in data:
        data = data["patch_params"]
    if not isinstance(data, dict):
        raise ValueError(f"{path}: {PATCH_PARAMS_EXPECTED}")
    try:
        return from_dict(PatchParams, data)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{path}: {exc}") from None


def from_dict(cls: type[T], data: dict[str, Any]) -> T:
    """Build ``cls`` from ``data``; unknown keys are an error naming them."""
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} field(s): {', '.join(unknown)}; expected some of {sorted(names)}")
    return cls(**data)


@dataclass(frozen=True)
class PatchParams:
    """The minimum-distance patch (paper, Sec. 2.1). Defaults are the paper's where it gives them.

    Layers around the tool mask, by Euclidean distance to the mask edge:
    interior = tool pixels farther than ``erosion_px`` from the background;
    excluded ring = the rest of the tool plus background pixels within ``ring_px`` of the tool;
    exterior band = background pixels between ``ring_px`` and ``ring_px + band_width`` of the tool,
    with band_width = clip(``band_scale`` x visible shaft width, ``band_min_px``, ``band_max_px``).
    """

    n1: int = 31  # side of the tool-depth window N1 around each band pixel, px (odd)
    n2: int = 17  # side of the scoring window N2 around each candidate, px (odd)
    tau_tool: int = 30  # fewest valid interior pixels in N1 for d(p) to be defined, count
    tau_patch: int = 8  # fewest valid distances in N2 for s(p) to be defined, count
    eps_m: float = 1e-4  # floor on |d| in the signal -log10(max(|d|, eps)), m
    erosion_px: float = 2.0  # interior = tool pixels more than this from the background, px
    ring_px: float = 3.0  # width of the excluded ring outside the tool edge, px
    band_scale: float = 0.1  # exterior band width per px of visible shaft width, px/px
    band_min_px: float = 2.0  # narrowest exterior band, px
    band_max_px: float = 8.0  # widest exterior band, px
    # Depth bled from the tool over the tissue (issue 13; the bleeding test of geometry.patch._band_distances):
    reject_bleeding: bool = True  # drop band pixels whose depth is nearer the tool's than the tissue's beyond, -
    bleed_step_m: float = 0.004  # ... only where tool and tissue beyond differ in depth by at least this, m
    bleed_beyond_px: float = 4.0  # the tissue beyond: background within this of the band's outer edge, px

    def __post_init__(self) -> None:
        for name in ("n1", "n2"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 3 or value % 2 == 0:
                raise ValueError(f"PatchParams.{name} must be an odd integer >= 3, got {value!r}")
        for name in ("tau_tool", "tau_patch"):
            value = getattr(self, name)
            if not isinstance(value, int) or value < 1:
                raise ValueError(f"PatchParams.{name} must be a positive integer, got {value!r}")
        if self.tau_tool > self.n1 * self.n1:
            raise ValueError(f"PatchParams.tau_tool={self.tau_tool} exceeds the {self.n1}x{self.n1} window")
        if self.tau_patch > self.n2 * self.n2:
            raise ValueError(f"PatchParams.tau_patch={self.tau_patch} exceeds the {self.n2}x{self.n2} window")
        if not self.eps_m > 0:
            raise ValueError(f"PatchParams.eps_m must be > 0, got {self.eps_m!r}")
        if self.erosion_px < 0 or self.ring_px < 0 or self.band_scale < 0:
            raise ValueError("PatchParams.erosion_px, ring_px and band_scale must be >= 0")
        if not self.bleed_step_m > 0 or not self.bleed_beyond_px >= 1:
            raise ValueError(f"PatchParams needs bleed_step_m > 0 and bleed_beyond_px >= 1, got "
                             f"{self.bleed_step_m!r} and {self.bleed_beyond_px!r}")
        if not 0 < self.band_min_px <= self.band_max_px:
            raise ValueError(
                f"PatchParams needs 0 < band_min_px <= band_max_px, got {self.band_min_px}, {self.band_max_px}"
            )
        reach = self.erosion_px + self.ring_px + self.band_max_px
        if reach > self.n1 // 2 - 1:
            raise ValueError(
                f"PatchParams: erosion_px + ring_px + band_max_px = {reach:g} px puts the outer band out of "
                f"reach of the interior for n1={self.n1} (half-width {self.n1 // 2} px); "
                f"it must be at most {self.n1 // 2 - 1} px"
            )

    @property
    def outer_reach_px(self) -> float:
        """Largest distance from the tool edge at which a band pixel can lie, px."""
        return self.ring_px + self.band_max_px

    @property
    def depth_reach_px(self) -> float:
        """Largest distance from the tool edge at which the patch reads the depth, px."""
        return self.outer_reach_px + (self.bleed_beyond_px if self.reject_bleeding else 0.0)


@dataclass(frozen=True)
class LabelParams:
    """How ground-truth contact labels are derived from force."""

    contact_force_n: float = 2.0  # contact where the force magnitude is at least this, N

    def __post_init__(self) -> None:
        if not self.contact_force_n > 0:
            raise ValueError(f"LabelParams.contact_force_n must be > 0, got {self.contact_force_n!r}")
