from dataclasses import dataclass, field

import pytest

from roadsurf.core.config import from_dict, load_yaml_config
from roadsurf.core.errors import ConfigError


@dataclass(frozen=True)
class Inner:
    lam: float = 2.0  # λ
    kind: str = "sift"


@dataclass(frozen=True)
class Outer:
    inner: Inner = field(default_factory=Inner)
    n: int = 3
    flags: tuple[int, ...] = (1, 2)
    maybe: float | None = None


def test_defaults_and_nested():
    cfg = from_dict(Outer, {"inner": {"lam": 1.5}, "n": 4, "flags": [3, 4, 5]})
    assert cfg.inner.lam == 1.5 and cfg.inner.kind == "sift"
    assert cfg.n == 4 and cfg.flags == (3, 4, 5)


def test_unknown_key_rejected_with_location():
    with pytest.raises(ConfigError, match=r"cfg.yaml: inner: unknown key\(s\) \['lamda'\]"):
        from_dict(Outer, {"inner": {"lamda": 1.0}}, "cfg.yaml")
    with pytest.raises(ConfigError, match="did you mean 'lam'"):
        from_dict(Outer, {"inner": {"lamda": 1.0}}, "cfg.yaml")


def test_ill_typed_value_rejected():
    with pytest.raises(ConfigError, match="expected an integer"):
        from_dict(Outer, {"n": "three"})
    with pytest.raises(ConfigError, match="expected a number"):
        from_dict(Outer, {"inner": {"lam": True}})


def test_optional_accepts_none_and_number():
    assert from_dict(Outer, {"maybe": None}).maybe is None
    assert from_dict(Outer, {"maybe": 2}).maybe == 2.0


