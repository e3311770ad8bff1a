"""Configuration of the CNN classifier, its self-labelling and the CNN/3D fusion rule."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

CLASS_NAMES: tuple[str, str] = ("non-defect", "defect")  # softmax output order


@dataclass(frozen=True)
class ClassifierConfig:
    """CNN classifier (dissertation §5.2-5.3). Lengths in metres, images in pixels."""

    # --- network (§5.2.3) ---
    input_size_px: int = 96  # square network input side (px); the dissertation used 227
    dropout: float = 0.5  # dropout probability before FC6 and FC7
    width: int = 1  # channel multiplier of the conv layers (1 = small CPU-sized net)
    # high-pass input: subtract a Gaussian blur of σ = this × input side before the per-image
    # standardisation, removing smooth illumination; 0 = off (round 4; 1)
    highpass_frac: float = 0.12

    # --- training (§5.3) ---
    # initial learning rate (1). The dissertation's 5e-5 (a large GPU training) does not fit
    # minutes on a CPU: on the sample data, 30 epochs at 5e-5 end at validation accuracy 0.5
    # and no sure frame, at 2e-3 + cosine at 0.8 with 70 % of frames sure, all right
    learning_rate: float = 2e-3
    lr_decay: float = 0.95  # ×this per epoch for lr_schedule "exponential" (dissertation) (1)
    # "cosine" (default): linear warm-up over warmup_epochs, then cosine decay to 1 % of
    # learning_rate by the last epoch; "exponential": ×lr_decay per epoch (the dissertation's,
    # with learning_rate 5e-5)
    lr_schedule: str = "cosine"
    warmup_epochs: int = 2  # epochs of linear learning-rate warm-up ("cosine" only)
    # fit the softmax temperature T on the validation split after training (temperature
    # scaling), so that p >= fusion_threshold means about that share of correct decisions
    calibrate: bool = True
    # fit a logit bias b together with T (Platt scaling of the logit margin): balanced sampling
    # trains the net as if half the frames were defects; b moves p toward the validation
    # frames' class balance. False: temperature only (1)
    calibrate_bias: bool = True
    # expected share of defect frames on the drives to screen (π, 0-1): shifts the calibrated
    # log-odds by logit(π) - logit(π_data), π_data the self-labelled frames' defect share
    # (label-shift correction). None = π_data. Set it from survey statistics, not to save time:
    # a lower π makes "non-defect" decisions surer
    defect_prior: float | None = None
    batch_size: int = 64  # images per step (dissertation default)
    epochs: int = 30  # passes over the training split
    min_steps_per_epoch: int = 10  # at least this many batches per epoch, for tiny datasets (1)
    weight_decay: float = 1e-4  # L2 penalty of the optimiser (1)
    val_fraction: float = 0.2  # share held out for validation (the 80/20 split)
    # keep the weights of the best validation epoch (balanced accuracy, then loss); False keeps
    # the last epoch (more confident after the learning-rate decay, when validation is tiny)
    keep_best_epoch: bool = False
    balanced_sampling: bool = True  # sample classes equally per epoch (§5.3.2 imbalance)
    class_weighting: bool = False  # weight the loss by inverse class frequency instead
    seed: int = 0  # seeds the split, augmentation, initialisation and sampling
    device: str = "auto"  # "auto" (CUDA when present), "cpu" or "cuda"
    # torch CPU threads (0 = torch default). 1 by default: on a small shared CPU, more threads
    # than free cores slow torch down by up to 10x
    num_threads: int = 1
    # torch CPU threads while screening a drive (count, capped at the usable cores; 0 = use
    # num_threads): nothing else runs then, and the 200-frame long drive screens in 1.2 s
    # with 2 threads against 2.1 s with 1 on the 2-core bench machine
    screen_num_threads: int = 2
    # screen in a worker process (classifier.screen_job) so torch's import (1.3-2 s)
    # and the screening overlap the pipeline's own start-up on another core; False screens in
    # the pipeline's process (same probabilities)
    screen_in_subprocess: bool = True

    # --- self-labelling (eq. 5.8-5.9) ---
    defect_depth_m: float = 0.010  # Z^d: a point deeper than this below the road is a defect (m)
    # α = Z^d / h on height-normalised points X̄ = X / h; when set it overrides defect_depth_m,
    # so the threshold scales with each drive's camera height h (1)
    defect_alpha: float | None = None
    min_defect_area_cm2: float = 20.0  # minimum footprint deeper than Z^d for a defect frame (cm²)
    min_defect_points: int = 5  # minimum reconstructed points deeper than Z^d (1)
    store_size_px: int = 96  # side of the square PNG written to the dataset (px)
    # frames whose 3D evidence is ambiguous (a few deep points, below the extent) are left out of
    # the dataset rather than given a noisy label
    drop_ambiguous: bool = True
    # defect types the CNN is not taught: a frame whose physics defects (RUN/defects.geojson,
    # ``frames``) are all of these types is left out of the dataset (rule ``left_to_3d(...)``).
    # A rut is a few-mm trough that shows in a single image only under low sun; taught as
    # "defect", it teaches the CNN that plain-looking road may be defective, so it is unsure
    # about plain road and every unsure frame costs a pair. Ruts are long: the sparse 3D audit
    # meets them and the growth follows them (classifier bench, session 10: validation accuracy
    # 0.907 -> 0.974, unsure frames on the long drive 31 -> 2). () teaches every type
    cnn_skip_types: tuple[str, ...] = ("rut",)

    # --- augmentation of defect images (§5.3.2) ---
    augment: bool = True  # write augmented copies of the defect images
    augment_max_copies: int = 12  # at most this many augmented copies per defect image (1)
    augment_target_ratio: float = 1.0  # aim for defect:non-defect this close to 1:1 (1)
    rescale_range: tuple[float, float] = (0.8, 1.25)  # zoom factor range for rescaling (1)
    # on-line photometric augmentation of every training batch (exposure, gamma, contrast, blur,
    # sensor noise, coarse grey levels, illumination ramps), so unseen cameras and lighting are in
    # distribution; scales every range, 0 = off (1)
    photometric_strength: float = 1.0

    # --- screening and fusion (Fig. 5.6) ---
    fusion_threshold: float = 0.95  # the CNN decision stands when max(p) >= this (1)
    # a confident CNN "defect" must be confirmed by the 3D result, which runs anyway to measure
    # the defect (a frame flagged with nothing to measure helps no one); False is the
    # dissertation's rule (the confident CNN decision stands). Session 5: fixed the one fused
    # false alarm on an unseen drive, changed no frame on 7 others (docs/classifier.md) (1)
    confirm_defect_with_3d: bool = True
    # neighbours (frames) of an unsure/defect frame that are reconstructed too and decided by 3D
    # (temporal-context extension; 0 = the dissertation's per-frame rule)
    context_frames: int = 1
    # sparse 3D audit: one pair every this far along the drive is reconstructed whatever the
    # CNN says, so long defects a single image cannot show (a shallow rut under diffuse light)
    # are met. Distance from OBD speed, else GPS (roadsurf.io.drive.along_track_m), so the cost
    # does not grow with the frame rate; 4 m = 10 frames at 15 fps and 6 m/s (m).
    # 0 = count frames instead (audit_every_frames)
    audit_every_m: float = 4.0
    # the audit spacing in frames when audit_every_m is 0 or the drive has no OBD and no GPS;
    # audit_every_m: 0 with audit_every_frames: 0 = no audit, the dissertation's rule (frames)
    audit_every_frames: int = 10
    # probe each audit pair first (reconstruction.probe: tracked corners, ~60 ms against ~450 ms
    # of CPU for a full pair at 640x480) and reconstruct it fully only when the probe fails or
    # shows some depth: more than audit_probe_max_deep_points points deeper than
    # audit_probe_depth_frac x Z^d. Clear probes keep the CNN's decision, as clear audited frames
    # always did. False = every audit pair is a full pair (1)
    audit_probe: bool = True
    audit_probe_depth_frac: float = 0.5  # the probe's depth threshold as a share of Z^d (1)
    audit_probe_max_deep_points: int = 1  # more probe points below it -> full pair (count)
    # a frame whose 3D shows a defect gets its neighbours reconstructed, repeatedly, so a defect
    # is followed along the drive to its ends (1)
    grow_along_defects: bool = True
    screen_batch_size: int = 64  # images per inference batch (1)
    # test-time augmentation: CNN logits averaged over this many flips/quarter turns of each
    # frame (1, 2, 4 or 8; 1 = off). Set at training, stored in the model file, used by
    # calibration and screening alike (1)
    tta_views: int = 8

    # valid values (interval notation; see roadsurf.core.config)
    RANGES: ClassVar[dict[str, str]] = {
        "input_size_px": "[16, inf); three stride-2 poolings need some pixels",
        "dropout": "[0, 1)",
        "width": "[1, inf)",
        "highpass_frac": "[0, 1]",
        "learning_rate": "(0, inf)",
        "lr_decay": "(0, 1]",
        "lr_schedule": "{cosine, exponential}",
        "warmup_epochs": "[0, inf)",
        "defect_prior": "(0, 1); a prior of 0 or 1 has infinite log-odds",
        "batch_size": "[1, inf)",
        "epochs": "[1, inf)",
        "min_steps_per_epoch": "[0, inf)",
        "weight_decay": "[0, inf)",
        "val_fraction": "[0, 1)",
        "seed": "[0, 4294967295]; numpy seeds are 32-bit",
        "device": "{auto, cpu, cuda}",
        "num_threads": "[0, inf); 0 = torch default",
        "screen_num_threads": "[0, inf); 0 = num_threads",
        "defect_depth_m": "(0, 1]; a Z^d above 1 m is a unit mistake (mm typed as m?)",
        "defect_alpha": "(0, 1]; α = Z^d / h",
        "min_defect_area_cm2": "[0, inf)",
        "min_defect_points": "[0, inf)",
        "store_size_px": "[16, inf)",
        "cnn_skip_types": "{pothole, crack, rut}",
        "augment_max_copies": "[0, inf)",
        "augment_target_ratio": "(0, inf)",
        "rescale_range": "(0, inf); zoom factors",
        "photometric_strength": "[0, inf); 0 = off",
        "fusion_threshold": "[0.5, 1]; max(p) of two classes is at least 0.5",
        "context_frames": "[0, inf)",
        "audit_every_m": "[0, inf); 0 = count frames",
        "audit_every_frames": "[0, inf); 0 (with audit_every_m 0) = no audit",
        "audit_probe_depth_frac": "[0, 1]",
        "audit_probe_max_deep_points": "[0, inf)",
        "screen_batch_size": "[1, inf)",
        "tta_views": "{1, 2, 4, 8}; flips and quarter turns",
    }

    def depth_threshold_m(self, camera_height_m: float) -> float:
        """Z^d for a camera at height h (m): α·h when α is set, else ``defect_depth_m``."""
        if self.defect_alpha is not None:
            return float(self.defect_alpha) * float(camera_height_m)
        return float(self.defect_depth_m)
