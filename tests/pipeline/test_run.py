"""PipelineConfig: YAML with one section per stage, unknown keys rejected with the file named."""

from __future__ import annotations

from pathlib import Path

import pytest

from roadsurf.core.errors import ConfigError
from roadsurf.pipeline import PipelineConfig, load_pipeline_config


def test_yaml_sections_per_stage(tmp_path: Path) -> None:
    p = tmp_path / "cfg.yaml"
    p.write_text(
        "mapping:\n  gsd_m: 0.01\n  robust_loss: huber\nreconstruction:\n  method: classic\n"
    )
    cfg = load_pipeline_config(p)
    assert cfg.mapping.gsd_m == 0.01 and cfg.mapping.robust_loss == "huber"
    assert cfg.reconstruction.method == "classic"
    assert cfg.detection == PipelineConfig().detection


@pytest.mark.parametrize(
    "text",
    ["mapping:\n  gsd: 0.01\n", "mappin:\n  gsd_m: 0.01\n", "mapping:\n  robust_loss: l2\n"],
)
def test_bad_keys_and_values_are_rejected(tmp_path: Path, text: str) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match="bad.yaml"):
        load_pipeline_config(p)


def test_fused_run_warm_up_imports_name_real_modules_and_not_torch() -> None:
    """The modules a fused run imports while the CNN screens in its worker must exist (a
    renamed module would silently stop overlapping), and none may pull in torch: the pipeline
    process of a fused run never imports it."""
    import importlib.util
    import subprocess
    import sys

    from roadsurf.pipeline.run import _FUSED_RUN_IMPORTS

    for name in _FUSED_RUN_IMPORTS:
        assert importlib.util.find_spec(name) is not None, name
    code = (
        "import importlib, sys\n"
        "from roadsurf.pipeline.run import _FUSED_RUN_IMPORTS\n"
        "for n in _FUSED_RUN_IMPORTS: importlib.import_module(n)\n"
        "print('torch' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
