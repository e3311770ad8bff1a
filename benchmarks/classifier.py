"""Benchmark: the dissertation's Table 5.2 / Fig. 5.5 on simulator drives (the CNN classifier).

Trains the CNN on self-labelled simulator drives and tests on OTHER drives (other seeds,
texture, lighting, greyscale images, more lane markings and shadows). For every test drive it
scores, against the simulator's truth (truth/frame_labels.csv):

- image-only CNN (p_defect >= 0.5),
- fused CNN + 3D (``roadsurf run --classifier``, Fig. 5.6),
- 3D-only physics pipeline (``roadsurf run``),

with the average processing time per image of each, measured in the same session on the same
machine. A longer drive with few defect frames (~5%) gives the time ratio fused / physics.
False positives are broken down by the distractors (lane marking, shadow, oil stain) in view.
Every step caches in the work folder; timings are only taken from runs computed from scratch.
The drives are in ``classifier_drives``, the scoring in ``classifier_score``, the markdown in
``classifier_report``.

``python -m benchmarks.classifier [--work DIR] [--quick] [--config YAML] [--epochs N] [--lr X]``
(``make bench-classifier``).
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import os
import shutil
import time
from pathlib import Path
from typing import Any

from benchmarks.classifier_drives import (
    LONG_DRIVE,
    TEST_DRIVES,
    TRAIN_DRIVES,
    require_simulator,
    shortened,
    simulate_drive,
)
from benchmarks.classifier_report import to_markdown
from benchmarks.classifier_score import distractors_in_view, frame_labels, frame_sources, score
from roadsurf.core.atomic import read_json, write_json_atomic, write_text_atomic
from roadsurf.detection.classifier.config import ClassifierConfig
from roadsurf.detection.classifier.modelfile import model_weights_path
from roadsurf.detection.classifier.screen import screen_drive
from roadsurf.detection.classifier.train import train
from roadsurf.io.formats import read_csv
from roadsurf.io.runfolder import SCREENING_JSON, RunFolder
from roadsurf.pipeline.label import classifier_config, label_drives
from roadsurf.pipeline.run import run_drive

log = logging.getLogger(__name__)


def timed_run(
    drive: Path, run_dir: Path, classifier: Path | None = None, cfg_path: Path | None = None
) -> dict[str, Any]:
    """Run the pipeline from scratch (timed) unless a finished, timed run is cached."""
    tpath = run_dir / "bench_timing.json"
    model_id = file_digest(model_weights_path(classifier)) if classifier is not None else None
    if tpath.is_file() and RunFolder(run_dir).frame_labels.is_file():
        rec = read_json(tpath)
        if rec.get("model") == model_id:  # a fused run is redone when the model changed
            return rec
    if run_dir.exists():
        shutil.rmtree(run_dir)  # a timing must come from a clean run, not a resumed one
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    report = run_drive(drive, run_dir, classifier=classifier, config_path=cfg_path)
    wall = time.perf_counter() - t0
    # process CPU time, all threads (torch, pycolmap, numpy); children are not spawned
    cpu = time.process_time() - c0
    load1 = os.getloadavg()[0]
    n = int(report.get("counts", {}).get("frames", 0)) or 1
    rec = {
        "wall_s": round(wall, 3),
        "frames": n,
        "s_per_frame": wall / n,
        "cpu_s": round(cpu, 3),
        "cpu_s_per_frame": cpu / n,
        "model": model_id,
        "load_avg_1min": [round(load0, 2), round(load1, 2)],
        "stage_timings_s": report.get("timings_s", {}),
        "pairs_reconstructed": report.get("counts", {}).get("pairs", 0),
    }
    write_json_atomic(tpath, rec)
    return rec


def file_digest(path: Path) -> str:
    """First 16 hex digits of the file's SHA-256 (which model a fused run used)."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]


