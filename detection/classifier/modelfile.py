"""Model files: safetensors weights plus JSON metadata. Nothing is ever unpickled.

``MODEL`` is a folder holding ``model.safetensors`` (weights, with the metadata JSON also in the
safetensors header so the file is self-contained) and ``model.json`` (the same metadata, for
people). Either the folder or the ``.safetensors`` file can be passed to ``load_model``.
"""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path
from typing import Any

import torch

from roadsurf.core.atomic import atomic_path, write_json_atomic
from roadsurf.core.errors import ModelFileError
from roadsurf.detection.classifier.config import CLASS_NAMES
from roadsurf.detection.classifier.network import DefectNet

log = logging.getLogger(__name__)

FORMAT = "roadsurf-defectnet"
FORMAT_VERSION = 1
WEIGHTS_NAME = "model.safetensors"
META_NAME = "model.json"


def _clean(obj: Any) -> Any:
    """NaN/inf -> None so the metadata is strict JSON."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _clean(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_clean(v) for v in obj]
    return obj


def model_weights_path(model: str | Path) -> Path:
    """The ``.safetensors`` file of a model folder (or the file itself)."""
    p = Path(model)
    return p / WEIGHTS_NAME if p.is_dir() or p.suffix != ".safetensors" else p


def save_model(out: str | Path, net: DefectNet, meta: dict[str, Any]) -> Path:
    """Write ``out/model.safetensors`` and ``out/model.json`` atomically; returns the weights path.

    ``meta`` must be JSON-serialisable; the architecture fields are added here.
    """
    from safetensors.torch import save_file

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    full = _clean(dict(meta))
    full.update(
        format=FORMAT,
        format_version=FORMAT_VERSION,
        class_names=list(CLASS_NAMES),
        input_size_px=net.input_size_px,
        temperature=float(net.temperature),
        logit_bias=float(net.logit_bias),
        tta_views=int(net.tta_views),
        torch_version=torch.__version__,
    )
    full.setdefault("architecture", {})
    tensors = {k: v.detach().cpu().contiguous() for k, v in net.state_dict().items()}
    path = out / WEIGHTS_NAME
    with atomic_path(path) as tmp:
        save_file(tensors, str(tmp), metadata={"roadsurf": json.dumps(full, allow_nan=False)})
    write_json_atomic(out / META_NAME, full)
    return path


def load_model(model: str | Path, device: torch.device | str = "cpu") -> tuple[DefectNet, dict]:
    """Load a model folder or ``.safetensors`` file -> (net in eval mode, metadata).

    Raises ``ModelFileError`` naming the file and saying what to do when it is missing, corrupt
    or incompatible with this version of roadsurf.
    """
    from safetensors import SafetensorError
    from safetensors.torch import load_file

    path = model_weights_path(model)
    if not path.is_file():
        raise ModelFileError(
            f"{path}: model file not found. Train one with `roadsurf train DATASET --out MODEL` "
            "and pass the MODEL folder (or its model.safetensors)."
        )
    try:
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as f:
            header = f.metadata() or {}
        tensors = load_file(str(path), device="cpu")
    except (SafetensorError, OSError, ValueError, RuntimeError) as e:
        raise ModelFileError(
            f"{path}: not a readable safetensors model file ({e}). The file is corrupt or "
            "truncated; retrain with `roadsurf train` or copy the file again."
        ) from e
    try:
        meta = json.loads(header["roadsurf"])
    except (KeyError, json.JSONDecodeError) as e:
        raise ModelFileError(
            f"{path}: safetensors file has no roadsurf metadata; it was not written by "
            "`roadsurf train`. Retrain the model."
        ) from e
    if meta.get("format") != FORMAT or int(meta.get("format_version", -1)) > FORMAT_VERSION:
        raise ModelFileError(
            f"{path}: model format {meta.get('format')!r} v{meta.get('format_version')} is not "
            f"supported (expected {FORMAT} v<={FORMAT_VERSION}); retrain with this roadsurf."
        )
    if list(meta.get("class_names", [])) != list(CLASS_NAMES):
        raise ModelFileError(
            f"{path}: class order {meta.get('class_names')} differs from {list(CLASS_NAMES)}; "
            "retrain the model."
        )
    arch = meta.get("architecture", {})
    try:
        net = DefectNet(
            input_size_px=int(meta["input_size_px"]),
            dropout=float(arch.get("dropout", 0.5)),
            width=int(arch.get("width", 1)),
            highpass_frac=float(arch.get("highpass_frac", 0.0)),
        )
        net.load_state_dict(tensors, strict=True)
        net.temperature = float(meta.get("temperature", 1.0))  # older files: uncalibrated
        if not 0.0 < net.temperature < 1e3:
            raise ValueError(f"softmax temperature {net.temperature} outside (0, 1000)")
        net.logit_bias = float(meta.get("logit_bias", 0.0))  # older files: no prior correction
        if not abs(net.logit_bias) < 50.0:
            raise ValueError(f"logit bias {net.logit_bias} outside (-50, 50)")
        net.tta_views = int(meta.get("tta_views", 1))  # older files: no test-time views
        if net.tta_views not in (1, 2, 4, 8):
            raise ValueError(f"tta_views {net.tta_views} is not 1, 2, 4 or 8")
    except (KeyError, RuntimeError, ValueError, TypeError) as e:
        raise ModelFileError(
            f"{path}: weights do not fit the DefectNet architecture described in its metadata "
            f"({e}); the file is incompatible with this roadsurf version. Retrain the model."
        ) from e
    net.eval()
    return net.to(device), meta
