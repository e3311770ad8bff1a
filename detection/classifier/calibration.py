"""Calibration of the trained defect CNN on its validation split (dissertation §5.3).

Temperature scaling (T) or Platt scaling of the logit margin (T and a bias b), plus the
label-shift correction from the data's defect share to an expected one (``defect_prior``), so
that p >= ``fusion_threshold`` means about that share of correct decisions. ``calibrate_model``
rewrites the saved model with T and b; ``train`` calls it after the last epoch.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
import torch

from roadsurf.core.errors import RoadsurfError
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.classifier.modelfile import load_model, save_model
from roadsurf.detection.classifier.network import DefectNet

log = logging.getLogger(__name__)


@torch.no_grad()
def logits_of(
    net: DefectNet, images: np.ndarray, device: torch.device, batch: int = 256
) -> np.ndarray:
    """Logits (N, 2) for uint8 images (N, S, S): test-time views averaged, no temperature."""
    net.eval()
    x = torch.as_tensor(np.asarray(images))
    out = [
        net.logits(x[i : i + batch].unsqueeze(1).to(device)).float().cpu()
        for i in range(0, x.shape[0], batch)
    ]
    return torch.cat(out).numpy() if out else np.zeros((0, 2), np.float32)


def fit_temperature(logits: np.ndarray, labels: np.ndarray, bias: float = 0.0) -> float:
    """Temperature T minimising the validation negative log-likelihood of
    softmax(logits / T + (0, bias)).

    A 1-D search over log T in [ln 0.25, ln 20] (robust for the few dozen validation frames
    here; no optimiser state). Returns 1.0 for an empty set.
    """
    logits = np.asarray(logits, np.float64)
    labels = np.asarray(labels, np.int64)
    if logits.shape[0] == 0:
        return 1.0
    z = logits[:, 1] - logits[:, 0]  # binary margin; softmax(l/T)[1] = sigmoid(z/T)
    sign = np.where(labels == 1, 1.0, -1.0)

    def nll(t: float) -> float:
        return float(np.mean(np.logaddexp(0.0, -sign * (z / t + bias))))

    grid = np.exp(np.linspace(np.log(0.25), np.log(20.0), 200))
    vals = [nll(t) for t in grid]
    return float(grid[int(np.argmin(vals))])


def _logit(p: float) -> float:
    p = min(max(float(p), 1e-6), 1 - 1e-6)
    return math.log(p / (1 - p))


def prior_shift(prior_trained: float, prior_target: float) -> float:
    """Log-odds shift moving a posterior from the class prior a net was trained at to another
    (label-shift correction): logit(prior_target) - logit(prior_trained). Priors in (0, 1)."""
    for name, v in (("prior_trained", prior_trained), ("prior_target", prior_target)):
        if not 0.0 < v < 1.0:
            raise RoadsurfError(f"{name} must be in (0, 1), got {v}")
    return _logit(prior_target) - _logit(prior_trained)


def _calibration_summary(
    logits: np.ndarray, labels: np.ndarray, t: float, threshold: float, bias: float = 0.0
) -> dict[str, float]:
    z = (logits[:, 1] - logits[:, 0]) / t + bias
    p = 1.0 / (1.0 + np.exp(-z))
    conf = np.maximum(p, 1 - p) >= threshold
    correct = (p >= 0.5) == (labels == 1)
    sign = np.where(labels == 1, 1.0, -1.0)
    return {
        "nll": float(np.mean(np.logaddexp(0.0, -sign * z))),
        "share_confident": float(conf.mean()),
        "accuracy_when_confident": float(correct[conf].mean()) if conf.any() else float("nan"),
        "share_confident_clear_of_clear": float(conf[labels == 0].mean())
        if (labels == 0).any()
        else float("nan"),
    }


def fit_temperature_bias(logits: np.ndarray, labels: np.ndarray) -> tuple[float, float]:
    """(T, b) minimising the validation negative log-likelihood of sigmoid(z / T + b), z the
    defect-minus-clear logit margin (Platt scaling of the margin). b corrects the class prior
    the net was trained at (balanced sampling: 1:1) toward the validation frames'. Grid search,
    log T in [ln 0.25, ln 20] and b in [-4, 4]; (1, 0) for an empty set."""
    logits = np.asarray(logits, np.float64)
    labels = np.asarray(labels, np.int64)
    if logits.shape[0] == 0:
        return 1.0, 0.0
    z = logits[:, 1] - logits[:, 0]
    sign = np.where(labels == 1, 1.0, -1.0)
    ts = np.exp(np.linspace(np.log(0.25), np.log(20.0), 200))
    bs = np.linspace(-4.0, 4.0, 161)
    best = (np.inf, 1.0, 0.0)
    for t in ts:  # (161, n) per temperature: small enough for any validation split here
        nll = np.mean(np.logaddexp(0.0, -sign[None, :] * (z[None, :] / t + bs[:, None])), axis=1)
        k = int(np.argmin(nll))
        if nll[k] < best[0] - 1e-12:
            best = (float(nll[k]), float(t), float(bs[k]))
    return best[1], best[2]


def calibrate_model(
    out: Path,
    images: np.ndarray,
    labels: np.ndarray,
    device: torch.device,
    cfg: ClassifierConfig,
    prior_trained: float = 0.5,
    prior_data: float = 0.5,
) -> None:
    """Calibrate the saved model in ``out`` on the validation split (rewrites the model):
    temperature T,
    with ``calibrate_bias`` a logit bias b fitted jointly, plus the shift from the data's
    defect share ``prior_data`` to ``cfg.defect_prior`` when that is set. ``prior_trained``
    (defect share the net was trained at) is recorded for reference."""
    net, meta = load_model(out, device)
    lg = logits_of(net, images, device)
    if cfg.calibrate_bias:
        t, b_val = fit_temperature_bias(lg, labels)
    else:
        t, b_val = fit_temperature(lg, labels), 0.0
    b = b_val
    if cfg.defect_prior is not None:
        b += prior_shift(prior_data, cfg.defect_prior)
    net.temperature = t
    net.logit_bias = b
    meta["calibration"] = {
        "method": "temperature"
        + (" and logit bias" if cfg.calibrate_bias else "")
        + " scaling on the validation split (NLL)",
        "temperature": t,
        "logit_bias_fitted": b_val,
        "logit_bias": b,
        "prior_trained": prior_trained,
        "prior_data": prior_data,
        "defect_prior": cfg.defect_prior,
        "n_val": int(len(labels)),
        "fusion_threshold": cfg.fusion_threshold,
        "before": _calibration_summary(lg, labels, 1.0, cfg.fusion_threshold),
        "after": _calibration_summary(lg, labels, t, cfg.fusion_threshold, b_val),
    }
    log.info("calibration: T = %.2f, bias %.2f, %s", t, b, meta["calibration"]["after"])
    save_model(out, net, meta)


def training_priors(
    labels: np.ndarray, augmented: np.ndarray, train_idx: np.ndarray, cfg: ClassifierConfig
) -> tuple[float, float]:
    """(defect share the net is trained at, defect share of the original self-labelled frames).

    Balanced sampling and class weighting both train at 1:1; otherwise the training split's
    share (augmented copies included). Shares are clipped to [0.001, 0.999].
    """
    lab = np.asarray(labels)
    orig = lab[~np.asarray(augmented, bool)]
    data = float(orig.mean()) if orig.size else 0.5
    if cfg.balanced_sampling or cfg.class_weighting:
        trained = 0.5
    else:
        tr = lab[np.asarray(train_idx, int)]
        trained = float(tr.mean()) if tr.size else 0.5
    return float(np.clip(trained, 1e-3, 1 - 1e-3)), float(np.clip(data, 1e-3, 1 - 1e-3))
