"""Fleet scale: `radaredge run` on an embedded Ray instance (outputs equal the sequential runtime's bit
for bit, a killed run resumes), `radaredge map build` / `map query` (the same Recall@N as `radaredge
eval` with the exact index), the runtime's backend choice, and bad input named in one error line."""

from __future__ import annotations

import json

import numpy as np
import pytest

from radaredge import runtime
from radaredge.data.pr_benchmark import make_pr_benchmark
from radaredge.fleet import maps
from radaredge.fleet.pipeline import ShardWorker, plan_shards, run_graph, run_sequential
from radaredge.data.run_shards import MANIFEST, read_run
from conftest import TINY_CARD, invoke, one_error_line


@pytest.fixture(scope="module")
def town(tmp_path_factory):
    """Two short drives of one synthetic town (database and queries) and the tiny TDFANet graph."""
    import radaredge
    d = tmp_path_factory.mktemp("fleet")
    make_pr_benchmark(d / "town", drives=2, frames_per_drive=14, seed=3)
    radaredge.export(TINY_CARD, d / "tiny.onnx")
    return d / "town", d / "tiny.onnx"


def _all(out):
    manifest, poses, outputs = read_run(out)
    return poses, outputs


def test_ray_run_equals_the_sequential_runtime_bit_for_bit_and_resumes(town, tmp_path):
    data, onnx = town
    seq = run_sequential(onnx, data, tmp_path / "seq", shard_windows=5)
    assert seq.windows == 2 * (14 - 2) and seq.shards == 2 * 3          # K = 3 frames: 12 windows a drive
    ray_report = run_graph(onnx, data, tmp_path / "ray", workers=2, shard_windows=5)
    assert ray_report.computed_windows == ray_report.windows == seq.windows and ray_report.workers == 2
    (p1, o1), (p2, o2) = _all(tmp_path / "seq"), _all(tmp_path / "ray")
    for k in p1:
        assert np.array_equal(p1[k], p2[k]), k
    assert o1.keys() == o2.keys() and "descriptor_normalized" in o1
    for k in o1:
        assert o1[k].dtype == o2[k].dtype and o1[k].tobytes() == o2[k].tobytes(), k
    # ... and they are what the runtime gives window by window
    model = runtime.load(onnx, threads=1)
    worker = ShardWorker(str(onnx), 1)
    first = plan_shards(data, model.frames, 5)[0]
    rows, outs = worker.outputs(first)
    assert np.array_equal(np.stack([o["descriptor_normalized"] for o in outs]), o1["descriptor_normalized"][:5])

    # a run killed after some shards: the finished ones are kept (checked by sha256), the rest computed
    manifest = json.loads((tmp_path / "ray" / MANIFEST).read_text())
    kept = sorted(manifest["shards"])[:2]
    for name in sorted(manifest["shards"])[2:]:
        del manifest["shards"][name]
        (tmp_path / "ray" / "shards" / f"{name}.parquet").unlink()
    (tmp_path / "ray" / MANIFEST).write_text(json.dumps(manifest))
    before = {n: (tmp_path / "ray" / "shards" / f"{n}.parquet").read_bytes() for n in kept}
    again = run_graph(onnx, data, tmp_path / "ray", workers=1, shard_windows=5)
    assert again.computed_shards == seq.shards - 2
    assert all((tmp_path / "ray" / "shards" / f"{n}.parquet").read_bytes() == b for n, b in before.items())
    for k, v in _all(tmp_path / "ray")[1].items():
        assert v.tobytes() == o1[k].tobytes(), k
    # a shard changed since it was recorded is named, not silently trusted
    victim = tmp_path / "ray" / "shards" / f"{kept[0]}.parquet"
    victim.write_bytes(victim.read_bytes()[:-10])
    res = invoke("run", "--onnx", onnx, "--data", data, "--out", tmp_path / "ray")
    one_error_line(res, kept[0], "sha256 differs")


