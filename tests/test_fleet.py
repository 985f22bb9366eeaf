"""Fleet scale: `radaredge run` on an embedded Ray instance (outputs equal the sequential runtime's bit
for bit, a killed run resumes), `radaredge map build` / `map query` (the same Recall@N as `radaredge
eval` with the exact index), the runtime's backend choice, and bad input named in one error line.
Nothing lost or silently wrong: drives whose paths flatten alike keep their own shards, a failed run
leaves the previous one as it was, a missing shard is named and repaired, a resumed run follows the
data as it is now, and threads or workers beyond the CPUs are cut down instead of hanging."""

from __future__ import annotations

import contextlib
import json
import shutil
import signal

import numpy as np
import pytest
from conftest import TINY_CARD, invoke, one_error_line

from radaredge import runtime
from radaredge.data.pr_benchmark import make_pr_benchmark
from radaredge.data.run_shards import MANIFEST, read_run
from radaredge.errors import InputError
from radaredge.fleet import maps
from radaredge.fleet.pipeline import ShardWorker, available_cpus, plan_shards, run_graph, run_sequential


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
    assert seq.windows == 2 * (14 - 2) and seq.shards == 2 * 3  # K = 3 frames: 12 windows a drive
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
    res = invoke(
        "map",
        "build",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        onnx,
        "--drives",
        data / "database",
        "--out",
        tmp_path / "map",
        "--workers",
        1,
        "--json",
    )
    assert res.exit_code == 0, res.output
    built = json.loads(res.stdout)
    assert built["index"]["kind"] == "flat" and built["windows"] == 12
    info = json.loads((tmp_path / "map" / "map.json").read_text())
    assert info["weights_sha256"] == runtime.load(onnx).weights_sha256 and info["model"] == "tdfanet-tiny"
    res = invoke("map", "query", "--map", tmp_path / "map", "--drive", data / "queries", "--radius", 25, "--json")
    assert res.exit_code == 0, res.output
    found = json.loads(res.stdout)
    res = invoke(
        "eval",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        onnx,
        "--database",
        data / "database",
        "--queries",
        data / "queries",
        "--radius",
        25,
        "--no-reference",
        "--report",
        tmp_path / "eval.json",
        "--plot",
        tmp_path / "eval.png",
        "--json",
    )
    assert res.exit_code == 0, res.output
    evaluated = json.loads(res.stdout)
    recall = evaluated["recall"]["onnxruntime"]
    for n, v in found["recall"]["recall"].items():
        assert v == pytest.approx(recall[str(n)], abs=1e-9), n
    assert len(found["queries"]) == 12 and len(found["queries"][0]["top"]) == 10
    # eval takes the map as its database: the same Recall@N
    res = invoke(
        "eval",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        onnx,
        "--map",
        tmp_path / "map",
        "--queries",
        data / "queries",
        "--radius",
        25,
        "--no-reference",
        "--report",
        tmp_path / "m.json",
        "--plot",
        tmp_path / "m.png",
        "--json",
    )
    assert res.exit_code == 0, res.output
    on_map = json.loads(res.stdout)
    # the map holds the graph's descriptors only, so eval --map has no no-learning baseline row
    assert on_map["recall"] == {"onnxruntime": evaluated["recall"]["onnxruntime"]}
    assert "polar_occupancy" in evaluated["recall"] and on_map["database"]["windows"] == 12
    one_error_line(
        invoke(
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            TINY_CARD,
            "--onnx",
            onnx,
            "--map",
            tmp_path / "map",
            "--queries",
            data / "queries",
        ),
        "--no-reference",
    )
    # a graph of other weights is refused
    other = tmp_path / "other.onnx"
    import radaredge
    from radaredge.cards import load_card

    card = load_card(TINY_CARD)
    card.data["seed"] = 7
    radaredge.export(card, other)
    one_error_line(
        invoke("map", "query", "--map", tmp_path / "map", "--drive", data / "queries", "--onnx", other),
        "was built with",
        "build the map again",
    )


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
    assert runtime.load(onnx, threads=1, backend="auto").backend == model.backend  # no second trial
    from radaredge.runtime import backends

    monkeypatch.setattr(backends, "auto_available", lambda: False)  # no OpenVINO: auto is onnxruntime
    assert runtime.load(onnx, threads=1, backend="auto").backend == "onnxruntime"
    monkeypatch.undo()
    ov = runtime.load(onnx, threads=1, backend="openvino")
    np.testing.assert_allclose(
        ov.run(frames)["descriptor_normalized"],
        runtime.load(onnx, threads=1).run(frames)["descriptor_normalized"],
        atol=1e-4,
    )


