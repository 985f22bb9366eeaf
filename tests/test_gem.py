"""GeM pooling: module == float64 numpy reference, the p = 1 and large-p limits, ONNX round trip.

Tolerance: GeM values scale with the input (a map of values ~1e3 pools to ~1e3), so the module
is compared element-wise relative, |got - expected| <= 1e-5 * |expected| (float32 carries ~6e-8
relative per operation; pow, mean and the root stay well inside 1e-5).
"""

import numpy as np
import pytest
import torch

from radaredge.errors import ConfigError, InputError
from radaredge.ops.gem import GeM, gem_reference

RTOL = 1e-5


def assert_rel_close(got, expected, what=""):
    got, expected = np.asarray(got, np.float64), np.asarray(expected, np.float64)
    assert got.shape == expected.shape, f"{what}: shape {got.shape} != {expected.shape}"
    rel = np.abs(got - expected) / np.abs(expected)
    assert rel.max() <= RTOL, f"{what}: max rel error {rel.max():.3g} > {RTOL:g}"


def feature_map(shape=(2, 5, 9, 11), scale=1.0, seed=0):
    """ReLU-like map: a third exact zeros (clamped to eps), the rest uniform in (0, scale)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-0.5, 1.0, shape) * scale
    return torch.from_numpy(x.astype(np.float32))


@pytest.mark.parametrize("p", [1.0, 3.0, 4.5])
@pytest.mark.parametrize("scale", [1.0, 1e3])
def test_matches_reference(p, scale):
    x = feature_map(scale=scale)
    with torch.no_grad():
        got = GeM(p=p)(x).numpy()
    assert_rel_close(got, gem_reference(x.numpy(), p), f"p={p}, scale={scale}")


def test_p1_is_the_mean_of_the_clamped_map():
    x = feature_map(seed=1)
    with torch.no_grad():
        got = GeM(p=1.0)(x)
    expected = x.clamp(min=1e-6).double().mean((-2, -1))
    assert_rel_close(got, expected, "p=1")


def test_large_p_approaches_the_max():
    x = feature_map(seed=2).numpy()
    peak = np.maximum(x.astype(np.float64), 1e-6).max(axis=(-2, -1))
    values = [gem_reference(x, p) for p in (1, 3, 10, 50, 400)]
    for lower, higher in zip(values, values[1:]):  # power-mean inequality
        assert np.all(lower <= higher * (1 + 1e-12)) and np.all(higher <= peak * (1 + 1e-12))
    hw = x.shape[-1] * x.shape[-2]
    assert np.all(values[-1] >= peak * hw ** (-1 / 400) * (1 - 1e-12))  # mean(x^p) >= max^p / HW
    with torch.no_grad():  # float32 module at p = 50
        assert_rel_close(GeM(p=50.0)(torch.from_numpy(x)), values[3], "p=50")


def test_learnable_flag_and_validation():
    assert isinstance(GeM(learnable=True).p, torch.nn.Parameter)
    frozen = GeM(p=2.0, learnable=False)
    assert not list(frozen.parameters()) and "p" in frozen.state_dict()
    with pytest.raises(ConfigError):
        GeM(p=0.0)
    with pytest.raises(InputError):
        GeM()(torch.ones(2, 3))


def test_onnx_export_matches_torch(onnx_roundtrip):
    gem = GeM(p=3.7)
    rt = onnx_roundtrip(gem, {"x": feature_map()}, ["descriptor"], {"x": {0: "B", 2: "H", 3: "W"}})
    for shape, scale, seed in [((2, 5, 9, 11), 1.0, 1), ((1, 5, 27, 31), 1e3, 2), ((3, 5, 4, 4), 1e-2, 3)]:
        ref, got = rt({"x": feature_map(shape, scale, seed)})
        assert_rel_close(got["descriptor"], ref["descriptor"], f"onnxruntime {shape}")