def test_map_build_and_query_give_evals_recall(town, tmp_path):
    data, onnx = town
    res = invoke("map", "build", "--model", "tdfanet-tiny", "--config", TINY_CARD, "--onnx", onnx,
                 "--drives", data / "database", "--out", tmp_path / "map", "--workers", 1, "--json")
    assert res.exit_code == 0, res.output
    built = json.loads(res.stdout)
    assert built["index"]["kind"] == "flat" and built["windows"] == 12
    info = json.loads((tmp_path / "map" / "map.json").read_text())
    assert info["weights_sha256"] == runtime.load(onnx).weights_sha256 and info["model"] == "tdfanet-tiny"
    res = invoke("map", "query", "--map", tmp_path / "map", "--drive", data / "queries", "--radius", 25, "--json")
    assert res.exit_code == 0, res.output
    found = json.loads(res.stdout)
    res = invoke("eval", "--model", "tdfanet-tiny", "--config", TINY_CARD, "--onnx", onnx, "--database",
                 data / "database", "--queries", data / "queries", "--radius", 25, "--no-reference",
                 "--report", tmp_path / "eval.json", "--plot", tmp_path / "eval.png", "--json")
    assert res.exit_code == 0, res.output
    evaluated = json.loads(res.stdout)
    recall = evaluated["recall"]["onnxruntime"]
    for n, v in found["recall"]["recall"].items():
        assert v == pytest.approx(recall[str(n)], abs=1e-9), n
    assert len(found["queries"]) == 12 and len(found["queries"][0]["top"]) == 10
    # eval takes the map as its database: the same Recall@N
    res = invoke("eval", "--model", "tdfanet-tiny", "--config", TINY_CARD, "--onnx", onnx, "--map", tmp_path / "map",
                 "--queries", data / "queries", "--radius", 25, "--no-reference", "--report", tmp_path / "m.json",
                 "--plot", tmp_path / "m.png", "--json")
    assert res.exit_code == 0, res.output
    on_map = json.loads(res.stdout)
    # the map holds the graph's descriptors only, so eval --map has no no-learning baseline row
    assert on_map["recall"] == {"onnxruntime": evaluated["recall"]["onnxruntime"]}
    assert "polar_occupancy" in evaluated["recall"] and on_map["database"]["windows"] == 12
    one_error_line(invoke("eval", "--model", "tdfanet-tiny", "--config", TINY_CARD, "--onnx", onnx, "--map",
                          tmp_path / "map", "--queries", data / "queries"), "--no-reference")
    # a graph of other weights is refused
    other = tmp_path / "other.onnx"
    import radaredge
    from radaredge.cards import load_card
    card = load_card(TINY_CARD)
    card.data["seed"] = 7
    radaredge.export(card, other)
    one_error_line(invoke("map", "query", "--map", tmp_path / "map", "--drive", data / "queries", "--onnx", other),
                   "was built with", "build the map again")


def test_large_map_index_recovers_the_exact_neighbours():
    rng = np.random.default_rng(0)
    base = rng.normal(size=(20_000, 32)).astype(np.float32)
    queries = base[rng.choice(len(base), 200, replace=False)] + rng.normal(0, 0.05, (200, 32)).astype(np.float32)
    exact = maps.build_index(base, maps.index_parameters("flat", *base.shape))
    truth = maps._search(exact, queries, 1)[1][:, 0]
    for kind in ("ivfpq", "hnsw"):
        params = maps.index_parameters(kind, *base.shape)
        got = maps._search(maps.build_index(base, params), queries, 1)[1][:, 0]
        assert (got == truth).mean() >= 0.95, kind
    assert maps.index_parameters("auto", 10**6, 256)["kind"] == "ivfpq"
    assert maps.index_parameters("auto", 10**5, 256)["kind"] == "flat"