@pytest.mark.parametrize(
    "case, needles",
    [
        ("no-scans", ["no drives found"]),
        ("bad-address", ["--ray-address 127.0.0.1:1", "cannot connect"]),
    ],
)
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
    from conftest import MAFFNET_TINY_CARD

    import radaredge
    from radaredge.data.sequences import write_sequence

    radaredge.export(MAFFNET_TINY_CARD, tmp_path / "det.onnx")
    rng = np.random.default_rng(4)
    scans = []
    for n in (40, 0, 25, 60, 3, 33):  # VoD's 7 columns: x y z rcs v_r v_r_comp time
        scan = np.zeros((n, 7), np.float32)
        scan[:, 0], scan[:, 1], scan[:, 2] = rng.uniform(1, 12, n), rng.uniform(-6, 6, n), rng.uniform(-1, 1, n)
        scan[:, 3:6] = rng.normal(0, 3, (n, 3))
        scans.append(scan)
    write_sequence(
        tmp_path / "drives" / "d0", scans, np.arange(6) * 0.1, np.stack([np.arange(6.0), np.zeros(6)], 1), fmt="vod"
    )
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


@contextlib.contextmanager
def _deadline(seconds: float):
    """Fail the test with TimeoutError after ``seconds`` instead of hanging (main thread only)."""

    def expire(signum, frame):
        raise TimeoutError(f"still running after {seconds} s")

    old = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _fleet(root, town_data, **drives):
    """Drives under ``root``: name (a relative path) -> the town's drive ("database" or "queries") copied there."""
    for name, source in drives.items():
        (drive,) = (town_data / source).iterdir()
        shutil.copytree(drive, root / name)
    return root


def _last_scan(drive):
    return sorted((drive / "scans").iterdir())[-1]


def _shard_files(out):
    return {p.name: p.read_bytes() for p in (out / "shards").iterdir()} if (out / "shards").is_dir() else {}


def _descriptors_of(onnx, drive):
    """The runtime's descriptors of every window of one drive, window by window."""
    worker = ShardWorker(str(onnx), 1)
    (plan,) = plan_shards(drive, worker.model.frames, 1 << 30)
    return np.stack([o["descriptor_normalized"] for o in worker.outputs(plan)[1]])


def test_drives_whose_paths_flatten_alike_keep_their_own_shards(town, tmp_path):
    """`a/b` and `a__b` were both shard `a__b-00000`: one drive's windows vanished from the run and the map."""
    data, onnx = town
    root = _fleet(tmp_path / "fleet", data, **{"a/b": "database", "a__b": "queries"})
    res = invoke(
        "map",
        "build",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        onnx,
        "--drives",
        root,
        "--out",
        tmp_path / "map",
        "--workers",
        1,
        "--json",
    )
    assert res.exit_code == 0, res.output
    manifest, poses, outputs = read_run(tmp_path / "map" / "run")
    assert poses["drive"].tolist() == ["a/b"] * 12 + ["a__b"] * 12
    for drive in ("a/b", "a__b"):
        mine = poses["drive"] == drive
        assert outputs["descriptor_normalized"][mine].tobytes() == _descriptors_of(onnx, root / drive).tobytes(), drive
    # run.json maps each drive to its own shards, and each shard back to its drive
    assert set(manifest["drives"]) == {"a/b", "a__b"}
    owned = {name: drive for drive, info in manifest["drives"].items() for name in info["shards"]}
    assert len(owned) == 2 and all(manifest["shards"][n]["drive"] == d for n, d in owned.items())
    assert {p.stem for p in (tmp_path / "map" / "run" / "shards").iterdir()} == set(owned)
    info = json.loads((tmp_path / "map" / "map.json").read_text())
    assert info["drives"] == ["a/b", "a__b"] and info["windows"] == 24 == json.loads(res.stdout)["windows"]
    with np.load(tmp_path / "map" / "poses.npz") as z:
        assert sorted(set(z["drive"].tolist())) == ["a/b", "a__b"]