def test_yaml_syntax_error_names_file_and_line(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text("n: 3\ninner: {lam: 1\n")
    with pytest.raises(ConfigError, match=r"bad.yaml line \d+"):
        load_yaml_config(Outer, p)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_yaml_config(Outer, tmp_path / "none.yaml")


# ---------------------------------------------------------------- declared ranges (issue 31)
import dataclasses  # noqa: E402
import re  # noqa: E402
import types  # noqa: E402
import typing  # noqa: E402
from typing import ClassVar  # noqa: E402

from roadsurf.core.config import check_ranges, parse_range, ranges_of  # noqa: E402
from roadsurf.pipeline.run import PipelineConfig, load_pipeline_config  # noqa: E402
from roadsurf.pipeline.sfm.config import SfmBaselineConfig  # noqa: E402
from roadsurf.simulation.config import SimConfig  # noqa: E402
from roadsurf.viewer.config import ViewerConfig  # noqa: E402

ROOTS = (PipelineConfig, SimConfig, ViewerConfig, SfmBaselineConfig)


def _config_classes() -> list[type]:
    seen: list[type] = []
    todo = list(ROOTS)
    while todo:
        cls = todo.pop()
        if cls in seen:
            continue
        seen.append(cls)
        for tp in typing.get_type_hints(cls).values():
            if dataclasses.is_dataclass(tp):
                todo.append(tp)
    return seen


def _is_numeric(tp) -> bool:
    if tp in (int, float):
        return True
    if typing.get_origin(tp) in (typing.Union, types.UnionType, tuple):
        args = [a for a in typing.get_args(tp) if a is not type(None) and a is not Ellipsis]
        return bool(args) and all(_is_numeric(a) for a in args)
    return False


def _write(tmp_path, text: str):
    p = tmp_path / "cfg.yaml"
    p.write_text(text)
    return p


def test_every_numeric_field_declares_a_range():
    classes = _config_classes()
    assert len(classes) >= 15  # the pipeline's 12, simulator, viewer, SfM baseline
    missing, stray, n = [], [], 0
    for cls in classes:
        hints = typing.get_type_hints(cls)
        names = {f.name for f in dataclasses.fields(cls)}
        ranges = ranges_of(cls)  # parses every spec: a malformed one raises here
        stray += [f"{cls.__name__}.{k}" for k in ranges if k not in names]
        for f in dataclasses.fields(cls):
            if _is_numeric(hints[f.name]):
                n += 1
                if f.name not in ranges:
                    missing.append(f"{cls.__name__}.{f.name}")
    assert not missing, f"numeric fields without a declared range: {missing}"
    assert not stray, f"ranges of no field (typo?): {stray}"
    assert n > 250


def test_every_default_is_inside_its_own_range():
    for cls in _config_classes():
        check_ranges(cls(), f"defaults of {cls.__name__}")


def test_ranges_are_class_variables_not_settings():
    assert "RANGES" not in {f.name for f in dataclasses.fields(PipelineConfig().mapping)}
    assert (
        typing.get_type_hints(type(PipelineConfig().mapping), include_extras=True)["RANGES"]
        == ClassVar[dict[str, str]]
    )
    with pytest.raises(ConfigError, match="unknown key"):
        from_dict(PipelineConfig, {"mapping": {"RANGES": {}}})


@pytest.mark.parametrize(
    ("text", "key", "value", "bound"),
    [
        ("mapping:\n  gsd_m: 0\n", "mapping.gsd_m", "0", "> 0 and <= 1 m"),
        ("mapping:\n  gsd_m: 5\n", "mapping.gsd_m", "5", "> 0 and <= 1 m"),
        ("mapping:\n  tile_px: 0\n", "mapping.tile_px", "0", ">= 16 and <= 65536 px"),
        ("mapping:\n  preview_max_px: 0\n", "mapping.preview_max_px", "0", ">= 16 px"),
        ("mapping:\n  voxel_m: -0.004\n", "mapping.voxel_m", "-0.004", ">= 0 and <= 1 m"),
        (
            "detection:\n  plane:\n    depth_threshold_m: -0.01\n",
            "detection.plane.depth_threshold_m",
            "-0.01",
            ">= 0 and <= 1 m",
        ),
        (
            "detection:\n  map:\n    depth_threshold_m: -1\n",
            "detection.map.depth_threshold_m",
            "-1",
            ">= 0 and <= 1 m",
        ),
        ("classifier:\n  dropout: 1.5\n", "classifier.dropout", "1.5", ">= 0 and < 1"),
        ("classifier:\n  tta_views: 3\n", "classifier.tta_views", "3", "one of 1, 2, 4, 8"),
        ("classifier:\n  lr_schedule: linear\n", "classifier.lr_schedule", "'linear'", "one of"),
        (
            "reconstruction:\n  features:\n    ratio: .nan\n",
            "reconstruction.features.ratio",
            "nan",
            "> 0",
        ),
        ("mapping:\n  gps_sigma_m: .inf\n", "mapping.gps_sigma_m", "inf", "> 0"),
    ],
)
def test_out_of_range_value_names_file_key_value_and_range(tmp_path, text, key, value, bound):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_pipeline_config(p)
    msg = str(err.value)
    assert "\n" not in msg
    assert msg.startswith(f"{p} line ")  # the file and the line of the key
    assert f"{key}: {value} is out of range" in msg
    assert bound in msg


def test_range_message_gives_the_reason_and_an_example(tmp_path):
    p = _write(tmp_path, "mapping:\n  overwrite: false\n  gsd_m: 0\n")
    with pytest.raises(ConfigError) as err:
        load_pipeline_config(p)
    assert str(err.value) == (
        f"{p} line 3: mapping.gsd_m: 0 is out of range: must be > 0 and <= 1 m (a raster cell "
        "above 1 m is a unit mistake (cm typed as m?)); e.g. 0.005"
    )


def test_range_applies_to_each_value_of_a_tuple():
    with pytest.raises(ConfigError, match=r"sim: pothole_depth_m: \[0.02, -0.01\] is out of range"):
        from_dict(SimConfig, {"pothole_depth_m": [0.02, -0.01]}, "sim")
    with pytest.raises(ConfigError, match="cnn_skip_types.*one of pothole, crack, rut"):
        from_dict(PipelineConfig, {"classifier": {"cnn_skip_types": ["pothole", "rutt"]}})
    ok = from_dict(SimConfig, {"pothole_depth_m": [0.02, 0.05]})
    assert ok.pothole_depth_m == (0.02, 0.05)


def test_optional_fields_accept_null_and_check_numbers():
    assert (
        from_dict(PipelineConfig, {"classifier": {"defect_prior": None}}).classifier.defect_prior
        is None
    )
    with pytest.raises(ConfigError, match="defect_prior: 1 is out of range"):
        from_dict(PipelineConfig, {"classifier": {"defect_prior": 1}})


def test_in_range_edges_load():
    cfg = from_dict(
        PipelineConfig,
        {"mapping": {"gsd_m": 1, "voxel_m": 0, "tile_px": 16}, "classifier": {"tta_views": 1}},
    )
    assert cfg.mapping.gsd_m == 1.0 and cfg.mapping.voxel_m == 0.0
    assert cfg.classifier.tta_views == 1


def test_parse_range_forms():
    r = parse_range("(0, 1]; why")
    assert (r.lo, r.hi, r.lo_open, r.hi_open, r.note) == (0, 1, True, False, "why")
    assert parse_range("[0, inf)").hi is None
    assert parse_range("(-inf, inf)").lo is None
    assert parse_range("{1, 2, x}").choices == (1, 2, "x")
    assert parse_range("[1e-9, 2.5]").contains(1e-9)
    for bad in ("0..1", "(1, 0]", "{}", "[a, 1]"):
        with pytest.raises(ValueError):
            parse_range(bad)


# ---------------------------------------------------------------- robust loading (issue 31)
@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ("~: 1\n", r"key None is not a setting name"),
        ("mapping:\n  ~: 1\n", r"line 1: mapping: key None is not a setting name"),
        ("3: 1\n", r"key 3 is not a setting name"),
        ("mapping: [1, 2]\n", r"line 1: mapping: expected a mapping of keys to values, got list"),
        ("mapping: 3\n", r"mapping: expected a mapping"),
        ("- 1\n- 2\n", r"expected a mapping of keys to values, got list"),
        ("mapping:\n  gsd_m: [1\n", r"line \d+: not valid YAML"),
        ("a: 1\n---\nb: 2\n", r"line 2: not valid YAML"),
        ("mapping: {gsd_m: 2024-13-45}\n", r"not valid YAML"),
        ("mapping:\n  gsd_m: 1.0e+999\n", r"mapping.gsd_m: inf is out of range"),
        ("mapping:\n  max_raster_px: 1e3\n", r"mapping.max_raster_px: expected an integer"),
        ("? [a]\n: 1\n", r"not valid YAML"),
    ],
)
def test_malformed_config_gives_one_line_error(tmp_path, text, pattern):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_pipeline_config(p)
    msg = str(err.value)
    assert "\n" not in msg and msg.startswith(str(p))
    assert re.search(pattern, msg), msg


