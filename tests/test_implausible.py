"""Points with a value outside its column's plausible range: left out by the graph and flagged
(``implausible``), or refused by the runtime when the card says so; a frame's cost stays that
of a plausible frame whatever a sensor driver writes into one point."""

from __future__ import annotations

import os
import statistics
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from conftest import TINY_CARD

import radaredge
from radaredge import runtime
from radaredge.cards import PLAUSIBLE_DEFAULTS, load_card, plausible_ranges
from radaredge.errors import ConfigError, InputError
from radaredge.models import create_model, model_spec
from radaredge.ops.input_flags import drop_implausible, drop_implausible_reference
from radaredge.runtime.flags import IMPLAUSIBLE, NON_FINITE

MAFF_TINY = Path(__file__).parent / "cards" / "maffnet-tiny.yaml"
F32_MAX = float(np.finfo(np.float32).max)


def test_drop_implausible_equals_its_reference():
    rng = np.random.default_rng(0)
    pts = rng.normal(0, 60, (500, 5)).astype(np.float32)
    pts[::7, 3:] = [np.nan, 0.0]  # a NaN is not "implausible": non_finite
    lo, hi = [-np.inf] * 3 + [-100.0, -50.0], [np.inf] * 3 + [100.0, 50.0]
    got, bad = drop_implausible(torch.from_numpy(pts), lo, hi)
    ref, ref_bad = drop_implausible_reference(pts, lo, hi)
    np.testing.assert_array_equal(bad.numpy(), ref_bad)
    np.testing.assert_array_equal(got.numpy(), ref)  # NaN rows compare equal in assert_array_equal
    assert ref_bad.sum() > 50 and not ref_bad[::7].any()


def test_cards_take_plausible_ranges_and_refuse_bad_ones(tmp_path):
    card = load_card("maffnet-vod")
    assert plausible_ranges(card) == {f: PLAUSIBLE_DEFAULTS[f] for f in ("rcs", "v_r", "v_r_comp", "time")}
    data = yaml.safe_load(TINY_CARD.read_text())
    for plausible, expect in (
        ({"v_r": [5, 1]}, "low 5 must be below high 1"),
        ({"x": [0, 1]}, "are not bounded here"),
        ({"v_r": "fast"}, r"expected \[low, high\]"),
        ({"v_r": [0, float("nan")]}, "finite"),
        ({"speed": [0, 1]}, "are not bounded here"),
    ):
        path = tmp_path / "card.yaml"
        path.write_text(yaml.safe_dump({**data, "plausible": plausible}))
        with pytest.raises(ConfigError, match=expect):
            load_card(path)
    path.write_text(yaml.safe_dump({**data, "implausible": "ignore"}))
    with pytest.raises(ConfigError, match="implausible must be one of"):
        load_card(path)


def _window(card):
    graph = model_spec(card).graph()
    return graph, graph.make_cases(card, 1, 3)[0][1]


@pytest.mark.parametrize("card_path", [TINY_CARD, MAFF_TINY], ids=["tdfanet", "maffnet"])
def test_an_implausible_point_is_left_out_like_a_nan_row(card_path):
    """Both formulations: a frame with one point made implausible in each non-coordinate column
    gives the outputs of the same frame with that row NaN, and flags ``implausible``, not
    ``non_finite``."""
    card = load_card(card_path)
    model = create_model(card)
    graph, feeds = _window(card)
    frame = graph.frame_inputs(card)[-1]
    for col, name in enumerate(card.features):
        if name in ("x", "y", "z"):
            continue
        absurd, nan = dict(feeds), dict(feeds)
        absurd[frame], nan[frame] = feeds[frame].copy(), feeds[frame].copy()
        absurd[frame][0, col] = F32_MAX
        nan[frame][0, :] = np.nan
        for run in (graph.run_export, graph.run_reference):
            with torch.no_grad():
                got = run(model, absurd)
                want = run(model, nan)
            k = len(graph.frame_inputs(card)) - 1
            flags = got["input_flags"].numpy()
            assert flags[k] & IMPLAUSIBLE and not flags[k] & NON_FINITE, (name, flags)
            assert want["input_flags"].numpy()[k] & NON_FINITE
            for out, value in got.items():
                if out != "input_flags":
                    np.testing.assert_array_equal(value.numpy(), want[out].numpy(), err_msg=f"{name}: {out}")


