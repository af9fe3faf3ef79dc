"""Fuzzing the configuration loader: whatever a file holds, the answer is a Config or a ConfigError naming the
problem, within a bounded time; never a traceback, never a hang, never an unbounded read."""

from __future__ import annotations

import datetime as dt
import math
import os
import time
from pathlib import Path
from typing import Any

import pytest
from extras import HealthCheck, given, settings, st

from logger.config import SCHEMA, Config, ConfigError, load, parse

# FUZZ_EXAMPLES=5000 (environment) searches deeper than the suite's default.
FUZZ = settings(max_examples=int(os.environ.get("FUZZ_EXAMPLES", "300")), deadline=None,
                suppress_health_check=[HealthCheck.too_slow])


def parse_or_refuse(text: str) -> Config | None:
    try:
        return parse(text, "fuzz.toml")
    except ConfigError as exc:
        assert exc.problems and all(isinstance(p, str) and p.startswith("fuzz.toml") for p in exc.problems)
        assert all("\n" not in p for p in exc.problems)  # one line per problem
        return None


@FUZZ
@given(st.text(max_size=2000))
def test_any_text(text: str) -> None:
    parse_or_refuse(text)


# ---- documents shaped like the schema, with values of every TOML type ---------------------------------------

def _toml_key(k: str) -> str:
    return k if k and all(c.isalnum() or c in "_-" for c in k) else _toml_str(k)


def _toml_str(s: str) -> str:
    out = []
    for c in s:
        if c in '"\\':
            out.append("\\" + c)
        elif ord(c) < 0x20 or ord(c) == 0x7F:
            out.append(f"\\u{ord(c):04x}")
        else:
            out.append(c)
    return '"' + "".join(out) + '"'


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v):
            return "nan"
        if math.isinf(v):
            return "inf" if v > 0 else "-inf"
        return repr(v)
    if isinstance(v, str):
        return _toml_str(v)
    if isinstance(v, dt.datetime | dt.date | dt.time):
        return v.isoformat()
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(type(v))


scalars = st.one_of(
    st.booleans(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),  # TOML's integer range
    st.floats(allow_nan=True, allow_infinity=True),
    st.text(max_size=40),
    st.datetimes(min_value=dt.datetime(1, 1, 1), max_value=dt.datetime(9999, 12, 31)),
    st.dates(),
)
values = st.recursive(scalars, lambda inner: st.lists(inner, max_size=4)
                      | st.dictionaries(st.text(min_size=1, max_size=8), inner, max_size=3), max_leaves=8)
known_keys = [(s, k) for s, keys in SCHEMA.items() for k in keys]


@st.composite
def documents(draw: st.DrawFn) -> str:
    sections: dict[str, dict[str, Any]] = {}
    for section, key in draw(st.lists(st.sampled_from(known_keys), max_size=12)):
        sections.setdefault(section, {})[key] = draw(values)
    for _ in range(draw(st.integers(0, 2))):  # unknown sections and keys, too
        sections.setdefault(draw(st.text(min_size=1, max_size=10)), {})[draw(st.text(min_size=1, max_size=10))] = \
            draw(values)
    lines = []
    for section, body in sections.items():
        lines.append(f"[{_toml_key(section)}]")
        lines += [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in body.items()]
    return "\n".join(lines) + "\n"


@FUZZ
@given(documents())
def test_schema_shaped_documents(text: str) -> None:
    cfg = parse_or_refuse(text)
    if cfg is not None:  # everything accepted is of the declared type and passed its check
        for section, keys in SCHEMA.items():
            for key, spec in keys.items():
                value = cfg[section][key]
                if value is None or f"{section}.{key}" not in cfg.explicit:
                    continue
                assert spec.check is None or spec.check(value) is None


@FUZZ
@given(st.sampled_from(known_keys), st.integers(min_value=-(2**63), max_value=2**63 - 1))
def test_every_integer_for_every_key(where: tuple[str, str], value: int) -> None:
    parse_or_refuse(f"[{where[0]}]\n{where[1]} = {value}\n")


@FUZZ
@given(st.sampled_from(known_keys), st.floats(allow_nan=True, allow_infinity=True))
def test_every_float_for_every_key(where: tuple[str, str], value: float) -> None:
    parse_or_refuse(f"[{where[0]}]\n{where[1]} = {_toml_value(value)}\n")


# ---- found by fuzzing ------------------------------------------------------------------------------------------

@pytest.mark.parametrize("text", [
    # A table header padded with thousands of blanks (valid TOML): the line index must not take seconds on it.
    "[" + " " * 20000 + "imu" + " " * 20000 + "]\nbus = 1\n",
    # Inside a multi-line string any line may look like the start of a table header.
    'x = """\n[' + " " * 30000 + "a\n" + '"""\n',
])
def test_pathological_lines_are_indexed_quickly(text: str) -> None:
    """Against a yardstick of the same run, not the clock: one Python pass over the text's characters. Parsing
    and indexing it costs two to five such passes (x86 and armhf alike); the lazy pattern this replaced
    backtracked in cubic time on the blanks (minutes), and even a quadratic scan of its 30-40 thousand characters
    done in C (str.strip at every position) costs 75-340."""
    passes = _least_time(parse_or_refuse, text) / _least_time(_python_pass, text)
    assert passes < 30, passes


def _python_pass(text: str) -> int:
    return sum(1 for ch in text if ch == "[")


def _least_time(work: Any, arg: str, runs: int = 3) -> float:
    """The least time of a few runs: what the work costs, without what a busy host added to some of them."""
    least = math.inf
    for _ in range(runs):
        t0 = time.perf_counter()
        work(arg)
        least = min(least, time.perf_counter() - t0)
    return least


def test_a_device_or_endless_file_is_refused_without_reading_it(tmp_path: Path) -> None:
    for path in ("/dev/zero", "/dev/urandom"):
        if os.path.exists(path):
            with pytest.raises(ConfigError, match="not a regular file"):
                load(path)
            # The type is checked before the first read: a device read up to the size limit is refused as too large
            # or not text, and one read without a limit never ends (no time bound needed: nothing else in between).
    with pytest.raises(ConfigError, match="not a regular file"):
        load(tmp_path)
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * (2 << 20) + "\n")
    with pytest.raises(ConfigError, match="too large"):
        load(big)
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)  # opening a FIFO for reading would block until a writer comes
    with pytest.raises(ConfigError, match="not a regular file"):
        load(fifo)
