"""The baseline ensemble: K fold models, their Platt map and decision threshold; saved as ensemble.json."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from contact_viz.baseline.checkpoint import load_checkpoint
from contact_viz.baseline.crops import SessionCrops
from contact_viz.baseline.net import build_model, raw_scores, resolve_device
from contact_viz.baseline.params import BaselineParams, BaselineWarning, ENSEMBLE_FILE
from contact_viz.baseline.platt import PlattScaling
from contact_viz.io.atomic import atomic_write
from contact_viz.params import from_dict as _params_from_dict
from contact_viz.params import to_dict as _params_to_dict

if TYPE_CHECKING:  # torch is imported lazily: importing this module stays cheap
    import torch


class BaselineEnsemble:
    """K fold models, their Platt map and decision threshold.

    Attributes:
        params: BaselineParams. session_names_: K training session names (fold k left out session k).
        checkpoints_: K checkpoint file names (relative to the directory of ensemble.json).
        init_: "scratch" or "imagenet:<weights file name>".
        platt_: PlattScaling fitted on the pooled out-of-fold raw scores.
        threshold_: float, ``select_f1_threshold`` on the calibrated pooled out-of-fold probabilities.
        oof_scores_: K (T_k,) float64 out-of-fold raw scores. models_: K torch modules (eval mode).
        device: torch.device the models run on.
    """

    def __init__(
        self,
        *,
        params: BaselineParams,
        session_names: list[str],
        checkpoints: list[str],
        init: str,
        platt: PlattScaling,
        threshold: float,
        oof_scores: list[np.ndarray],
        models: list[Any],
        device: torch.device,
    ) -> None:
        self.params = params
        self.session_names_ = list(session_names)
        self.checkpoints_ = list(checkpoints)
        self.init_ = init
        self.platt_ = platt
        self.threshold_ = float(threshold)
        self.oof_scores_ = [np.asarray(o, dtype=np.float64) for o in oof_scores]
        self.models_ = list(models)
        self.device = device

    def _check_crops(self, crops: Any) -> np.ndarray:
        arr = crops.crops if isinstance(crops, SessionCrops) else crops
        size = self.params.crop_px
        ok = isinstance(arr, np.ndarray) and arr.ndim == 4 and arr.shape[1:] == (size, size, 3)
        if not ok or arr.dtype != np.uint8:
            raise ValueError(
                f"crops: expected SessionCrops or a (T, {size}, {size}, 3) uint8 array, got "
                f"{getattr(arr, 'shape', type(arr).__name__)} {getattr(arr, 'dtype', '')}"
            )
        return arr

    def predict_raw(self, crops: SessionCrops | np.ndarray) -> np.ndarray:
        """Mean over the K models of the raw score (logit difference), (T,) float64."""
        arr = self._check_crops(crops)
        batch = self.params.eval_batch_size
        return np.mean([raw_scores(m, arr, batch, self.device) for m in self.models_], axis=0)

    def predict_proba(self, crops: SessionCrops | np.ndarray) -> np.ndarray:
        """Calibrated P(contact) per frame, (T,) float64: Platt map of ``predict_raw``."""
        return self.platt_(self.predict_raw(crops))

    def predict(self, crops: SessionCrops | np.ndarray) -> np.ndarray:
        """Contact decision per frame, (T,) bool: ``predict_proba >= threshold_``."""
        return self.predict_proba(crops) >= self.threshold_

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready description (everything but the weights, which stay in the checkpoints)."""
        return {
            "params": _params_to_dict(self.params),
            "session_names": list(self.session_names_),
            "checkpoints": list(self.checkpoints_),
            "init": self.init_,
            "platt": {"slope": self.platt_.slope, "intercept": self.platt_.intercept},
            "threshold": self.threshold_,
            "oof_scores": [[float(v) for v in o] for o in self.oof_scores_],
        }

    def save(self, path: str | Path) -> None:
        """Write ``to_dict`` as JSON to ``path`` atomically (keep it beside the fold checkpoints)."""
        with atomic_write(path, "w", encoding="utf-8") as handle:
            json.dump(self.to_dict(), handle, indent=1)

    @classmethod
    def load(cls, path: str | Path, device: str | torch.device | None = None) -> BaselineEnsemble:
        """Read ``ensemble.json`` and its fold checkpoints (``torch.load(weights_only=True)``)."""
        path = Path(path)
        if path.is_dir():
            path = path / ENSEMBLE_FILE
        if not path.is_file():
            raise FileNotFoundError(f"{path}: missing: expected a baseline ensemble description ({ENSEMBLE_FILE})")
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{path}: expected a JSON baseline ensemble description ({exc})") from exc
        expected = {"params", "session_names", "checkpoints", "init", "platt", "threshold", "oof_scores"}
        if not isinstance(data, dict) or set(data) != expected:
            found = sorted(data) if isinstance(data, dict) else type(data).__name__
            raise ValueError(f"{path}: expected keys {sorted(expected)}, found {found}")
        try:
            params = _params_from_dict(BaselineParams, data["params"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: params: {exc}") from exc
        dev = resolve_device(device)
        models = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", BaselineWarning)
            for name in data["checkpoints"]:
                ckpt_path = path.parent / name
                if not ckpt_path.is_file():
                    raise FileNotFoundError(f"{ckpt_path}: missing: expected the fold checkpoint named in {path}")
                ckpt = load_checkpoint(ckpt_path)
                if not ckpt.get("complete") or ckpt.get("params") != _params_to_dict(params):
                    raise ValueError(f"{ckpt_path}: expected a completed fold trained with the params in {path}")
                model = build_model(params)
                model.load_state_dict(ckpt["model"])
                models.append(model.to(dev).eval())
        return cls(
            params=params,
            session_names=data["session_names"],
            checkpoints=data["checkpoints"],
            init=data["init"],
            platt=PlattScaling(float(data["platt"]["slope"]), float(data["platt"]["intercept"])),
            threshold=data["threshold"],
            oof_scores=data["oof_scores"],
            models=models,
            device=dev,
        )
