"""Fuzzing of config loading (issue 31): random YAML documents, random bytes and random values
for the PipelineConfig either load or raise ConfigError, never anything else."""

from __future__ import annotations

import dataclasses
import tempfile
import typing
from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from roadsurf.core.config import check_ranges, from_dict, load_yaml_config
from roadsurf.core.errors import ConfigError
from roadsurf.pipeline.run import PipelineConfig

SETTINGS = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _section_keys() -> dict[str, list[str]]:
    """Stage section -> its field names (nested sections as dotted paths are not needed)."""
    out: dict[str, list[str]] = {}
    for name, tp in typing.get_type_hints(PipelineConfig).items():
        out[name] = [f.name for f in dataclasses.fields(tp)]
    return out


SECTIONS = _section_keys()
ALL_KEYS = sorted({k for keys in SECTIONS.values() for k in keys})

scalars = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(min_value=-(10**30), max_value=10**30),
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=12),
    st.sampled_from(["sift", "cosine", "auto", "flann", "map", "rigid", "1e3", "~", ""]),
)
values = st.recursive(
    scalars,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.dictionaries(
            st.one_of(st.sampled_from(ALL_KEYS), st.text(max_size=6)), inner, max_size=4
        ),
    ),
    max_leaves=8,
)
keys = st.one_of(
    st.sampled_from(ALL_KEYS), st.none(), st.integers(-3, 3), st.text(max_size=8), st.booleans()
)


@st.composite
def pipeline_dicts(draw) -> dict:
    """A mapping shaped like the pipeline config, with real and bogus keys and random values."""
    doc: dict = {}
    for section in draw(st.lists(st.sampled_from(sorted(SECTIONS)), max_size=4, unique=True)):
        body = draw(
            st.one_of(
                st.dictionaries(
                    st.one_of(st.sampled_from(SECTIONS[section]), keys), values, max_size=6
                ),
                values,
            )
        )
        doc[section] = body
    if draw(st.booleans()):
        doc[draw(keys)] = draw(values)
    return doc


def _load_file(data: bytes) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "cfg.yaml"
        p.write_bytes(data)
        try:
            cfg = load_yaml_config(PipelineConfig, p)
        except ConfigError as e:
            assert "\n" not in str(e), str(e)
            assert str(e).startswith(str(p)), str(e)
        else:
            check_ranges(cfg, "fuzz")  # what loads is in range


@SETTINGS
@given(pipeline_dicts())
def test_random_values_load_or_raise_config_error(doc):
    try:
        cfg = from_dict(PipelineConfig, doc, "fuzz")
    except ConfigError as e:
        assert "\n" not in str(e), str(e)
    else:
        check_ranges(cfg, "fuzz")


@SETTINGS
@given(pipeline_dicts())
def test_random_yaml_documents_load_or_raise_config_error(doc):
    try:
        text = yaml.safe_dump(doc, allow_unicode=False)
    except yaml.YAMLError:  # e.g. a key PyYAML cannot represent
        return
    _load_file(text.encode("utf-8"))


@SETTINGS
@given(st.binary(max_size=200))
def test_random_bytes_load_or_raise_config_error(data):
    _load_file(data)


@SETTINGS
@given(
    st.lists(
        st.sampled_from(
            [
                "mapping:",
                "\n",
                "  ",
                "gsd_m",
                ": ",
                "0",
                "-1",
                "[",
                "]",
                "{",
                "}",
                "~",
                "!!",
                "&a",
                "*a",
                "<<",
                "---",
                "? ",
                "#",
                "'",
                '"',
                "\t",
                ",",
                "- ",
                "2024-13-45",
                ".nan",
                "1.0e+999",
                "classifier",
                "tta_views",
                "\xe9",
                "\x00",
                "|",
                ">",
            ]
        ),
        max_size=30,
    )
)
def test_yaml_like_text_loads_or_raises_config_error(parts):
    _load_file("".join(parts).encode("utf-8"))
