"""Parameters of the pipeline as frozen, typed dataclasses, and the one way they are checked.

Every field carries its unit. ``to_dict`` / ``from_dict`` give the JSON form that is saved
with every result, so a result can always be traced back to the parameters that made it.

Every config class of the package checks its fields the same way: a field made with
:func:`checked` states its range next to its default, and the class's ``__post_init__`` calls
:func:`check_fields`, which checks each field against its annotation (``int``, ``float``,
``bool``, ``str``, optionally ``| None``) and that range; a bad value is one ValueError naming
``Class.field``, what was expected and what was given. Rules that tie several fields together
stay written out in ``__post_init__`` after it. (Not pydantic dataclasses: importing
pydantic.dataclasses costs about as long as importing the whole patch module, numpy and
OpenCV included, and they turn an integer given for a float field into a float, which would
change the saved JSON and the cache keys made from it.)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from contact_viz.io.jsonfile import read_json

T = TypeVar("T")
PATCH_PARAMS_EXPECTED = 'expected a JSON object of PatchParams fields or {"patch_params": {...}}'
MM_PER_M = 1000.0  # millimetres per metre (uint16 depth PNGs hold millimetres; the viewer and figures show mm)


# --------------------------------------------------------------------------------------------
# Checking fields
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Range:
    """What :func:`checked` allows beyond the field's annotated type."""

    ge: float | None = None  # value >= ge
    gt: float | None = None  # value > gt
    le: float | None = None  # value <= le
    lt: float | None = None  # value < lt
    odd: bool = False  # an odd integer
    multiple_of: int | None = None  # an integer multiple of this
    choices: tuple[Any, ...] | None = None  # one of these
    pair: bool = False  # a (lo, hi) pair of numbers with lo <= hi, both within the bounds; stored as floats


def checked(default: Any, *,
            ge: float | None = None, gt: float | None = None, le: float | None = None, lt: float | None = None,
            odd: bool = False, multiple_of: int | None = None, choices: Any = None, pair: bool = False) -> Any:
    """A dataclass field with a range that :func:`check_fields` enforces (see the module docstring)."""
    rule = _Range(ge, gt, le, lt, odd, multiple_of, None if choices is None else tuple(choices), pair)
    return dataclasses.field(default=default, metadata={"range": rule})


def _number_text(value: float) -> str:
    return f"{value:g}"


def _bounds_text(rule: _Range, pair: bool = False) -> str:
    """The bounds in words: ' >= 0', ' in (0, 1]', '' for none; for a pair: '0 < lo <= hi <= 1'."""
    low = high = None  # (bound, interval bracket, operator before the value, operator after it)
    if rule.ge is not None or rule.gt is not None:
        low = (rule.ge, "[", ">=", "<=") if rule.ge is not None else (rule.gt, "(", ">", "<")
    if rule.le is not None or rule.lt is not None:
        high = (rule.le, "]", "<=") if rule.le is not None else (rule.lt, ")", "<")
    if pair:
        text = "lo <= hi"
        if low:
            text = f"{_number_text(low[0])} {low[3]} {text}"
        if high:
            text = f"{text} {high[2]} {_number_text(high[0])}"
        return text
    if low and high:
        return f" in {low[1]}{_number_text(low[0])}, {_number_text(high[0])}{high[1]}"
    if low:
        return f" {low[2]} {_number_text(low[0])}"
    if high:
        return f" {high[2]} {_number_text(high[0])}"
    return ""


def _expected(kind: str | None, optional: bool, rule: _Range) -> str:
    if rule.choices is not None:
        text = f"one of {list(rule.choices)}"
    elif rule.pair:
        text = f"a (lo, hi) pair of numbers with {_bounds_text(rule, pair=True)}"
    elif kind == "int":
        text = "an odd integer" if rule.odd else f"a multiple of {rule.multiple_of}" if rule.multiple_of else "an integer"
        text += _bounds_text(rule)
    elif kind == "float":
        text = "a finite number" + _bounds_text(rule)
    elif kind == "bool":
        text = "True or False"
    else:
        text = "a string"
    return f"None or {text}" if optional else text


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def _within(value: float, rule: _Range) -> bool:
    return ((rule.ge is None or value >= rule.ge) and (rule.gt is None or value > rule.gt)
            and (rule.le is None or value <= rule.le) and (rule.lt is None or value < rule.lt))


def _valid(value: Any, kind: str | None, rule: _Range) -> bool:
    if rule.pair:
        return (isinstance(value, (tuple, list)) and len(value) == 2 and all(_is_number(v) for v in value)
                and value[0] <= value[1] and _within(value[0], rule) and _within(value[1], rule))
    if kind == "int" and (isinstance(value, bool) or not isinstance(value, int)):
        return False
    if (kind == "float" and not _is_number(value)) or (kind == "bool" and not isinstance(value, bool)) \
            or (kind == "str" and not isinstance(value, str)):
        return False
    if rule.choices is not None:
        return value in rule.choices
    if kind in ("int", "float"):
        return (_within(value, rule) and (not rule.odd or value % 2 == 1)
                and (not rule.multiple_of or value % rule.multiple_of == 0))
    return True