def test_the_runtime_refuses_when_the_card_says_so(tmp_path):
    data = yaml.safe_load(TINY_CARD.read_text())
    card_path = tmp_path / "tdfanet-tiny.yaml"
    card_path.write_text(yaml.safe_dump({**data, "implausible": "refuse", "plausible": {"rcs": [-40, 60]}}))
    res = radaredge.export(str(card_path), tmp_path / "refuse.onnx")
    m = runtime.load(res.path)
    graph, feeds = _window(load_card(card_path))
    frames = [feeds[n] for n in graph.frame_inputs(m.card)]
    frames[1][4, 4] = 61.0
    with pytest.raises(
        InputError,
        match=r"frame 1: point 4, column 'rcs': 61.0 is outside its plausible range "
        r"\[-40, 60\]",
    ):
        m.run(frames)
    assert m.errors & IMPLAUSIBLE
    raw = {**feeds, graph.frame_inputs(m.card)[1]: frames[1]}
    from radaredge.runtime.session import run_session

    assert run_session(m.session, raw)["input_flags"][1] & IMPLAUSIBLE  # the graph drops and flags it too


def _peak_rss(fn, runs: int = 3) -> float:
    """Peak resident memory growth (bytes) over ``runs`` runs of ``fn()``."""
    page = os.sysconf("SC_PAGE_SIZE")

    def rss():
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * page

    peak, stop = [0], threading.Event()

    def sample():
        while not stop.wait(0.002):
            peak[0] = max(peak[0], rss())

    base = rss()
    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    for _ in range(runs):
        fn()
    stop.set()
    thread.join()
    return max(peak[0] - base, 0)


def _cpu_medians(fns, runs: int = 7) -> list[float]:
    """Median CPU seconds of this thread per function, the functions interleaved run by run: a
    one-thread session computes in the calling thread, so the figure is the work done, whatever
    else the machine runs meanwhile."""
    times = [[] for _ in fns]
    for _ in range(runs):
        for fn, acc in zip(fns, times):
            t = time.thread_time()
            fn()
            acc.append(time.thread_time() - t)
    return [statistics.median(acc) for acc in times]


def test_one_absurd_point_costs_no_more_than_a_normal_frame(tmp_path):
    """MAFF-Net (the stage-one tiny card): a scan plus one point with float32's largest value in a
    column, column by column, stays within 1.5x the normal scan's peak memory growth and median
    CPU time (one-thread session, interleaved with the normal scan; a ratio of work, not a
    wall-clock figure), with the same boxes."""
    res = radaredge.export(str(MAFF_TINY), tmp_path / "maffnet-tiny.onnx")
    m = runtime.load(res.path, threads=1)
    card = m.card
    _, feeds = _window(card)
    normal = feeds["points"]
    m.run(normal)  # warm-up: arenas, first-run allocations
    ref = m.run(normal)
    base_mem = _peak_rss(lambda: m.run(normal))
    r = card.get("pillars.point_cloud_range")
    centre = np.zeros(len(card.features), np.float32)
    centre[:3] = [(r[0] + r[3]) / 2, (r[1] + r[4]) / 2, (r[2] + r[5]) / 2]  # where a point reaches the network
    for col, name in enumerate(card.features):
        scan = np.concatenate([normal, centre[None]])
        scan[-1, col] = F32_MAX if name not in ("x", "y", "z") else 1e30
        out = m.run(scan)
        assert out["input_flags"][0] & (IMPLAUSIBLE if name not in ("x", "y", "z") else 4), name
        np.testing.assert_array_equal(out["boxes"], ref["boxes"], err_msg=name)
        mem = _peak_rss(lambda: m.run(scan))
        assert mem <= 1.5 * base_mem + 32 * 2**20, f"{name}: {mem / 2**20:.0f} MiB vs {base_mem / 2**20:.0f} MiB"
        base_time, t = _cpu_medians([lambda: m.run(normal), lambda: m.run(scan)])
        assert t <= 1.5 * base_time + 0.02, f"{name}: {t * 1e3:.1f} ms vs {base_time * 1e3:.1f} ms of CPU"
