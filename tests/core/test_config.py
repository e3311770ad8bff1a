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
    with pytest.raises(ConfigError, match=r"cfg.yaml.inner: unknown key\(s\) \['lamda'\]"):
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
