"""Hypothesis fuzzing of what users feed radaredge: the runtime's frames and timestamps, the scan
and drive readers, and the card parser. Whatever comes in, the result is either a finite output or
one of radaredge's own errors (never another exception, a NaN or a hang). Examples are bounded so
the suite stays fast; every example also has a deadline. In CI (``CI`` set) the examples are
derandomised, so a red run is reproducible and never a matter of the draw; elsewhere each run
draws new ones (a failure prints the example to add to the bad-input catalogue)."""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from radaredge import runtime
from radaredge.cards import card_from_yaml
from radaredge.data.readers import read_scan
from radaredge.data.sequences import load_sequence
from radaredge.errors import RadarEdgeError
from radaredge.models.tdfanet.model import TDFANetConfig
from radaredge.ops.ego_velocity import RansacConfig
from radaredge.ops.pillars import PillarConfig

IN_CI = bool(os.environ.get("CI"))
FUZZ = settings(
    max_examples=60,
    deadline=5000,
    derandomize=IN_CI,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

FLOATS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True, width=32),
    st.sampled_from([0.0, -0.0, 1e30, -1e30, 3.4e38, -3.4e38, 1e-45, 5.0, 80.0, -40.0]),
)


@pytest.fixture(scope="module")
def model(tiny_export):
    return runtime.load(tiny_export[2], threads=1)


def frames_strategy(columns: int = 5):
    shapes = st.tuples(st.integers(0, 400), st.sampled_from([columns, columns, columns, 3, 6]))
    dtypes = st.sampled_from([np.float32, np.float64, np.float16, np.int32, np.int16, np.uint8, np.int64])
    arrays = st.builds(
        lambda shape, dtype, seed, scale, bad: _array(shape, dtype, seed, scale, bad),
        shapes,
        dtypes,
        st.integers(0, 2**31),
        st.sampled_from([1.0, 50.0, 1e6, 1e30]),
        st.sampled_from([None, np.nan, np.inf, -np.inf]),
    )
    return st.lists(arrays, min_size=2, max_size=4)


@np.errstate(invalid="ignore", over="ignore")
def _array(shape, dtype, seed, scale, bad):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=shape) * scale
    if np.issubdtype(dtype, np.integer):
        info = np.iinfo(dtype)
        a = np.clip(a, info.min, info.max)
    a = a.astype(dtype)
    if bad is not None and a.size and np.issubdtype(dtype, np.floating):
        a.flat[rng.integers(0, a.size)] = bad
    layout = seed % 3
    return np.asfortranarray(a) if layout == 1 else (a[::1] if layout == 0 else np.repeat(a, 2, axis=0)[::2])


@FUZZ
@given(
    frames=frames_strategy(),
    stamps=st.one_of(
        st.none(), st.lists(FLOATS, min_size=0, max_size=4), st.lists(st.floats(1e9, 2e9), min_size=3, max_size=3)
    ),
)
def test_runtime_gives_finite_outputs_or_its_own_error(model, frames, stamps):
    try:
        out = model.run(frames, stamps)
    except RadarEdgeError as exc:
        assert str(exc) and "\n" not in str(exc)
        return
    for name, value in out.items():
        if np.issubdtype(value.dtype, np.floating):
            assert np.isfinite(value).all(), name
    assert abs(float(np.linalg.norm(out["descriptor_normalized"])) - 1.0) < 1e-3
    assert np.all(np.linalg.norm(out["ego_velocity"], axis=1) <= 70.0 + 1e-3)


@FUZZ
@given(
    data=st.binary(max_size=3000),
    suffix=st.sampled_from([".bin", ".npy"]),
    fmt=st.sampled_from([None, "vod", "tj4d", "transloc"]),
)
def test_scan_reader_on_random_bytes(data, suffix, fmt):
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / f"scan{suffix}"
        path.write_bytes(data)
        try:
            out = read_scan(path, ["x", "y", "z"], fmt)
        except RadarEdgeError:
            return
        assert out.dtype == np.float32 and out.ndim == 2 and out.shape[1] == 3


@FUZZ
@given(
    rows=st.lists(st.lists(st.one_of(FLOATS.map(repr), st.text(max_size=6)), min_size=0, max_size=4), max_size=6),
    header=st.sampled_from(["timestamp,northing,easting", "timestamp,easting", "", "easting,timestamp,northing,x"]),
)
def test_gps_reader_on_random_tables(rows, header):
    with tempfile.TemporaryDirectory() as d:
        drive = Path(d)
        (drive / "scans").mkdir()
        for i in range(len(rows)):
            np.save(drive / "scans" / f"{i:06d}.npy", np.zeros((2, 5), np.float32))
        if not rows:
            np.save(drive / "scans" / "000000.npy", np.zeros((2, 5), np.float32))
        (drive / "gps.csv").write_text("\n".join([header] + [",".join(r) for r in rows]) + "\n")
        try:
            seq = load_sequence(drive)
        except RadarEdgeError:
            return
        assert np.isfinite(seq.timestamps).all() and np.isfinite(seq.positions).all()
        assert (np.diff(seq.timestamps) > 0).all()


SECTIONS = {"preprocess": {"ransac": RansacConfig}, "pillars": PillarConfig, "network": TDFANetConfig}
VALUES = st.one_of(
    FLOATS, st.integers(-(10**12), 10**12), st.booleans(), st.text(max_size=5), st.none(), st.lists(FLOATS, max_size=7)
)


@st.composite
def cards(draw):
    text = Path(__file__).with_name("cards").joinpath("tdfanet-tiny.yaml").read_text()
    data = yaml.safe_load(text)
    for _ in range(draw(st.integers(1, 4))):
        section = draw(
            st.sampled_from(
                [
                    "preprocess.ransac",
                    "pillars",
                    "network",
                    "frames",
                    "frame_rate",
                    "seed",
                    "features",
                    "max_points_per_frame",
                ]
            )
        )
        if "." in section or section in ("pillars", "network"):
            cls = RansacConfig if section == "preprocess.ransac" else SECTIONS[section]
            field = draw(st.sampled_from([f for f in cls.__dataclass_fields__]))
            node = data
            for part in section.split("."):
                node = node.setdefault(part, {})
            node[field] = draw(VALUES)
        else:
            data[section] = draw(VALUES)
    return yaml.safe_dump(data)


@settings(max_examples=80, deadline=5000, derandomize=IN_CI)
@given(text=cards())
def test_card_parser_refuses_or_builds(text):
    """A fuzzed card is refused with a ConfigError, or every section it has parses into finite values."""
    from radaredge.models import create_model

    try:
        card = card_from_yaml(text)
        create_model(card)
    except RadarEdgeError:
        return
    for section in (
        card.section("preprocess.ransac", RansacConfig),
        card.section("pillars", PillarConfig),
        card.section("network", TDFANetConfig),
    ):
        for value in section.__dict__.values():
            for x in value if isinstance(value, tuple) else (value,):
                if isinstance(x, float):
                    assert math.isfinite(x)


@settings(max_examples=60, deadline=5000, derandomize=IN_CI)
@given(text=st.text(max_size=400))
def test_card_parser_on_random_text(text):
    try:
        card_from_yaml(text)
    except RadarEdgeError:
        pass
