"""Leave-one-session-out training of the fold models (``fit_loso``), with resumable checkpoints."""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from contact_viz.baseline.checkpoint import check_checkpoint, checkpoint_complete, load_checkpoint, save_checkpoint
from contact_viz.baseline.crops import SessionCrops
from contact_viz.baseline.ensemble import BaselineEnsemble
from contact_viz.baseline.net import build_model, make_augmentation, prepare_batch, raw_scores, resolve_device
from contact_viz.baseline.params import (
    BaselineParams, BaselineWarning, CHECKPOINT_FORMAT, CONTACT, ENSEMBLE_FILE, NO_CONTACT, N_CLASSES,
)
from contact_viz.baseline.platt import fit_platt
from contact_viz.model.hmm import select_f1_threshold
from contact_viz.params import to_dict as _params_to_dict

if TYPE_CHECKING:  # torch is imported lazily: importing this module stays cheap
    import torch


@dataclass(frozen=True)
class FoldEvent:
    """Progress report of ``fit_loso``."""

    fold: int  # fold index k, 0-based
    held_out: str  # name of the session left out of fold k
    stage: str  # "loaded" (complete checkpoint reused), "resumed" (partial checkpoint), "epoch", "done"
    epoch: int  # epochs finished in this fold, count
    loss: float | None = None  # mean weighted cross-entropy of the epoch just finished ("epoch"), -


def _fold_seeds(seed: int, fold: int) -> tuple[int, int]:
    """(torch global seed, shuffle seed) of one fold, independent streams."""
    a, b = np.random.SeedSequence([seed, fold]).generate_state(2)
    return int(a), int(b)


def _init_tag(weights: str | Path | None) -> str:
    return "scratch" if weights is None else f"imagenet:{Path(weights).name}"


def _check_crops(sessions: Sequence[SessionCrops], params: BaselineParams) -> list[str]:
    if len(sessions) < 2:
        raise ValueError(f"fit_loso: expected at least 2 training sessions, got {len(sessions)}")
    names = [s.name for s in sessions]
    if len(set(names)) != len(names):
        raise ValueError(f"fit_loso: expected distinct session names, got {names}")
    for s in sessions:
        if not isinstance(s, SessionCrops):
            raise TypeError(f"fit_loso: expected SessionCrops, got {type(s).__name__}")
        if s.crops.shape[1] != params.crop_px:
            raise ValueError(
                f"fit_loso: session {s.name!r} has {s.crops.shape[1]} px crops, params.crop_px is {params.crop_px}"
            )
        if not s.trainable.any():
            raise ValueError(
                f"fit_loso: session {s.name!r} has no labelled frame with a readable image (labels all -1?); "
                "it can be neither trained on nor used for calibration"
            )
    return names


def _fold_info(k: int, names: list[str], sessions: Sequence[SessionCrops], init: str) -> dict[str, Any]:
    return {
        "fold": k,
        "held_out": names[k],
        "train_sessions": [n for i, n in enumerate(names) if i != k],
        "n_frames": [len(s) for s in sessions],
        "init": init,
    }


def _class_weights(labels: np.ndarray, fold_name: str) -> np.ndarray:
    counts = np.array([(labels == NO_CONTACT).sum(), (labels == CONTACT).sum()], dtype=np.float64)
    if (counts == 0).any():
        raise ValueError(
            f"fit_loso, {fold_name}: the training frames hold {int(counts[0])} no-contact and "
            f"{int(counts[1])} contact frames; both classes are needed"
        )
    return counts.sum() / (N_CLASSES * counts)


def _gather(sessions: Sequence[SessionCrops], refs: np.ndarray) -> np.ndarray:
    """Crops of (session, frame) pairs ``refs`` (B, 2) as (B, S, S, 3) uint8."""
    return np.stack([sessions[s].crops[i] for s, i in refs])