def test_the_runtime_backend_auto_picks_and_remembers_one(town, tmp_path, monkeypatch):
    monkeypatch.setenv("RADAREDGE_CACHE", str(tmp_path))
    _, onnx = town
    model = runtime.load(onnx, threads=1, backend="auto")
    frames = [np.zeros((10, 5), np.float32) + i for i in range(model.frames)]
    out = model.run(frames)
    assert model.backend in ("onnxruntime", "openvino") and "descriptor_normalized" in out
    cache = json.loads((tmp_path / "backends.json").read_text())
    (entry,) = cache.values()
    assert entry["backend"] == model.backend and set(entry["median_s"]) == {"onnxruntime", "openvino"}
    assert runtime.load(onnx, threads=1, backend="auto").backend == model.backend     # no second trial
    from radaredge.runtime import backends
    monkeypatch.setattr(backends, "auto_available", lambda: False)     # no OpenVINO: auto is onnxruntime
    assert runtime.load(onnx, threads=1, backend="auto").backend == "onnxruntime"
    monkeypatch.undo()
    ov = runtime.load(onnx, threads=1, backend="openvino")
    np.testing.assert_allclose(ov.run(frames)["descriptor_normalized"],
                               runtime.load(onnx, threads=1).run(frames)["descriptor_normalized"], atol=1e-4)


@pytest.mark.parametrize("case, needles", [
    ("no-scans", ["no drives found"]),
    ("bad-address", ["--ray-address 127.0.0.1:1", "cannot connect"]),
])
def test_bad_fleet_input_ends_with_one_error_line(town, tmp_path, case, needles):
    data, onnx = town
    if case == "no-scans":
        (tmp_path / "empty").mkdir()
        res = invoke("run", "--onnx", onnx, "--data", tmp_path / "empty", "--out", tmp_path / "out")
    else:
        import ray
        if ray.is_initialized():
            ray.shutdown()
        res = invoke("run", "--onnx", onnx, "--data", data, "--out", tmp_path / "out", "--ray-address", "127.0.0.1:1")
    one_error_line(res, *needles)
    assert not (tmp_path / "out" / "shards").exists() or not any((tmp_path / "out" / "shards").iterdir())


def test_a_detector_runs_over_every_frame_of_vod_bin_drives(tmp_path):
    """MAFF-Net: one frame a window, the drive's .bin scans read as View-of-Delft's (format inferred);
    detections of varying count per frame come back as the runtime gives them."""
    import radaredge
    from radaredge.data.sequences import write_sequence
    from conftest import MAFFNET_TINY_CARD
    radaredge.export(MAFFNET_TINY_CARD, tmp_path / "det.onnx")
    rng = np.random.default_rng(4)
    scans = []
    for n in (40, 0, 25, 60, 3, 33):                    # VoD's 7 columns: x y z rcs v_r v_r_comp time
        scan = np.zeros((n, 7), np.float32)
        scan[:, 0], scan[:, 1], scan[:, 2] = rng.uniform(1, 12, n), rng.uniform(-6, 6, n), rng.uniform(-1, 1, n)
        scan[:, 3:6] = rng.normal(0, 3, (n, 3))
        scans.append(scan)
    write_sequence(tmp_path / "drives" / "d0", scans, np.arange(6) * 0.1, np.stack([np.arange(6.0), np.zeros(6)], 1),
                   fmt="vod")
    report = run_graph(tmp_path / "det.onnx", tmp_path / "drives", tmp_path / "out", workers=1)
    assert report.windows == 6
    poses, outputs = _all(tmp_path / "out")
    model = runtime.load(tmp_path / "det.onnx", threads=1)
    from radaredge.data.sequences import load_sequence
    seq = load_sequence(tmp_path / "drives" / "d0", "vod")
    for i in range(6):
        want = model.run([seq.scan(i, model.features)])
        assert np.array_equal(np.asarray(outputs["boxes"][i]), want["boxes"]), i
    assert poses["frame"].tolist() == list(range(6))
