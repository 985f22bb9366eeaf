"""Card sections are validated field by field: every numeric field declares its range."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest

from radaredge.cards import load_card
from radaredge.cards.des4pos import CellConfig, TextConfig
from radaredge.config import Range, card_ranges, config_from_dict, field_range
from radaredge.data.road_network import NetworkConfig
from radaredge.errors import ConfigError
from radaredge.models.des4pos.model import FineConfig, SubmapConfig
from radaredge.models.maffnet.fuser import CafConfig
from radaredge.models.maffnet.model import AnchorClass, BackboneConfig, HeadConfig, InputConfig, SpaConfig
from radaredge.models.maffnet.rcnn import KeypointConfig, ProposalConfig, RoiHeadConfig, SAConfig, VsaConfig
from radaredge.models.tdfanet.model import TDFANetConfig
from radaredge.ops.dbscan import DbscanConfig
from radaredge.ops.ego_velocity import RansacConfig
from radaredge.ops.grid_density import GridDensityConfig
from radaredge.ops.nms import NmsConfig
from radaredge.ops.pillars import PillarConfig

SECTIONS = [
    PillarConfig,
    DbscanConfig,
    GridDensityConfig,
    RansacConfig,
    NmsConfig,
    SpaConfig,
    InputConfig,
    BackboneConfig,
    AnchorClass,
    HeadConfig,
    CafConfig,
    TDFANetConfig,
    ProposalConfig,
    KeypointConfig,
    SAConfig,
    VsaConfig,
    RoiHeadConfig,
    SubmapConfig,
    FineConfig,
    CellConfig,
    TextConfig,
    NetworkConfig,
]


def _numeric(f: dataclasses.Field) -> bool:
    d = f.default
    if f.name in ("anchor_sizes",):  # required, no default: a list of sizes
        return True
    flat = list(_flat(d)) if isinstance(d, tuple) else [d]
    return bool(flat) and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in flat)


def _flat(t):
    for v in t:
        yield from (_flat(v) if isinstance(v, tuple) else (v,))


@pytest.mark.parametrize("cls", SECTIONS, ids=lambda c: c.__name__)
def test_every_numeric_field_declares_a_range(cls):
    missing = [f.name for f in dataclasses.fields(cls) if _numeric(f) and field_range(cls, f.name) is None]
    assert not missing, f"{cls.__name__}: no card_ranges for {missing}"


@pytest.mark.parametrize("cls", SECTIONS, ids=lambda c: c.__name__)
def test_defaults_lie_in_their_ranges(cls):
    for f in dataclasses.fields(cls):
        rng = field_range(cls, f.name)
        if rng is None or f.default is dataclasses.MISSING or f.default is None:  # None: unset, optional
            continue
        values = list(_flat(f.default)) if isinstance(f.default, tuple) else [f.default]
        assert all(v in rng for v in values), f"{cls.__name__}.{f.name} = {f.default} outside {rng}"


@card_ranges(count=(1, 10), ratio=Range(0.0, 1.0, high_open=True), sizes=(0.5, 4.0))
@dataclasses.dataclass(frozen=True)
class _Section:
    count: int = 2
    ratio: float = 0.5
    sizes: tuple = (1.0, 2.0)
    name: str = "a"


@pytest.mark.parametrize(
    "field,value,message",
    [
        ("count", 0, "count: 0 is out of range; allowed [1, 10]"),
        ("count", 2.5, "count: expected an integer in [1, 10], got 2.5"),
        ("count", "3", "count: expected an integer in [1, 10], got '3'"),
        ("count", True, "count: expected an integer"),
        ("ratio", 1.0, "ratio: 1.0 is out of range; allowed [0, 1)"),
        ("ratio", math.nan, "ratio: expected a finite number in [0, 1)"),
        ("ratio", math.inf, "ratio: expected a finite number"),
        ("sizes", [1.0, 5.0], "sizes: 5.0 is out of range; allowed [0.5, 4]"),
        ("sizes", [1.0, "x"], "sizes: expected a number in [0.5, 4]"),
        ("sizes", 1.0, "sizes: expected a list"),
        ("name", 3, "name: expected a string"),
    ],
)
def test_violations_name_the_field_and_the_range(field, value, message):
    with pytest.raises(ConfigError) as err:
        config_from_dict(_Section, {field: value}, "card.yaml: sec")
    assert f"card.yaml: sec.{message}" in str(err.value)


def test_valid_values_convert():
    s = config_from_dict(_Section, {"count": 3.0, "ratio": 0, "sizes": [1, 2]}, "w")
    assert s == _Section(count=3, ratio=0.0, sizes=(1, 2))
    assert isinstance(s.count, int) and isinstance(s.ratio, float)


def test_a_range_for_a_missing_field_is_a_programming_error():
    with pytest.raises(TypeError, match="no field"):
        card_ranges(nope=(0, 1))(_Section)


def test_every_benchmark_card_builds():
    """The configurations tried under benchmarks/cards/ stay valid cards of the current code."""
    from radaredge.models import create_model

    paths = sorted((Path(__file__).resolve().parent.parent / "benchmarks" / "cards").glob("*.yaml"))
    assert paths
    for path in paths:
        card = load_card(path)
        assert card.name == path.stem and create_model(card) is not None
