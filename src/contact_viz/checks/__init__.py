"""Diagnostics of mask, depth and force failures: pure measurements over arrays (no I/O, no Rerun).

frame.py measures one frame (each instrument of it), rules.py turns measurements into checks that fire
(with the likely cause; per instrument, and instruments against each other), session.py has the
per-session checks, params.py their thresholds (DiagnosticParams).
"""

from contact_viz.checks.frame import ToolMeasures, measure_tools
from contact_viz.checks.params import DiagnosticParams
from contact_viz.checks.rules import CHECKS, SESSION_CHECKS, Diagnostic, FrameChecker, PatchNumbers, fired_ranges

__all__ = ["CHECKS", "SESSION_CHECKS", "Diagnostic", "DiagnosticParams", "FrameChecker", "PatchNumbers",
           "ToolMeasures", "fired_ranges", "measure_tools"]
