"""Fold checkpoints of the baseline: written atomically, loaded with ``torch.load(weights_only=True)``,
checked against the run they are meant to resume."""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

from contact_viz.baseline.params import BaselineParams, CHECKPOINT_FORMAT
from contact_viz.io.atomic import atomic_write
from contact_viz.params import to_dict as _params_to_dict


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    import torch

    buffer = io.BytesIO()  # torch.save into a real file turns a full disk into a RuntimeError
    torch.save(payload, buffer)
    with atomic_write(path, "wb") as handle:
        handle.write(buffer.getbuffer())


def load_checkpoint(path: Path) -> dict[str, Any]:
    import torch

    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:
        raise ValueError(
            f"{path}: expected a contact-viz baseline fold checkpoint ({type(exc).__name__}: {exc})"
        ) from exc
    if not isinstance(data, dict) or data.get("format") != CHECKPOINT_FORMAT:
        raise ValueError(f"{path}: expected a contact-viz baseline fold checkpoint of format {CHECKPOINT_FORMAT}")
    return data


def checkpoint_complete(path: Path) -> bool:
    """Whether ``path`` holds a completed fold checkpoint (unreadable counts as not complete)."""
    if not path.is_file():
        return False
    try:
        return bool(load_checkpoint(path).get("complete"))
    except ValueError:
        return False


def check_checkpoint(path: Path, data: dict[str, Any], params: BaselineParams, info: dict[str, Any]) -> None:
    stored_params, current = data.get("params"), _params_to_dict(params)
    if stored_params != current:
        diff = sorted(k for k in current if not isinstance(stored_params, dict) or stored_params.get(k) != current[k])
        raise ValueError(
            f"{path}: this checkpoint was made with other BaselineParams (differing: {diff}); "
            "use another checkpoint directory or delete it"
        )
    if data.get("fold_info") != info:
        raise ValueError(
            f"{path}: this checkpoint belongs to another run (stored {data.get('fold_info')}, expected {info}); "
            "use another checkpoint directory or delete it"
        )