def test_a_failed_run_leaves_the_previous_run_as_it_was(town, tmp_path):
    """A corrupt scan, or one with the wrong column count, fails the run with one error naming the file
    and leaves no run.json or shard of the failed attempt: the previous run stays as it was."""
    data, onnx = town
    root, out = _fleet(tmp_path / "fleet", data, d1="database", d2="queries"), tmp_path / "out"
    bad = _last_scan(root / "d2")  # in d2's last shard: d1's shards finish before it fails
    good = bad.read_bytes()
    bad.write_bytes(good[:70])  # a truncated .npy
    args = ("run", "--onnx", onnx, "--data", root, "--out", out, "--workers", 1, "--shard-windows", 5)
    one_error_line(invoke(*args), str(bad.resolve()))
    assert not (out / MANIFEST).exists() and not _shard_files(out)
    np.save(bad, np.zeros((9, 4), np.float32))  # TransLoc .npy scans have 5 columns
    one_error_line(invoke(*args), str(bad.resolve()), "4 columns")
    assert not (out / MANIFEST).exists() and not _shard_files(out)
    bad.write_bytes(good)
    res = invoke(*args)
    assert res.exit_code == 0, res.output
    assert "finished by an earlier attempt that failed, reused" in res.output  # d1's, staged by the first
    manifest, shards = (out / MANIFEST).read_bytes(), _shard_files(out)
    assert len(shards) == 6 and not (out / ".staging").exists()
    # a run over more drives, one of them bad, fails and leaves that run as it was
    _fleet(root, data, d3="database", d4="queries")
    worse = _last_scan(root / "d4")
    worse.write_bytes(worse.read_bytes()[:70])
    one_error_line(invoke(*args), str(worse.resolve()))
    assert (out / MANIFEST).read_bytes() == manifest and _shard_files(out) == shards
    assert sorted(set(read_run(out)[1]["drive"].tolist())) == ["d1", "d2"]


def test_a_missing_shard_is_named_when_read_and_recomputed_on_resume(town, tmp_path):
    data, onnx = town
    out = tmp_path / "out"
    run_sequential(onnx, data, out, shard_windows=5)
    name = sorted(json.loads((out / MANIFEST).read_text())["shards"])[1]
    victim = out / "shards" / f"{name}.parquet"
    before = victim.read_bytes()
    victim.unlink()
    with pytest.raises(InputError) as caught:
        read_run(out)
    assert name in str(caught.value) and "is missing" in str(caught.value)
    assert "`radaredge run` with the same arguments" in str(caught.value)
    res = invoke("run", "--onnx", onnx, "--data", data, "--out", out)
    assert res.exit_code == 0, res.output
    assert "1 shard(s) named in run.json but missing, recomputed" in res.output and name in res.output
    assert victim.read_bytes() == before
    assert len(read_run(out)[1]["frame"]) == 24