_CHECKED_KINDS = ("int", "float", "bool", "str")
_FIELD_RULES: dict[type, tuple[tuple[str, str | None, bool, _Range], ...]] = {}


def _field_rules(cls: type) -> tuple[tuple[str, str | None, bool, _Range], ...]:
    """(name, kind, optional, range) of every field of ``cls`` that is checked, computed once per class."""
    rules = _FIELD_RULES.get(cls)
    if rules is None:
        out = []
        for f in dataclasses.fields(cls):
            annotation = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", str(f.type))
            parts = [p.strip() for p in annotation.split("|")]
            optional = "None" in parts
            kinds = [p for p in parts if p != "None"]
            kind = kinds[0] if len(kinds) == 1 and kinds[0] in _CHECKED_KINDS else None
            rule = f.metadata.get("range", _Range())
            if kind not in ("int", "float") and not rule.pair and rule.choices is None and rule != _Range():
                raise TypeError(f"{cls.__name__}.{f.name}: a range needs an int or float annotation, got {annotation}")
            if kind is not None or rule.pair or rule.choices is not None:
                out.append((f.name, kind, optional, rule))
        rules = _FIELD_RULES[cls] = tuple(out)
    return rules


def check_fields(config: Any) -> None:
    """Check every field of the dataclass instance ``config`` against its annotation and its
    :func:`checked` range; ValueError ``"Class.field must be <expected>, got <value>"`` for the first bad one.
    Pairs are stored as tuples of floats (a JSON round trip gives lists)."""
    for name, kind, optional, rule in _field_rules(type(config)):
        value = getattr(config, name)
        if value is None and optional:
            continue
        if not _valid(value, kind, rule):
            raise ValueError(f"{type(config).__name__}.{name} must be {_expected(kind, optional, rule)}, got {value!r}")
        if rule.pair:
            object.__setattr__(config, name, (float(value[0]), float(value[1])))


# --------------------------------------------------------------------------------------------
# JSON form
# --------------------------------------------------------------------------------------------


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

    n1: int = checked(31, ge=3, odd=True)  # side of the tool-depth window N1 around each band pixel, px (odd)
    n2: int = checked(17, ge=3, odd=True)  # side of the scoring window N2 around each candidate, px (odd)
    tau_tool: int = checked(30, ge=1)  # fewest valid interior pixels in N1 for d(p) to be defined, count
    tau_patch: int = checked(8, ge=1)  # fewest valid distances in N2 for s(p) to be defined, count
    eps_m: float = checked(1e-4, gt=0)  # floor on |d| in the signal -log10(max(|d|, eps)), m
    erosion_px: float = checked(2.0, ge=0)  # interior = tool pixels more than this from the background, px
    ring_px: float = checked(3.0, ge=0)  # width of the excluded ring outside the tool edge, px
    band_scale: float = checked(0.1, ge=0)  # exterior band width per px of visible shaft width, px/px
    band_min_px: float = checked(2.0, gt=0)  # narrowest exterior band, px
    band_max_px: float = checked(8.0, gt=0)  # widest exterior band, px
    # Depth bled from the tool over the tissue (the bleeding test of geometry.patch._band_distances):
    reject_bleeding: bool = True  # drop band pixels whose depth is nearer the tool's than the tissue's beyond, -
    bleed_step_m: float = checked(0.004, gt=0)  # ... only where tool and tissue beyond differ by this, m
    bleed_beyond_px: float = checked(4.0, ge=1)  # tissue beyond: background within this of the band, px
    # band pixels the right camera cannot see (the half-occluded strip left of each instrument, found from the
    # depth, the mask and the baseline: geometry.occlusion) are not candidates: "sgbm" with depth computed by
    # contact-viz's SGBM (which observed nothing there), "always" also with supplied depth (a network fills the
    # strip from its priors), "never" (the paper: every band pixel counts), -
    hidden_strip: str = checked("sgbm", choices=("sgbm", "always", "never"))

    def __post_init__(self) -> None:
        check_fields(self)
        if self.tau_tool > self.n1 * self.n1:
            raise ValueError(f"PatchParams.tau_tool={self.tau_tool} exceeds the {self.n1}x{self.n1} window")
        if self.tau_patch > self.n2 * self.n2:
            raise ValueError(f"PatchParams.tau_patch={self.tau_patch} exceeds the {self.n2}x{self.n2} window")
        if self.band_min_px > self.band_max_px:
            raise ValueError(
                f"PatchParams needs band_min_px <= band_max_px, got {self.band_min_px}, {self.band_max_px}"
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

    contact_force_n: float = checked(2.0, gt=0)  # contact where the force magnitude is at least this, N

    def __post_init__(self) -> None:
        check_fields(self)
