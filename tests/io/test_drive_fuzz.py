"""Fuzzing the drive loader: random text, random bytes, and truncated or mutated valid files in
place of camera.yaml, frames.csv, gps.csv, gps.gpx, gps.nmea and obd.csv. ``load_drive`` must
return a Drive or raise the project's own ``RoadsurfError`` with a one-line message; any other
exception fails. Bounded: a few hundred examples per file, tiny images."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from roadsurf.core.errors import RoadsurfError
from roadsurf.io.drive import Drive, load_drive
from tests.io.drive_fixtures import T0, gpx_text, make_drive, nmea_lines

FILES = ("camera.yaml", "frames.csv", "gps.csv", "gps.gpx", "gps.nmea", "obd.csv")
UBX = bytes([0xB5, 0x62, 0x01, 0x07, 0x5C, 0x00, 0x24, 0x0A, 0xFF])


@pytest.fixture(scope="module")
def drives(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, bytes]]:
    """For each file: a valid drive holding it (the only GPS log, for the GPS files), and the
    file's valid content."""
    out: dict[str, tuple[Path, bytes]] = {}
    for name in FILES:
        root = tmp_path_factory.mktemp(name.replace(".", "_")) / "d"
        t0 = T0 if name in ("gps.gpx", "gps.nmea") else 0.0
        make_drive(
            root, n=4, t0=t0, gps="csv" if name != "gps.gpx" and name != "gps.nmea" else None
        )
        if name == "gps.gpx":
            (root / name).write_text(gpx_text(T0 - 0.5, 4))
        elif name == "gps.nmea":
            (root / name).write_text("\r\n".join(nmea_lines(T0 - 0.5, 4)) + "\r\n")
        elif name == "obd.csv":
            (root / name).write_text("timestamp_s,speed_mps\n0.0,0.2\n0.1,0.2\n0.2,0.25\n")
        out[name] = (root, (root / name).read_bytes())
    return out


@st.composite
def mutated(draw: st.DrawFn, valid: bytes) -> bytes:
    """The valid content truncated, or with a few bytes replaced, inserted or deleted."""
    data = bytearray(valid)
    if draw(st.booleans()):
        data = data[: draw(st.integers(0, len(data)))]
    for _ in range(draw(st.integers(0, 4))):
        pos = draw(st.integers(0, len(data)))
        op = draw(st.sampled_from(["replace", "insert", "delete", "ubx"]))
        if op == "ubx":
            data[pos:pos] = UBX
        elif op == "delete":
            del data[pos : pos + draw(st.integers(1, 8))]
        else:
            chunk = draw(
                st.one_of(
                    st.binary(min_size=1, max_size=4),
                    st.sampled_from([b",", b"\n", b"-", b"9" * 400, b"nan", b"1e999", b"$", b"*"]),
                    st.text(max_size=4).map(lambda s: s.encode()),
                )
            )
            if op == "replace":
                data[pos : pos + len(chunk)] = chunk
            else:
                data[pos:pos] = chunk
    return bytes(data)


def contents(valid: bytes) -> st.SearchStrategy[bytes]:
    return st.one_of(
        st.text(max_size=300).map(lambda s: s.encode()),
        st.binary(max_size=300),
        mutated(valid),
        mutated(valid),  # weighted: mutations of valid files find the deep paths
    )


def _load(root: Path) -> None:
    try:
        d = load_drive(root)
    except RoadsurfError as e:
        assert "\n" not in str(e), f"multi-line error: {e!s}"
    else:
        assert isinstance(d, Drive)


@pytest.mark.parametrize("name", FILES)
def test_loader_survives_any_content(drives: dict[str, tuple[Path, bytes]], name: str) -> None:
    root, valid = drives[name]

    @settings(
        max_examples=150,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
        database=None,
    )
    @given(data=contents(valid))
    def run(data: bytes) -> None:
        (root / name).write_bytes(data)
        try:
            _load(root)
        finally:
            (root / name).write_bytes(valid)

    run()