def test_a_resumed_run_follows_the_data_as_it_is_now(town, tmp_path):
    """A drive removed from the data leaves the run; a drive whose scans changed is recomputed."""
    data, onnx = town
    root, out = _fleet(tmp_path / "fleet", data, d1="database", d2="queries", d3="database"), tmp_path / "out"
    run_sequential(onnx, root, out, shard_windows=5)
    shutil.rmtree(root / "d2")
    scan = sorted((root / "d3" / "scans").iterdir())[4]
    np.save(scan, np.load(scan)[:-3])  # three points fewer in one scan of d3
    res = invoke("run", "--onnx", onnx, "--data", root, "--out", out, "--workers", 1)
    assert res.exit_code == 0, res.output
    assert "1 drive(s) no longer in the data, their shards dropped: d2" in res.output
    assert "1 drive(s) whose scans or gps.csv changed, their shards recomputed: d3" in res.output
    manifest, poses, outputs = read_run(out)
    assert sorted(set(poses["drive"].tolist())) == ["d1", "d3"] and set(manifest["drives"]) == {"d1", "d3"}
    assert {p.stem for p in (out / "shards").iterdir()} == set(manifest["shards"])  # d2's and d3's old files gone
    fresh = run_sequential(onnx, root, tmp_path / "fresh", shard_windows=5)
    assert fresh.windows == 24
    _, _, want = read_run(tmp_path / "fresh")
    assert outputs["descriptor_normalized"].tobytes() == want["descriptor_normalized"].tobytes()
    # --json carries the same account
    again = json.loads(invoke("run", "--onnx", onnx, "--data", root, "--out", out, "--json").stdout)
    assert again["computed_shards"] == 0 and again["changes"]["removed"] == [] and again["changes"]["changed"] == []


def test_a_run_json_of_the_older_format_is_read_and_recomputed_on_resume(town, tmp_path):
    data, onnx = town
    out = tmp_path / "out"
    run_sequential(onnx, data, out, shard_windows=5)
    _, poses, outputs = read_run(out)
    # what radaredge wrote before drive fingerprints: no format or drives, shards named <drive>-<n>
    new = json.loads((out / MANIFEST).read_text())
    old = {k: v for k, v in new.items() if k not in ("format", "drives")}
    old["shards"] = {}
    for name, entry in new["shards"].items():
        old_name = f"{entry['drive'].replace('/', '__')}-{entry['first'] // 5:05d}"
        (out / "shards" / f"{name}.parquet").rename(out / "shards" / f"{old_name}.parquet")
        old["shards"][old_name] = entry
    (out / MANIFEST).write_text(json.dumps(old))
    assert read_run(out)[2]["descriptor_normalized"].tobytes() == outputs["descriptor_normalized"].tobytes()
    report = run_sequential(onnx, data, out)
    assert report.computed_shards == 6 and report.changes["older_format"]
    assert json.loads((out / MANIFEST).read_text()) == new
    assert {p.stem for p in (out / "shards").iterdir()} == set(new["shards"])
    # a manifest of a newer format is refused, not misread
    (out / MANIFEST).write_text(json.dumps({**new, "format": 99}))
    with pytest.raises(InputError, match="newer radaredge"):
        read_run(out)


def test_threads_and_workers_beyond_the_cpus_are_cut_down_with_a_warning(town, tmp_path):
    """`run --threads 64` on a 2-core machine waited for ever for a Ray actor that could not start."""
    data, onnx = town
    many = max(64, 4 * available_cpus())
    with _deadline(240):
        res = invoke(
            "run",
            "--onnx",
            onnx,
            "--data",
            data / "database",
            "--out",
            tmp_path / "out",
            "--threads",
            many,
            "--workers",
            many,
        )
    assert res.exit_code == 0, res.output
    warned = [ln for ln in res.output.splitlines() if ln.startswith("warning:")]
    assert any(f"--threads {many}: more than the" in w for w in warned), res.output
    assert any(f"--workers {many}: more than the" in w for w in warned), res.output
    assert len(read_run(tmp_path / "out")[1]["frame"]) == 12
    with _deadline(240):
        res = invoke(
            "map",
            "build",
            "--model",
            "tdfanet-tiny",
            "--config",
            TINY_CARD,
            "--onnx",
            onnx,
            "--drives",
            data / "database",
            "--out",
            tmp_path / "map",
            "--threads",
            many,
            "--workers",
            many,
        )
    assert res.exit_code == 0, res.output
    assert f"warning: --threads {many}: more than the" in res.output
    res = invoke("map", "query", "--map", tmp_path / "map", "--drive", data / "queries", "--threads", many)
    assert res.exit_code == 0, res.output
    assert f"warning: --threads {many}: more than the {available_cpus()} CPU(s)" in res.output
