"""AlexNet-inspired defect classifier in plain torch (dissertation §5.2.3).

Layers, as in the dissertation: Conv1+ReLU, MaxPool+Conv2+ReLU, MaxPool+Conv3+ReLU, Conv4+ReLU,
Conv5+ReLU, MaxPool+Dropout+FC6+ReLU, Dropout+FC7+ReLU, FC8, softmax over
{non-defect, defect}. Channel counts and the input side are scaled down from AlexNet's 227 px so
the net trains on a CPU in minutes; ``width`` multiplies the channel counts.

The input is a greyscale uint8 batch (N, 1, S, S). Each image is standardised by its own mean and
standard deviation inside ``forward``, so overall brightness and contrast (lighting, exposure,
camera) do not matter; only the relative pattern does.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from roadsurf.core.errors import RoadsurfError

# (quarter turns, mirrored) of the test-time views, in order: 2 = identity + mirror, 4 = the four
# quarter turns, 8 = all eight symmetries of the square
DIHEDRAL_VIEWS: tuple[tuple[int, bool], ...] = (
    (0, False),
    (0, True),
    (2, False),
    (2, True),
    (1, False),
    (1, True),
    (3, False),
    (3, True),
)


class DefectNet(nn.Module):
    """Binary road-defect CNN. ``forward`` returns logits (N, 2); ``predict_proba`` softmax."""

    def __init__(
        self,
        input_size_px: int = 64,
        dropout: float = 0.5,
        width: int = 1,
        highpass_frac: float = 0.0,
    ) -> None:
        super().__init__()
        if input_size_px < 32:
            raise RoadsurfError(f"input_size_px must be >= 32, got {input_size_px}")
        if not 0.0 <= highpass_frac <= 1.0:
            raise RoadsurfError(f"highpass_frac must be in [0, 1], got {highpass_frac}")
        # subtract a Gaussian blur of σ = highpass_frac · side before standardising (0 = off):
        # removes smooth illumination (cloud edges, vignetting, undulation shading) that a
        # per-image standardisation blows up on plain, low-contrast road
        self.highpass_frac = float(highpass_frac)
        sigma = self.highpass_frac * input_size_px
        if sigma > 0:
            self.register_buffer(
                "_blur", _reflect_blur_matrix(input_size_px, sigma), persistent=False
            )
        else:
            self._blur = None
        c1, c2, c3, c4, c5 = (16 * width, 32 * width, 48 * width, 48 * width, 32 * width)
        fc = 128 * width
        self.input_size_px = int(input_size_px)
        self.conv1 = nn.Conv2d(1, c1, kernel_size=5, stride=2, padding=2)
        self.pool1 = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.conv2 = nn.Conv2d(c1, c2, kernel_size=5, padding=2)
        self.pool2 = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.conv3 = nn.Conv2d(c2, c3, kernel_size=3, padding=1)
        self.conv4 = nn.Conv2d(c3, c4, kernel_size=3, padding=1)
        self.conv5 = nn.Conv2d(c4, c5, kernel_size=3, padding=1)
        self.pool5 = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        side = self._side_after_features(self.input_size_px)
        self.drop6 = nn.Dropout(dropout)
        self.fc6 = nn.Linear(c5 * side * side, fc)
        self.drop7 = nn.Dropout(dropout)
        self.fc7 = nn.Linear(fc, fc)
        self.fc8 = nn.Linear(fc, 2)
        self.relu = nn.ReLU(inplace=True)
        # temperature T of the softmax (calibration, fitted on the validation split after
        # training); a plain attribute, not a weight, so it lives in the model metadata
        self.temperature = 1.0
        # added to the defect logit after the temperature: the prior correction from the class
        # balance the net was trained at (balanced sampling: 1:1) to the data's (calibration)
        self.logit_bias = 0.0
        # test-time augmentation: logits averaged over this many dihedral views (flips/quarter
        # turns) in ``logits``/``predict_proba``; 1 = the plain forward pass. Like the
        # temperature it is metadata, not a weight
        self.tta_views = 1
        self._init_weights()
        # NHWC conv weights (and inputs, in ``head``): oneDNN's fast CPU kernels want this
        # layout; on 2 cores the forward pass is ~2x and a training step ~1.4x faster than NCHW.
        # The values are the same; safetensors files store contiguous copies (modelfile)
        self.to(memory_format=torch.channels_last)

    def _init_weights(self) -> None:
        # He initialisation suits the ReLU stack; without batch norm the default init leaves the
        # loss flat at ln 2 for many epochs on small datasets
        for m in self.modules():
            if isinstance(m, (nn.Conv2d, nn.Linear)):
                nn.init.kaiming_normal_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)
        nn.init.normal_(self.fc8.weight, std=0.01)

    @staticmethod
    def _side_after_features(s: int) -> int:
        s = (s + 2 * 2 - 5) // 2 + 1  # conv1 stride 2
        for _ in range(3):  # pool1, pool2, pool5 (k3 s2 p1)
            s = (s + 2 - 3) // 2 + 1
        return s

    def blur(self, x: torch.Tensor) -> torch.Tensor:
        """Separable Gaussian blur of (N, 1, S, S) float images, reflected borders: B x Bᵀ
        with the (S, S) blur matrix B (two small matrix products; a 1-D convolution with a
        ~70-tap kernel was 20x slower on a CPU)."""
        b = self._blur
        return b @ x @ b.transpose(0, 1)

    @staticmethod
    def standardise(x: torch.Tensor) -> torch.Tensor:
        """uint8 grey levels (N, 1, S, S) -> float32, zero mean and unit std per image."""
        x = x.float() / 255.0
        mean = x.mean(dim=(1, 2, 3), keepdim=True)
        # the floor keeps a flat (featureless) image from blowing up sensor noise
        std = x.std(dim=(1, 2, 3), keepdim=True).clamp_min(0.01)
        return (x - mean) / std

    def prepare(self, x: torch.Tensor) -> torch.Tensor:
        """uint8 (N, 1, S, S) -> the standardised float input of the conv stack (high-pass
        first when ``highpass_frac`` > 0). Commutes with flips and quarter turns."""
        if x.ndim != 4 or x.shape[1] != 1 or x.shape[2:] != (self.input_size_px,) * 2:
            raise RoadsurfError(
                f"DefectNet expects (N, 1, {self.input_size_px}, {self.input_size_px}) input, "
                f"got {tuple(x.shape)}"
            )
        if self._blur is not None:
            x = x.float() / 255.0
            x = 255.0 * (x - self.blur(x)) + 128.0  # keeps the uint8-like scale standardise expects
        return self.standardise(x)

    def head(self, x: torch.Tensor) -> torch.Tensor:
        """Prepared input (N, 1, S, S) float -> logits (N, 2)."""
        r = self.relu
        x = r(self.conv1(x.contiguous(memory_format=torch.channels_last)))
        x = r(self.conv2(self.pool1(x)))
        x = r(self.conv3(self.pool2(x)))
        x = r(self.conv4(x))
        x = r(self.conv5(x))
        x = torch.flatten(self.pool5(x), 1)
        x = r(self.fc6(self.drop6(x)))
        x = r(self.fc7(self.drop7(x)))
        return self.fc8(x)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.prepare(x))

    def logits(self, x: torch.Tensor) -> torch.Tensor:
        """Logits (N, 2) averaged over the first ``tta_views`` dihedral views of each image
        (``DIHEDRAL_VIEWS``). A road seen from above has no 'up', so every view is a valid
        image of the same road; averaging removes the net's orientation-dependent noise. The
        input is prepared once: the isotropic blur and the per-image standardisation commute
        with the views."""
        views = int(self.tta_views)
        if views <= 1:
            return self.forward(x)
        x = self.prepare(x)
        out = torch.zeros((x.shape[0], 2), dtype=torch.float32, device=x.device)
        for k, flip in DIHEDRAL_VIEWS[:views]:
            xv = torch.rot90(x, k, dims=(2, 3))
            out += self.head(torch.flip(xv, dims=(3,)) if flip else xv)
        return out / views

    @torch.no_grad()
    def predict_proba(self, x: torch.Tensor) -> torch.Tensor:
        """Calibrated softmax probabilities (N, 2), softmax(logits / T + (0, b)), class order
        (non-defect, defect); logits with test-time augmentation (``tta_views``)."""
        z = self.logits(x) / float(self.temperature)
        z[:, 1] += float(self.logit_bias)
        return torch.softmax(z, dim=1)


def _reflect_blur_matrix(side: int, sigma: float) -> torch.Tensor:
    """(side, side) float32 matrix B with (B v)[i] = Σ_k g[k] v[reflect(i + k)]: a normalised
    Gaussian of σ ``sigma`` (px), radius min(⌈3σ⌉, side - 1), borders reflected without
    repeating the edge pixel (numpy/torch "reflect")."""
    r = min(int(math.ceil(3 * sigma)), side - 1)
    k = np.arange(-r, r + 1)
    g = np.exp(-0.5 * (k / sigma) ** 2)
    g /= g.sum()
    j = np.arange(side)[:, None] + k[None, :]  # (side, 2r + 1) source index of each tap
    j = np.where(j < 0, -j, j)
    j = np.where(j > side - 1, 2 * (side - 1) - j, j)  # r < side: one reflection suffices
    b = np.zeros((side, side))
    np.add.at(b, (np.repeat(np.arange(side), len(k)), j.ravel()), np.tile(g, side))
    return torch.from_numpy(b.astype(np.float32))


def pick_device(name: str = "auto") -> torch.device:
    """ "auto": CUDA when present, else CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise RoadsurfError("device 'cuda' requested but no CUDA device is available; use 'auto'")
    return torch.device(name)