def _train_fold(
    k: int,
    sessions: Sequence[SessionCrops],
    names: list[str],
    params: BaselineParams,
    weights: str | Path | None,
    device: torch.device,
    path: Path,
    progress: Callable[[FoldEvent], None] | None,
) -> tuple[torch.nn.Module, np.ndarray]:
    """Train (or load, or resume) fold ``k``; returns (model in eval mode on ``device``, out-of-fold raw scores)."""
    import torch

    info = _fold_info(k, names, sessions, _init_tag(weights))
    data = None
    if path.is_file():
        data = load_checkpoint(path)
        check_checkpoint(path, data, params, info)
    torch_seed, shuffle_seed = _fold_seeds(params.seed, k)
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        torch.manual_seed(torch_seed)
        with warnings.catch_warnings():  # fit_loso warns once about training from scratch
            warnings.simplefilter("ignore", BaselineWarning)
            model = build_model(params, None if data is not None else weights).to(device)
        if data is not None and data["complete"]:
            model.load_state_dict(data["model"])
            model.eval()
            if progress is not None:
                progress(FoldEvent(k, names[k], "loaded", int(data["epochs_done"])))
            return model, data["oof_scores"].numpy().astype(np.float64)

        refs = np.concatenate(
            [np.stack([np.full(int(s.trainable.sum()), i), np.flatnonzero(s.trainable)], axis=1)
             for i, s in enumerate(sessions) if i != k]
        )
        train_labels = np.concatenate([s.labels[s.trainable] for i, s in enumerate(sessions) if i != k])
        class_weights = _class_weights(train_labels, f"fold {k} (leaving out {names[k]!r})")
        criterion = torch.nn.CrossEntropyLoss(weight=torch.tensor(class_weights, dtype=torch.float32, device=device))
        optimizer = torch.optim.Adam(model.parameters(), lr=params.lr, weight_decay=params.weight_decay)
        augmentation = make_augmentation(params).to(device)
        shuffle = torch.Generator().manual_seed(shuffle_seed)
        start_epoch = 0
        if data is not None:
            model.load_state_dict(data["model"])
            optimizer.load_state_dict(data["optimizer"])
            torch.set_rng_state(data["rng_torch"])
            shuffle.set_state(data["rng_shuffle"])
            if device.type == "cuda" and "rng_cuda" in data:
                torch.cuda.set_rng_state(data["rng_cuda"], device)
            start_epoch = int(data["epochs_done"])
            if progress is not None:
                progress(FoldEvent(k, names[k], "resumed", start_epoch))
        labels_t = torch.from_numpy(train_labels.astype(np.int64))
        for epoch in range(start_epoch, params.epochs):
            model.train()
            order = torch.randperm(len(refs), generator=shuffle).numpy()
            total, seen = 0.0, 0
            for start in range(0, len(order), params.batch_size):
                batch = order[start : start + params.batch_size]
                x = prepare_batch(_gather(sessions, refs[batch]), device, augmentation)
                y = labels_t[batch].to(device)
                optimizer.zero_grad(set_to_none=True)
                loss = criterion(model(x), y)
                loss.backward()
                optimizer.step()
                total += float(loss.detach()) * len(batch)
                seen += len(batch)
            payload = {
                "format": CHECKPOINT_FORMAT,
                "params": _params_to_dict(params),
                "fold_info": info,
                "complete": False,
                "epochs_done": epoch + 1,
                "model": model.state_dict(),
                "optimizer": optimizer.state_dict(),
                "rng_torch": torch.get_rng_state(),
                "rng_shuffle": shuffle.get_state(),
            }
            if device.type == "cuda":
                payload["rng_cuda"] = torch.cuda.get_rng_state(device)
            save_checkpoint(path, payload)
            if progress is not None:
                progress(FoldEvent(k, names[k], "epoch", epoch + 1, total / seen))
        oof = raw_scores(model, sessions[k].crops, params.eval_batch_size, device)
        save_checkpoint(
            path,
            {
                "format": CHECKPOINT_FORMAT,
                "params": _params_to_dict(params),
                "fold_info": info,
                "complete": True,
                "epochs_done": params.epochs,
                "model": model.state_dict(),
                "oof_scores": torch.from_numpy(oof),
            },
        )
        if progress is not None:
            progress(FoldEvent(k, names[k], "done", params.epochs))
    return model, oof


def fit_loso(
    sessions: Sequence[SessionCrops],
    params: BaselineParams,
    checkpoint_dir: str | Path,
    weights: str | Path | None = None,
    device: str | torch.device | None = None,
    progress: Callable[[FoldEvent], None] | None = None,
) -> BaselineEnsemble:
    """Leave-one-session-out training of K = len(sessions) models, Platt calibration and threshold.

    Fold k trains on every session but k (frames labelled 0/1 with a readable image) and scores
    session k. Completed folds found in ``checkpoint_dir`` are loaded, an interrupted fold resumes
    (see the docstring of ``contact_viz.baseline``). A checkpoint made with other params, sessions or
    init is an error.
    Writes ``checkpoint_dir/ensemble.json`` and returns the fitted ensemble (models on ``device``).
    """
    names = _check_crops(sessions, params)
    directory = Path(checkpoint_dir)
    directory.mkdir(parents=True, exist_ok=True)
    dev = resolve_device(device)
    if weights is not None and not Path(weights).expanduser().is_file():
        raise FileNotFoundError(
            f"{Path(weights).expanduser()}: missing: expected an efficientnet-pytorch ImageNet state dict (.pth) "
            f"for {params.model_name}"
        )
    if weights is None and not all(checkpoint_complete(directory / f"fold_{k}.pt") for k in range(len(sessions))):
        warnings.warn(
            f"no ImageNet weights given (--weights): {params.model_name} trains from scratch",
            BaselineWarning,
            stacklevel=2,
        )
    models, oof = [], []
    for k in range(len(sessions)):
        model, scores = _train_fold(k, sessions, names, params, weights, dev, directory / f"fold_{k}.pt", progress)
        models.append(model)
        oof.append(scores)
    pooled_scores = np.concatenate(oof)
    pooled_labels = np.concatenate([s.labels for s in sessions])
    try:
        platt = fit_platt(pooled_scores, pooled_labels)
        threshold = select_f1_threshold(platt(pooled_scores), pooled_labels)
    except ValueError as exc:
        raise ValueError(f"fit_loso, calibration on pooled out-of-fold scores: {exc}") from exc
    ensemble = BaselineEnsemble(
        params=params,
        session_names=names,
        checkpoints=[f"fold_{k}.pt" for k in range(len(sessions))],
        init=_init_tag(weights),
        platt=platt,
        threshold=threshold,
        oof_scores=oof,
        models=models,
        device=dev,
    )
    ensemble.save(directory / ENSEMBLE_FILE)
    return ensemble