def bench_classifier(
    work: str | Path,
    cfg: ClassifierConfig | None = None,
    *,
    quick: bool = False,
    config_path: str | Path | None = None,
) -> dict[str, Any]:
    """Run the whole benchmark in ``work``; returns the results (also work/results.json/.md)."""
    cfg = cfg or ClassifierConfig()
    work = Path(work)
    work.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    train_specs = [(shortened(s, 30) if quick else s) for s in TRAIN_DRIVES]
    test_specs = [(shortened(s, 30) if quick else s) for s in TEST_DRIVES]
    long_spec = shortened(LONG_DRIVE, 80) if quick else LONG_DRIVE
    cfg_path = Path(config_path) if config_path else None

    log.info("bench classifier: simulating %d drives", len(train_specs) + len(test_specs) + 1)
    train_drives = [simulate_drive(s, work) for s in train_specs]
    test_drives = [simulate_drive(s, work) for s in test_specs + [long_spec]]

    log.info("bench classifier: physics pipeline on the training drives (self-labelling)")
    train_runs = []
    for s, d in zip(train_specs, train_drives, strict=True):
        run_dir = work / "runs" / s.name / "physics"
        timed_run(d, run_dir, cfg_path=cfg_path)
        train_runs.append(run_dir)
    ds_dir = work / "dataset"
    if ds_dir.exists():
        shutil.rmtree(ds_dir)
    balance = label_drives(train_drives, ds_dir, cfg, runs=train_runs)
    # how good are the self-labels? (the CNN can be no better than its teacher)
    self_labels = {}
    rows = [r for r in read_csv(ds_dir / "labels.csv") if not r.get("augmentation")]
    for s, d in zip(train_specs, train_drives, strict=True):
        truth = frame_labels(d / "truth" / "frame_labels.csv")
        pred = {r["frame"]: int(r["label"]) for r in rows if Path(r["drive"]) == d}
        self_labels[s.name] = score(pred, truth, {})
        self_labels[s.name]["frames_labelled"] = len(pred)
        self_labels[s.name]["frames_total"] = len(truth)

    model_dir = work / "model"
    meta = train(ds_dir, model_dir, cfg, resume=False)

    results: dict[str, Any] = {}
    for s, d in zip(test_specs + [long_spec], test_drives, strict=True):
        truth = frame_labels(d / "truth" / "frame_labels.csv")
        dis = distractors_in_view(d)
        phys = timed_run(d, work / "runs" / s.name / "physics", cfg_path=cfg_path)
        t0, c0 = time.perf_counter(), time.process_time()
        probs = screen_drive(model_dir, d, cfg, progress=False)
        t_cnn, c_cnn = time.perf_counter() - t0, time.process_time() - c0
        fused = timed_run(d, work / "runs" / s.name / "fused", model_dir, cfg_path)
        phys_run = RunFolder(work / "runs" / s.name / "physics")
        fused_run = RunFolder(work / "runs" / s.name / "fused")
        phys_pred = frame_labels(phys_run.frame_labels)
        fused_pred = frame_labels(fused_run.frame_labels)
        sources = frame_sources(fused_run.frame_labels)
        cnn_pred = {f: int(p >= 0.5) for f, p in probs.items()}
        thr = cfg.fusion_threshold
        clear = [f for f in truth if not truth[f] and f in probs]
        confidence = {
            # the speed lever: clear frames the CNN is sure about need no 3D
            "clear_frames_confident": sum(probs[f] <= 1 - thr for f in clear),
            "clear_frames": len(clear),
            # the accuracy risk: frames the CNN is sure about and wrong
            "confident_wrong": sorted(
                f
                for f, p in probs.items()
                if f in truth and max(p, 1 - p) >= thr and int(p >= 0.5) != truth[f]
            ),
        }
        # variant: where the CNN is confident "defect" the 3D pipeline ran anyway; let it decide
        # (confirm_defect_with_3d). Its 3D label is taken from the 3D-only run of the same drive.
        confirm_pred = {
            f: (phys_pred.get(f, v) if sources.get(f) == "fused" else v)
            for f, v in fused_pred.items()
        }
        # ablation: the same run with the frames only the audit/growth sent to 3D decided by
        # the CNN again (the dissertation's rule plus context; its time is not measured)
        scr_path = fused_run.path(SCREENING_JSON)
        scr = read_json(scr_path) if scr_path.is_file() else {}
        reason = {f["filename"]: f.get("3d_reason") for f in scr.get("frames", [])}
        plain_pred = {
            f: (
                cnn_pred[f]
                if reason.get(f) in ("audit", "grown") and f in probs and probs[f] <= 1 - thr
                else v
            )
            for f, v in fused_pred.items()
        }
        n = len(truth)
        results[s.name] = {
            "spec": dataclasses.asdict(s),
            "frames": n,
            "defect_frames": int(sum(truth.values())),
            "frames_with_distractor": sum(1 for v in dis.values() if v),
            "cnn": {
                **score(cnn_pred, truth, dis),
                "s_per_frame": t_cnn / max(1, len(probs)),
                "cpu_s_per_frame": c_cnn / max(1, len(probs)),
            },
            "fused": {
                **score(fused_pred, truth, dis),
                "s_per_frame": fused["s_per_frame"],
                "cpu_s_per_frame": fused.get("cpu_s_per_frame", float("nan")),
            },
            "fused_3d_confirms": {
                **score(confirm_pred, truth, dis),
                "s_per_frame": fused["s_per_frame"],
                "cpu_s_per_frame": fused.get("cpu_s_per_frame", float("nan")),
            },
            "fused_no_audit": {
                **score(plain_pred, truth, dis),
                "s_per_frame": float("nan"),
                "cpu_s_per_frame": float("nan"),
            },
            "screening": {
                k: scr.get(k) for k in ("frames_with_3d_by_reason", "rounds", "pairs_reconstructed")
            },
            "physics": {
                **score(phys_pred, truth, dis),
                "s_per_frame": phys["s_per_frame"],
                "cpu_s_per_frame": phys.get("cpu_s_per_frame", float("nan")),
            },
            "fused_sources": {k: list(sources.values()).count(k) for k in ("cnn", "3d", "fused")},
            "cnn_confidence": confidence,
            "pairs_reconstructed": {
                "physics": phys["pairs_reconstructed"],
                "fused": fused["pairs_reconstructed"],
            },
            "stage_timings_s": {
                "physics": phys.get("stage_timings_s", {}),
                "fused": fused.get("stage_timings_s", {}),
            },
            "load_avg_1min": {
                "physics": phys.get("load_avg_1min"),
                "fused": fused.get("load_avg_1min"),
            },
            "time_ratio_fused_over_physics": fused["s_per_frame"] / phys["s_per_frame"],
            "cpu_time_ratio_fused_over_physics": fused["cpu_s_per_frame"] / phys["cpu_s_per_frame"],
        }
    out = {
        "machine_note": "see docs/benchmarks.md",
        "quick": quick,
        "config": dataclasses.asdict(cfg),
        "balance": balance,
        "self_labels_vs_truth": self_labels,
        "model": {
            "best_epoch": meta.get("best_epoch"),
            "val_metrics": meta.get("metrics"),
            "train_time_s": meta.get("train_time_s"),
            "train_balance": meta.get("training_data", {}).get("train_balance"),
            "calibration": meta.get("calibration"),
        },
        "tests": results,
        "total_s": round(time.perf_counter() - t_all, 1),
    }
    write_json_atomic(work / "results.json", out)
    write_text_atomic(work / "results.md", to_markdown(out))
    return out