def test_non_utf8_bytes_name_file_and_line(tmp_path):
    p = tmp_path / "cfg.yaml"
    p.write_bytes(b"mapping:\n  gsd_m: 0.01  # \xe9\n")
    with pytest.raises(ConfigError, match=r"cfg.yaml line 2: byte 0xe9 at offset \d+ is not UTF-8"):
        load_pipeline_config(p)


def test_yaml_syntax_error_is_one_line(tmp_path):
    p = _write(tmp_path, "mapping:\n  gsd_m: 0.01\n bad indent: [\n")
    with pytest.raises(ConfigError) as err:
        load_pipeline_config(p)
    assert "\n" not in str(err.value) and re.match(
        rf"{re.escape(str(p))} line \d+: ", str(err.value)
    )


def test_order_pairs_name_real_fields():
    """Every ORDER pair names two fields of its class (a typo would silently check nothing)."""
    n = 0
    for cls in _config_classes():
        names = {f.name for f in dataclasses.fields(cls)}
        for a, b in getattr(cls, "ORDER", ()):
            assert a in names and b in names, f"{cls.__name__}: ORDER ({a}, {b})"
            n += 1
    assert n >= 8


@pytest.mark.parametrize(
    ("text", "key", "other"),
    [
        (
            "detection:\n  severity:\n    depth_low_m: 0.06\n",
            "severity.depth_low_m",
            "depth_high_m",
        ),
        (
            "detection:\n  severity:\n    depth_high_m: 0.02\n",
            "severity.depth_high_m",
            "depth_low_m",
        ),
        ("detection:\n  rut:\n    min_width_m: 2.0\n", "rut.min_width_m", "max_width_m"),
    ],
)
def test_inverted_interval_names_both_keys_and_the_line(tmp_path, text, key, other):
    p = _write(tmp_path, text)
    with pytest.raises(ConfigError) as e:
        load_pipeline_config(p)
    msg = str(e.value)
    assert str(p) in msg and key in msg and other in msg and "\n" not in msg, msg
    assert ":3" in msg or "line 3" in msg, msg


def test_order_is_checked_on_built_objects_too():
    import dataclasses as dc

    from roadsurf.detection.config import SeverityConfig

    with pytest.raises(ConfigError, match="depth_low_m"):
        check_ranges(dc.replace(SeverityConfig(), depth_low_m=0.1))


def test_a_section_override_keeps_the_enclosing_config_default() -> None:
    # MappingConfig's dense section defaults to smooth_px 1.5 (DenseHeightConfig's own is 0):
    # overriding another key of that section must not reset it to the class default
    from roadsurf.mapping.config import MappingConfig

    cfg = from_dict(MappingConfig, {"dense": {"hole_fill_m": 0.0}})
    assert cfg.dense.hole_fill_m == 0.0
    assert cfg.dense.smooth_px == MappingConfig().dense.smooth_px == 1.5


def test_an_unquoted_iso_time_for_a_string_field_is_its_text(tmp_path):
    """YAML reads `kind: 2026-06-15T14:00:00+10:00` as a timestamp; a str field takes the
    text back (`roadsurf simulate --set start_utc=...` failed with 'expected a string')."""
    p = tmp_path / "c.yaml"
    p.write_text("inner:\n  kind: 2026-06-15T14:00:00+10:00\n")
    assert load_yaml_config(Outer, p).inner.kind == "2026-06-15T14:00:00+10:00"
    p.write_text("inner:\n  kind: 2026-06-15\n")
    assert load_yaml_config(Outer, p).inner.kind == "2026-06-15"
    with pytest.raises(ConfigError, match="expected a string"):
        from_dict(Outer, {"inner": {"kind": 3}})
