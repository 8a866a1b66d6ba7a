"""model.json: a fitted contact model as hand-readable JSON (never pickle).

It holds the model kind (``model_kind``, :mod:`contact_viz.model.emission`), the K
leave-one-session-out HMMs, the decision threshold, the training sessions, the patch and label
parameters the features were computed with, and the package version. A file without
``model_kind`` (written before the kinds existed) holds the paper's model and loads as it.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from contact_viz import __version__
from contact_viz.io.jsonfile import read_json, write_json
from contact_viz.model.emission import PAPER_KIND
from contact_viz.model.hmm import LosoEnsemble
from contact_viz.params import LabelParams, PatchParams, from_dict, to_dict

MODEL_FORMAT = "contact-viz-model/1"  # the "format" field of model.json


@dataclass(frozen=True)
class ContactModel:
    """A fitted LOSO ensemble with the parameters its features were computed with."""

    ensemble: LosoEnsemble
    patch_params: PatchParams
    label_params: LabelParams
    training_sessions: tuple[dict[str, Any], ...]  # {"name", "path", "frames"} per training session
    version: str = __version__

    @property
    def model_kind(self) -> str:
        """The emission of the ensemble's HMMs (contact_viz.model.emission.MODEL_KINDS)."""
        return self.ensemble.params.model_kind

    @property
    def threshold(self) -> float:
        """Decision threshold on the ensemble posterior."""
        return float(self.ensemble.threshold_)

    def predict_proba(self, signal: np.ndarray) -> np.ndarray:
        """(T,) float64 mean filtered P(contact | x_1..x_t) of the K models."""
        return self.ensemble.predict_proba(signal)


def check_params(model_params: PatchParams, found: PatchParams, where: str) -> None:
    """Refuse features computed with other patch parameters than the model's: one ValueError
    starting with ``where`` and listing 'field: model X, features Y' for every field that differs."""
    a, b = to_dict(model_params), to_dict(found)
    diff = [f"{k}: model {a[k]!r}, features {b[k]!r}" for k in a if a[k] != b[k]]
    if diff:
        raise ValueError(
            f"{where}: features were computed with other patch parameters than the model's "
            f"({'; '.join(diff)}); re-extract them with the model's parameters"
        )


def model_to_dict(model: ContactModel) -> dict[str, Any]:
    """The JSON form of ``model``."""
    return {
        "format": MODEL_FORMAT,
        "contact_viz_version": model.version,
        "model_kind": model.model_kind,
        "threshold": model.threshold,
        "training_sessions": list(model.training_sessions),
        "patch_params": to_dict(model.patch_params),
        "label_params": to_dict(model.label_params),
        "ensemble": model.ensemble.to_dict(),
    }


def save_model(model: ContactModel, path: str | Path) -> Path:
    """Write ``model`` to ``path`` as indented JSON, atomically."""
    path = Path(path)
    write_json(path, model_to_dict(model), indent=1)
    return path


def load_model(path: str | Path) -> ContactModel:
    """Read a model.json; any problem is one ValueError naming the file and what was expected."""
    path = Path(path)
    data = read_json(path, "expected a contact-viz model.json",
                     missing="model file not found (make one with `contact-viz fit`)")
    if not isinstance(data, dict) or data.get("format") != MODEL_FORMAT:
        raise ValueError(f"{path}: expected a contact-viz model.json with \"format\": \"{MODEL_FORMAT}\"")
    try:
        kind = data.get("model_kind", PAPER_KIND)  # an older file: the paper's (so are its HMMParams' defaults)
        ensemble = LosoEnsemble.from_dict(data["ensemble"])
        if ensemble.params.model_kind != kind:
            raise ValueError(f"model_kind is {kind!r} but the ensemble holds {ensemble.params.model_kind!r}")
        model = ContactModel(
            ensemble=ensemble,
            patch_params=from_dict(PatchParams, data["patch_params"]),
            label_params=from_dict(LabelParams, data["label_params"]),
            training_sessions=tuple(data["training_sessions"]),
            version=str(data["contact_viz_version"]),
        )
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path}: malformed model.json ({type(exc).__name__}: {exc})") from None
    return model
