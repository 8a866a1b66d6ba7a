"""Several instruments in one scene: the scene's contact posterior from the instruments' posteriors,
and the per-instrument training labels made from the scene's labels.

A session with several instruments (SAM2 object ids) has one signal sequence per instrument, over
all frames of the session (NaN where the instrument is absent or has no patch). The HMM filters
each sequence on its own (``forward_filter``: a NaN frame adds no evidence, its posterior is the
one-step prediction); :func:`scene_posterior` combines them frame by frame into the posterior the
threshold applies to and Table 1 scores against the scene's labels. The labels belong to the scene
(force >= the contact threshold, or labels.csv): :func:`training_labels` turns them into a label
per instrument sequence for the supervised fit, unless labels.csv labels the instruments itself.

With one instrument both are the identity: the scene posterior is the instrument's posterior and
its training labels are the scene's, so single-instrument sessions give exactly the results of a
single sequence.

Pure computation on arrays: no I/O.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

__all__ = ["COMBINE_RULE", "instrument_posteriors", "scene_posterior", "training_labels"]

COMBINE_RULE = "max"  # scene P(contact) = the largest posterior of the instruments in the frame
_UNKNOWN, _NO_CONTACT, _CONTACT = -1, 0, 1


def _as_2d(array: Any, name: str, dtype=np.float64) -> np.ndarray:
    arr = np.asarray(array, dtype=dtype)
    if arr.ndim != 2 or arr.shape[0] == 0:
        raise ValueError(f"{name}: expected a 2-D array (instruments K >= 1, frames T), got shape {arr.shape}")
    return arr


def instrument_posteriors(predict_proba: Callable[[np.ndarray], np.ndarray], signals: Any) -> np.ndarray:
    """Each instrument's filtered posterior, (K, T) float64: ``predict_proba`` ((T,) signal -> (T,)
    P(contact | x_1..x_t)) run on every row of ``signals`` (K, T) separately."""
    x = _as_2d(signals, "signals")
    return np.stack([np.asarray(predict_proba(row), dtype=np.float64) for row in x])


def scene_posterior(posteriors: Any, present: Any = None) -> np.ndarray:
    """The scene's P(contact) per frame, (T,) float64: the max of the instruments' filtered posteriors
    over the instruments present in the frame (``present`` (K, T) bool: the instrument is in the frame's
    mask; None = all); in a frame without any instrument, the max over all of them (each one's posterior
    there is its one-step prediction, as for a single instrument's frame without a patch).

    Why the max and not the noisy-OR 1 - prod_k (1 - p_k):

    * The scene is in contact when at least one instrument is, and the instrument most likely in
      contact says how likely that is: the max is a lower bound on P(any in contact) that is tight
      when one instrument carries the evidence (the usual case: one instrument touches, the others
      hover). The noisy-OR assumes the instruments independent given their signals, which they are
      not (one scene, one force sensor), and it grows with the number of instruments: three
      instruments hovering at 0.3 each give 0.66, a false contact that no single sequence supports.
    * The threshold is chosen on out-of-fold posteriors of single sequences (``LosoEnsemble``); the
      max keeps every scene posterior the posterior of one filtered sequence, on the scale the
      threshold was chosen on, whatever the number of instruments.
    * With one instrument the max is that instrument's posterior, bit for bit (the noisy-OR computes
      1 - (1 - p), which is not p in floating point): single-instrument outputs are unchanged.

    Absent instruments are left out because an instrument that left the view keeps its last belief,
    decaying toward the stationary P(contact), which says nothing about the frame; with no instrument
    in the frame there is nothing better than those predictions.
    """
    p = _as_2d(posteriors, "posteriors")
    if p.shape[0] == 1:
        return p[0]  # one instrument: its posterior, unchanged
    if present is None:
        return p.max(axis=0)
    here = np.asarray(present, dtype=bool)
    if here.shape != p.shape:
        raise ValueError(f"present: expected shape {p.shape} (instruments, frames), got {here.shape}")
    # the rule (see the docstring): max over the instruments in the frame, else over all of them
    out = np.where(here, p, -np.inf).max(axis=0)
    empty = ~here.any(axis=0)
    out[empty] = p[:, empty].max(axis=0)
    return out


def training_labels(signals: Any, scene_labels: Any, tool_labels: Any = None) -> np.ndarray:
    """Per-instrument labels for the supervised fit, (K, T) int8 in {-1, 0, 1}.

    Args:
        signals: (K, T) float, each instrument's signal (dec, larger = nearer the tissue; NaN = absent
            or no patch), rows in ascending object id.
        scene_labels: (T,) int, the scene's labels (1 contact, 0 none, -1 unknown).
        tool_labels: optional (K, T) int, labels.csv's per-instrument labels (-1 where it gives none).

    The rule, frame by frame:

    * a frame where ``tool_labels`` labels any instrument: those labels as they are, -1 for the
      instruments it does not name;
    * otherwise a frame labelled no contact: every instrument no contact; unknown: every one unknown;
    * otherwise a frame labelled contact: the instrument with the largest finite signal (the one
      nearest the tissue; ties go to the lowest object id) gets contact, every other instrument no
      contact. A contact frame where no instrument has a finite signal takes the instrument chosen at
      the nearest frame of the same contact run (consecutive contact frames labelled this way) that
      has one, the earlier side first (the contact stays with the instrument that had it); a run
      where no frame has one gives contact to the only instrument of a single-instrument session and
      leaves every instrument unknown (-1) otherwise (nothing tells which one touched).

    With one instrument and no ``tool_labels`` the result is the scene's labels.
    """
    x = _as_2d(signals, "signals")
    n_tools, n_frames = x.shape
    y = np.asarray(scene_labels)
    if y.shape != (n_frames,):
        raise ValueError(f"scene_labels: expected shape ({n_frames},), got {y.shape}")
    out = np.full((n_tools, n_frames), _UNKNOWN, dtype=np.int8)
    named = np.zeros(n_frames, dtype=bool)
    if tool_labels is not None:
        given = np.asarray(tool_labels)
        if given.shape != x.shape:
            raise ValueError(f"tool_labels: expected shape {x.shape} (instruments, frames), got {given.shape}")
        named = (given >= 0).any(axis=0)
        out[:, named] = given[:, named]
    rule = ~named
    out[:, rule & (y == _NO_CONTACT)] = _NO_CONTACT
    contact = rule & (y == _CONTACT)
    if n_tools == 1:
        out[0, contact] = _CONTACT
        return out
    finite = np.isfinite(x)
    # the nearest instrument per frame: largest finite signal, first (lowest id) on ties; -1 = none finite
    pick = np.where(finite.any(axis=0), np.argmax(np.where(finite, x, -np.inf), axis=0), -1)
    t = 0
    while t < n_frames:
        if not contact[t]:
            t += 1
            continue
        end = t
        while end < n_frames and contact[end]:
            end += 1
        run = pick[t:end].copy()
        known = np.flatnonzero(run >= 0)
        if known.size:
            # fill each unmeasured frame from the last measured one before it, else the first after it
            before = np.maximum.accumulate(np.where(run >= 0, np.arange(run.size), -1))
            source = np.where(before >= 0, before, known[0])
            run = run[source]
            out[:, t:end] = _NO_CONTACT
            out[run, np.arange(t, end)] = _CONTACT
        t = end
    return out

