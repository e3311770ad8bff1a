"""Training of the defect CNN (dissertation §5.3): seeded, resumable, with a progress bar.

``train(dataset_dir, out, cfg)`` splits the dataset 80/20 by source frame (augmented copies stay
with their original, and validation uses original frames only, so no augmented twin of a
validation image is trained on), trains with Adam and an exponential learning-rate decay
(×``lr_decay`` per epoch), balances the classes by sampling (or loss weighting), and keeps the
weights of the best validation epoch in ``out/model.safetensors`` with metadata ``out/model.json``.
After every epoch ``out/checkpoint.pt`` (a torch state dict, read back with
``weights_only=True``) lets an interrupted run resume where it stopped. The saved model is then
calibrated on the validation split (``calibration``).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from tqdm import tqdm

from roadsurf.core.atomic import atomic_path, output_error, write_json_atomic
from roadsurf.core.config import to_dict
from roadsurf.core.errors import ModelFileError, RoadsurfError
from roadsurf.core.fingerprint import Fingerprint
from roadsurf.detection.classifier import augment
from roadsurf.detection.classifier.calibration import calibrate_model, training_priors
from roadsurf.detection.classifier.config import CLASS_NAMES, ClassifierConfig
from roadsurf.detection.classifier.dataset import Dataset, load_dataset
from roadsurf.detection.classifier.modelfile import META_NAME, save_model
from roadsurf.detection.classifier.network import DefectNet, pick_device

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.pt"


def split_groups(
    groups: list[str], labels: np.ndarray, augmented: np.ndarray, val_fraction: float, seed: int
) -> tuple[np.ndarray, np.ndarray]:
    """Stratified group split -> (train indices, validation indices).

    Whole groups (a frame and its augmented copies) go to one side; per class about
    ``val_fraction`` of the groups (at least one when the class has >= 2 groups) validate.
    Validation keeps only non-augmented images.
    """
    rng = np.random.default_rng(seed)
    group_label: dict[str, int] = {}
    for g, lab in zip(groups, labels, strict=True):
        group_label[g] = max(group_label.get(g, 0), int(lab))
    val_groups: set[str] = set()
    for c in (0, 1):
        gs = sorted(g for g, lab in group_label.items() if lab == c)
        if len(gs) < 2:
            continue
        k = max(1, int(round(val_fraction * len(gs))))
        val_groups.update(gs[i] for i in rng.permutation(len(gs))[:k])
    is_val = np.array([g in val_groups for g in groups])
    train_idx = np.flatnonzero(~is_val)
    val_idx = np.flatnonzero(is_val & ~augmented)
    return train_idx, val_idx


def metrics(y_true: np.ndarray, y_pred: np.ndarray) -> dict[str, float]:
    """Frame-level accuracy, precision, recall, F1 (defect = positive) and TP/TN/FP/FN."""
    y_true = np.asarray(y_true).astype(bool)
    y_pred = np.asarray(y_pred).astype(bool)
    tp = int(np.sum(y_true & y_pred))
    tn = int(np.sum(~y_true & ~y_pred))
    fp = int(np.sum(~y_true & y_pred))
    fn = int(np.sum(y_true & ~y_pred))
    n = max(1, tp + tn + fp + fn)
    prec = tp / (tp + fp) if tp + fp else float("nan")
    rec = tp / (tp + fn) if tp + fn else float("nan")
    spec = tn / (tn + fp) if tn + fp else float("nan")
    f1 = 2 * prec * rec / (prec + rec) if tp else 0.0
    bal = np.nanmean([rec, spec]) if not (np.isnan(rec) and np.isnan(spec)) else float("nan")
    return {
        "accuracy": (tp + tn) / n,
        "precision": prec,
        "recall": rec,
        "f1": f1,
        "balanced_accuracy": float(bal),
        "tp": tp,
        "tn": tn,
        "fp": fp,
        "fn": fn,
    }


def _random_dihedral(x: torch.Tensor, gen: torch.Generator) -> torch.Tensor:
    """Random flips / quarter turns per batch (cheap on-line augmentation; roads have no 'up')."""
    k = int(torch.randint(0, 4, (1,), generator=gen))
    x = torch.rot90(x, k, dims=(2, 3))
    if int(torch.randint(0, 2, (1,), generator=gen)):
        x = torch.flip(x, dims=(3,))
    return x


@torch.no_grad()
def predict(
    net: DefectNet, images: np.ndarray | torch.Tensor, device: torch.device, batch: int = 256
) -> np.ndarray:
    """p_defect (N,) for uint8 images (N, S, S)."""
    net.eval()
    x = torch.as_tensor(np.asarray(images))
    out = []
    for i in range(0, x.shape[0], batch):
        xb = x[i : i + batch].unsqueeze(1).to(device)
        out.append(net.predict_proba(xb)[:, 1].float().cpu())
    return torch.cat(out).numpy() if out else np.zeros(0, np.float32)


def make_scheduler(
    optim: torch.optim.Optimizer, cfg: ClassifierConfig
) -> torch.optim.lr_scheduler.LRScheduler:
    """Per-epoch learning-rate schedule (``cfg.lr_schedule``)."""
    if cfg.lr_schedule == "exponential":
        return torch.optim.lr_scheduler.ExponentialLR(optim, gamma=cfg.lr_decay)
    if cfg.lr_schedule == "cosine":
        warm = max(0, int(cfg.warmup_epochs))
        total = max(1, int(cfg.epochs))

        def factor(epoch: int) -> float:
            # epoch = number of scheduler steps taken; factor for the NEXT epoch
            if epoch < warm:
                return (epoch + 1) / (warm + 1)
            t = min(1.0, (epoch - warm) / max(1, total - warm))
            # a Python float: a numpy scalar would end up in the optimiser state and make the
            # checkpoint unreadable with torch.load(weights_only=True), i.e. no resume
            return float(0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * t)))

        return torch.optim.lr_scheduler.LambdaLR(optim, factor)
    raise RoadsurfError(
        f"classifier.lr_schedule {cfg.lr_schedule!r} unknown; use 'exponential' or 'cosine'"
    )


# settings that do not change the trained weights: a checkpoint stays resumable across them
_NOT_TRAINING = frozenset(
    {
        "device",
        "num_threads",
        "screen_num_threads",
        "screen_in_subprocess",
        "epochs",
        "calibrate",
        "calibrate_bias",
        "defect_prior",
        "fusion_threshold",
        "confirm_defect_with_3d",
        "context_frames",
        "audit_every_m",
        "audit_every_frames",
        "audit_probe",
        "audit_probe_depth_frac",
        "audit_probe_max_deep_points",
        "grow_along_defects",
        "screen_batch_size",
    }
)


def _fingerprint(ds: Dataset, cfg: ClassifierConfig) -> str:
    keep = {k: v for k, v in to_dict(cfg).items() if k not in _NOT_TRAINING}
    fp = Fingerprint().add_file_bytes(ds.root / "labels.csv").add_repr(sorted(keep.items()))
    return fp.hexdigest(16)


def train_steps(
    net: DefectNet,
    images: torch.Tensor,
    labels: torch.Tensor,
    optim: torch.optim.Optimizer,
    steps: int,
    batch: int,
    gen: torch.Generator,
    weights: torch.Tensor | None = None,
    class_weight: torch.Tensor | None = None,
    dihedral: bool = True,
    photometric: float = 0.0,
) -> float:
    """Run ``steps`` optimiser steps on uint8 ``images`` (N, S, S); returns the mean loss.

    ``weights`` (N,) are sampling weights (balanced sampling), else uniform. ``photometric`` is
    the strength of the random lighting/camera changes (``augment.photometric``; 0 = none).
    """
    net.train()
    device = next(net.parameters()).device
    loss_fn = nn.CrossEntropyLoss(
        weight=class_weight.to(device) if class_weight is not None else None
    )
    n = images.shape[0]
    total = 0.0
    for _ in range(steps):
        if weights is not None:
            idx = torch.multinomial(weights, batch, replacement=True, generator=gen)
        else:
            idx = torch.randint(0, n, (min(batch, n),), generator=gen)
        xb = images[idx].unsqueeze(1)
        if dihedral:
            xb = _random_dihedral(xb, gen)
        if photometric > 0:
            xb = augment.photometric(xb, gen, photometric)
        xb, yb = xb.to(device), labels[idx].to(device)
        optim.zero_grad(set_to_none=True)
        loss = loss_fn(net(xb), yb)
        loss.backward()
        optim.step()
        total += float(loss.detach())
    return total / max(1, steps)


def train(
    dataset_dir: str | Path,
    out: str | Path,
    cfg: ClassifierConfig | None = None,
    *,
    resume: bool = True,
    progress: bool = True,
) -> dict[str, Any]:
    """Train on ``dataset_dir`` into the model folder ``out``; returns the metadata written."""
    cfg = cfg or ClassifierConfig()
    out = Path(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as e:  # a file in the way, a read-only folder
        raise output_error(e, out) from e
    if cfg.num_threads > 0:
        torch.set_num_threads(cfg.num_threads)
    device = pick_device(cfg.device)
    t0 = time.perf_counter()
    ds = load_dataset(dataset_dir, cfg.input_size_px)
    augmented = np.array([bool(r.get("augmentation")) for r in ds.rows])
    tr, va = split_groups(ds.groups, ds.labels, augmented, cfg.val_fraction, cfg.seed)
    if len(np.unique(ds.labels[tr])) < 2:
        raise RoadsurfError(
            f"{dataset_dir}: the training split holds only class "
            f"{CLASS_NAMES[int(ds.labels[tr][0])]!r}; label more drives (with defects and "
            "clear road) before training"
        )
    x_tr = torch.from_numpy(ds.images[tr])
    y_tr = torch.from_numpy(ds.labels[tr])
    counts = torch.bincount(y_tr, minlength=2).double()
    weights = (1.0 / counts)[y_tr] if cfg.balanced_sampling else None
    class_weight = (counts.sum() / (2 * counts)).float() if cfg.class_weighting else None

    torch.manual_seed(cfg.seed)
    net = DefectNet(cfg.input_size_px, cfg.dropout, cfg.width, cfg.highpass_frac).to(device)
    if cfg.tta_views not in (1, 2, 4, 8):
        raise RoadsurfError(f"classifier.tta_views must be 1, 2, 4 or 8, got {cfg.tta_views}")
    net.tta_views = int(cfg.tta_views)
    optim = torch.optim.Adam(net.parameters(), lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
    sched = make_scheduler(optim, cfg)
    fp = _fingerprint(ds, cfg)
    history: list[dict[str, float]] = []
    best: dict[str, float] = {}
    start_epoch = 0
    ckpt_path = out / CHECKPOINT_NAME
    if resume and ckpt_path.is_file():
        ck = _read_checkpoint(ckpt_path, device)
        if ck.get("fingerprint") == fp:
            try:
                net.load_state_dict(ck["model"])
                optim.load_state_dict(ck["optim"])
                sched.load_state_dict(ck["sched"])
                history = list(ck["history"])
                best = dict(ck["best"])
                start_epoch = int(ck["epoch"])
            except (KeyError, TypeError, ValueError, RuntimeError) as e:
                raise _bad_checkpoint(ckpt_path, e) from e
            log.info("resuming %s at epoch %d of %d", ckpt_path, start_epoch, cfg.epochs)
        else:
            log.warning("%s belongs to other data or settings; training from scratch", ckpt_path)

    steps = max(cfg.min_steps_per_epoch, int(np.ceil(len(tr) / cfg.batch_size)))
    bar = tqdm(
        range(start_epoch, cfg.epochs),
        desc="train",
        unit="epoch",
        initial=start_epoch,
        total=cfg.epochs,
        disable=not progress,
    )
    for epoch in bar:
        gen = torch.Generator().manual_seed(cfg.seed * 1000 + epoch)
        torch.manual_seed(cfg.seed * 1000 + epoch)  # dropout masks
        loss = train_steps(
            net,
            x_tr,
            y_tr,
            optim,
            steps,
            cfg.batch_size,
            gen,
            weights,
            class_weight,
            photometric=cfg.photometric_strength,
        )
        sched.step()
        p_val = predict(net, ds.images[va], device) if len(va) else np.zeros(0)
        m = metrics(ds.labels[va], p_val >= 0.5) if len(va) else {}
        rec = {"epoch": epoch + 1, "loss": loss, "lr": optim.param_groups[0]["lr"]}
        rec.update({f"val_{k}": float(v) for k, v in m.items()})
        history.append(rec)
        score = (m.get("balanced_accuracy", 0.0), -loss) if m else (0.0, -loss)
        score = (np.nan_to_num(score[0]), score[1])
        improved = not best or tuple(score) > (best["score"], best["neg_loss"])
        if improved or not cfg.keep_best_epoch:
            best = {"epoch": epoch + 1, "score": float(score[0]), "neg_loss": float(score[1])}
            _save(out, net, cfg, ds, tr, va, rec, history, device, t0)
        bar.set_postfix(
            loss=f"{loss:.3f}",
            val_acc=f"{m.get('accuracy', float('nan')):.3f}",
            val_rec=f"{m.get('recall', float('nan')):.3f}",
        )
        with atomic_path(ckpt_path) as tmp:
            torch.save(
                {
                    "model": net.state_dict(),
                    "optim": optim.state_dict(),
                    "sched": sched.state_dict(),
                    "epoch": epoch + 1,
                    "history": history,
                    "best": best,
                    "fingerprint": fp,
                },
                tmp,
            )
    if not (out / META_NAME).is_file():
        _save(out, net, cfg, ds, tr, va, history[-1] if history else {}, history, device, t0)
    from roadsurf.core.atomic import read_json

    if cfg.calibrate and len(va):
        pt, pd = training_priors(ds.labels, augmented, tr, cfg)
        calibrate_model(out, ds.images[va], ds.labels[va], device, cfg, pt, pd)
    meta = read_json(out / META_NAME)
    # the final history/timing is recorded even if the best epoch was earlier
    meta["history"] = history
    meta["best_epoch"] = best.get("epoch")
    meta["train_time_s"] = round(time.perf_counter() - t0, 2)  # this invocation only
    write_json_atomic(out / META_NAME, meta)
    return meta


def _read_checkpoint(path: Path, device: torch.device) -> dict[str, Any]:
    """The training state saved after an epoch; ``ModelFileError`` when it is unreadable."""
    try:
        ck = torch.load(path, map_location=device, weights_only=True)
    except Exception as e:  # noqa: BLE001 - whatever fails to unpickle, the file is bad
        raise _bad_checkpoint(path, e) from e
    if not isinstance(ck, dict):
        raise _bad_checkpoint(path, TypeError(f"it holds a {type(ck).__name__}"))
    return ck


def _bad_checkpoint(path: Path, e: BaseException) -> ModelFileError:
    why = (str(e).strip().splitlines() or [type(e).__name__])[0][:200]
    return ModelFileError(
        f"{path}: not a readable training checkpoint ({why}); the file is corrupt or from "
        "another version. Delete it to train from scratch, or run `roadsurf train` with "
        "--overwrite."
    )


def _save(
    out: Path,
    net: DefectNet,
    cfg: ClassifierConfig,
    ds: Dataset,
    tr: np.ndarray,
    va: np.ndarray,
    rec: dict[str, float],
    history: list[dict[str, float]],
    device: torch.device,
    t0: float,
) -> None:
    meta = {
        "architecture": {
            "name": "DefectNet",
            "dropout": cfg.dropout,
            "width": cfg.width,
            "highpass_frac": cfg.highpass_frac,
        },
        "store_size_px": int(ds.meta.get("store_size_px", cfg.store_size_px)),
        "config": dataclasses.asdict(cfg),
        "training_data": {
            "dataset": str(ds.root.resolve()),
            "drives": ds.meta.get("drives", []),
            "n_train": int(len(tr)),
            "n_val": int(len(va)),
            "train_balance": {
                c: int((ds.labels[tr] == k).sum()) for k, c in enumerate(CLASS_NAMES)
            },
            "val_balance": {c: int((ds.labels[va] == k).sum()) for k, c in enumerate(CLASS_NAMES)},
        },
        "metrics": {"epoch": rec.get("epoch"), **{k: v for k, v in rec.items() if k != "epoch"}},
        "history": history,
        "device": str(device),
        "elapsed_s": round(time.perf_counter() - t0, 2),
    }
    save_model(out, net, meta)
