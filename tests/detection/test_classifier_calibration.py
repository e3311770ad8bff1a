"""Temperature scaling and the learning-rate schedule of the CNN classifier."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
import torch

from roadsurf.core.errors import ModelFileError, RoadsurfError
from roadsurf.detection.classifier.calibration import fit_temperature
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.classifier.modelfile import load_model, save_model
from roadsurf.detection.classifier.network import DefectNet
from roadsurf.detection.classifier.train import make_scheduler


def _logits_with_temperature(t_true: float, n: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """Labels drawn from sigmoid(z / t_true): logits z * 1 are overconfident by t_true."""
    rng = np.random.default_rng(seed)
    z = rng.normal(0.0, 6.0, n)
    y = (rng.random(n) < 1.0 / (1.0 + np.exp(-z / t_true))).astype(np.int64)
    return np.column_stack([np.zeros(n), z]), y


@pytest.mark.parametrize("t_true", [0.5, 1.0, 3.0])
def test_fit_temperature_recovers_the_generating_temperature(t_true: float) -> None:
    logits, y = _logits_with_temperature(t_true, 4000, seed=int(10 * t_true))
    t = fit_temperature(logits, y)
    assert t == pytest.approx(t_true, rel=0.2)


def test_fit_temperature_empty_is_identity() -> None:
    assert fit_temperature(np.zeros((0, 2)), np.zeros(0)) == 1.0


def test_temperature_round_trips_and_softens_probabilities(tmp_path: Path) -> None:
    torch.manual_seed(1)
    net = DefectNet(48).eval()
    x = torch.randint(0, 256, (6, 1, 48, 48), dtype=torch.uint8)
    p1 = net.predict_proba(x)[:, 1]
    net.temperature = 4.0
    p4 = net.predict_proba(x)[:, 1]
    # a higher temperature pulls every probability towards 0.5, never across it
    assert torch.all((p4 - 0.5).abs() <= (p1 - 0.5).abs() + 1e-6)
    assert torch.equal(p4 >= 0.5, p1 >= 0.5)
    save_model(tmp_path / "m", net, {})
    net2, meta = load_model(tmp_path / "m")
    assert meta["temperature"] == 4.0 and net2.temperature == 4.0
    assert torch.allclose(net2.predict_proba(x)[:, 1], p4)
    net.temperature = -1.0
    save_model(tmp_path / "bad", net, {})
    with pytest.raises(ModelFileError, match="temperature"):
        load_model(tmp_path / "bad")


def test_cosine_schedule_warms_up_then_decays() -> None:
    cfg = ClassifierConfig(learning_rate=1e-3, lr_schedule="cosine", warmup_epochs=2, epochs=10)
    opt = torch.optim.SGD([torch.nn.Parameter(torch.zeros(1))], lr=cfg.learning_rate)
    sched = make_scheduler(opt, cfg)
    lrs = []
    for _ in range(cfg.epochs):
        lrs.append(opt.param_groups[0]["lr"])
        opt.step()
        sched.step()
    assert lrs[0] < lrs[1] < lrs[2] == pytest.approx(1e-3)
    assert all(a >= b for a, b in zip(lrs[2:], lrs[3:], strict=False))
    assert lrs[-1] < 0.1e-3
    # the schedule's state must survive the checkpoint (resume loads it with weights_only=True;
    # a numpy scalar learning rate made every cosine checkpoint unreadable)
    buf = io.BytesIO()
    torch.save({"optim": opt.state_dict(), "sched": sched.state_dict()}, buf)
    buf.seek(0)
    back = torch.load(buf, weights_only=True)
    assert back["optim"]["param_groups"][0]["lr"] == pytest.approx(opt.param_groups[0]["lr"])
    with pytest.raises(RoadsurfError, match="lr_schedule"):
        make_scheduler(opt, ClassifierConfig(lr_schedule="step"))


def test_prior_shift_and_bias_calibration(tmp_path: Path) -> None:
    """Balanced sampling trains at 1:1; a fitted logit bias moves p to the data's prior."""
    from roadsurf.detection.classifier.calibration import prior_shift, training_priors

    assert prior_shift(0.5, 0.25) == pytest.approx(np.log(1 / 3))
    assert prior_shift(0.2, 0.2) == 0.0
    with pytest.raises(RoadsurfError):
        prior_shift(0.5, 0.0)
    labels = np.array([1, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 1])
    aug = np.array([0, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0], bool)  # 2 augmented copies
    assert training_priors(labels, aug, np.arange(12), ClassifierConfig()) == (0.5, 0.2)
    unbal = ClassifierConfig(balanced_sampling=False, class_weighting=False)
    assert training_priors(labels, aug, np.arange(12), unbal) == (pytest.approx(4 / 12), 0.2)

    # a net whose posterior is right at 1:1 but too sharp (T = 2), validation drawn at a 1:4
    # prior: the joint fit recovers both the temperature and the prior shift
    from roadsurf.detection.classifier.calibration import fit_temperature_bias

    rng = np.random.default_rng(0)
    z = rng.normal(0.0, 4.0, 8000)
    b = prior_shift(0.5, 0.2)
    y = (rng.random(z.size) < 1 / (1 + np.exp(-(z / 2.0 + b)))).astype(np.int64)
    lg = np.column_stack([np.zeros_like(z), z])
    t_fit, b_fit = fit_temperature_bias(lg, y)
    assert t_fit == pytest.approx(2.0, rel=0.15) and b_fit == pytest.approx(b, abs=0.2)
    assert fit_temperature(lg, y, b) == pytest.approx(2.0, rel=0.15)
    assert fit_temperature_bias(np.zeros((0, 2)), np.zeros(0)) == (1.0, 0.0)

    # stored with the weights and applied by predict_proba: odds scale by exp(bias)
    torch.manual_seed(0)
    net = DefectNet(48).eval()
    x = torch.randint(0, 256, (4, 1, 48, 48), dtype=torch.uint8)
    p0 = net.predict_proba(x)[:, 1].double()
    net.logit_bias = -2.0
    save_model(tmp_path / "m", net, {})
    net2, meta = load_model(tmp_path / "m")
    assert meta["logit_bias"] == -2.0 and net2.logit_bias == -2.0
    p1 = net2.predict_proba(x)[:, 1].double()
    odds = (p1 / (1 - p1)) / (p0 / (1 - p0))
    assert torch.allclose(odds, torch.full_like(odds, float(np.exp(-2.0))), rtol=1e-4)