def run_benchmark(
    work: Path,
    *,
    quick: bool = False,
    config_path: Path | None = None,
    epochs: int | None = None,
    learning_rate: float | None = None,
) -> dict[str, Any]:
    """The benchmark with the config file's ``classifier:`` section plus overrides (what
    ``main`` runs)."""
    require_simulator()
    cfg = classifier_config(config_path, epochs=epochs, learning_rate=learning_rate)
    return bench_classifier(work, cfg, quick=quick, config_path=config_path)


def main(argv: list[str] | None = None) -> int:
    """``python -m benchmarks.classifier`` (``make bench-classifier ARGS="..."``)."""
    import argparse

    from benchmarks._result import write_result

    ap = argparse.ArgumentParser(
        description="CNN vs fused CNN+3D vs 3D-only on unseen simulator drives "
        "(Table 5.2, Fig. 5.5)."
    )
    ap.add_argument(
        "--work",
        type=Path,
        default=Path("out/bench_classifier"),
        help="work folder (drives, runs, dataset, model, results)",
    )
    ap.add_argument("--quick", action="store_true", help="shorter drives (smoke run)")
    ap.add_argument(
        "--config", type=Path, default=None, help="YAML config for the pipeline and the classifier"
    )
    ap.add_argument("--epochs", type=int, default=None, help="training epochs")
    ap.add_argument("--lr", type=float, default=None, help="learning rate")
    ap.add_argument("--json", type=Path, default=None, help="result file (default results/)")
    a = ap.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        datefmt="%H:%M:%S",
    )
    res = run_benchmark(
        a.work, quick=a.quick, config_path=a.config, epochs=a.epochs, learning_rate=a.lr
    )
    print((a.work / "results.md").read_text(encoding="utf-8"))
    print(f"Total {res['total_s']} s; details in {a.work}/results.json")
    write_result(a.json, "classifier", res)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
