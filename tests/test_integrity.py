"""Integrity checked, not trusted: every exported graph records the hash of its own contents
(``radaredge.content_sha256``, :mod:`radaredge.runtime.integrity`), which the runtime recomputes
from the file whenever it loads a graph (map build and query, eval, run, inspect), cached per
file identity; a graph with one initializer edited is refused, and ``inspect`` shows it. The
card embedded in a graph is checked against the graph's inputs."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
import time
import warnings
from pathlib import Path

import numpy as np
import onnx
import pytest
from conftest import TINY_CARD, invoke, one_error_line
from onnx import numpy_helper

from radaredge import runtime
from radaredge.errors import InputError

CONTENT_SHA256 = "radaredge.content_sha256"
EDITED = "its contents do not match the hash recorded at export: the graph was edited after export; re-export it"


def _hash(path):
    """The content hash of the file at ``path`` (imported here, so that each test fails on its own
    where the runtime has no content hashes)."""
    from radaredge.runtime import integrity

    return integrity.content_hash(path)


def _props(path) -> dict[str, str]:
    return {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}


def _edit_one_weight(src: Path, dst: Path, delta: float = 0.05) -> Path:
    """``src`` with one float of one weight initializer changed, saved to ``dst`` (its metadata,
    recorded content hash included, untouched)."""
    proto = onnx.load(str(src))
    init = max(
        (t for t in proto.graph.initializer if t.data_type == onnx.TensorProto.FLOAT),
        key=lambda t: int(np.prod(t.dims)),
    )
    values = numpy_helper.to_array(init).copy()
    values.flat[0] += delta
    init.CopyFrom(numpy_helper.from_array(values, init.name))
    onnx.save(proto, str(dst))
    return dst


def _edit_card(src: Path, dst: Path, old: str, new: str, restamp: bool = False, drop_hash: bool = False) -> Path:
    """``src`` with ``old`` replaced by ``new`` in its embedded card; ``restamp`` records the
    edited graph's own content hash (a graph that verifies but whose card disagrees with it),
    ``drop_hash`` removes the content hash (an export from before content hashes)."""
    proto = onnx.load(str(src))
    for prop in proto.metadata_props:
        if prop.key == "radaredge.card":
            assert old in prop.value
            prop.value = prop.value.replace(old, new)
    if drop_hash:
        kept = [(p.key, p.value) for p in proto.metadata_props if p.key != CONTENT_SHA256]
        del proto.metadata_props[:]
        for k, v in kept:
            proto.metadata_props.add(key=k, value=v)
    if restamp:
        from radaredge.exporting.graphs import stamp_content_hash

        stamp_content_hash(proto)
    onnx.save(proto, str(dst))
    return dst


def _age(path: Path, seconds: float = 120.0) -> None:
    """Set the file's modification time ``seconds`` into the past (out of the racy window)."""
    t = time.time_ns() - int(seconds * 1e9)
    os.utime(path, ns=(t, t))


# ----------------------------------------------------------------------------- the hash


def test_an_unedited_export_records_its_content_hash_and_verifies(tiny_export):
    _, _, path, debug = tiny_export
    for graph in (path, debug):
        recorded = _props(graph)[CONTENT_SHA256]
        found = _hash(graph)
        assert found.status == "verified" and found.recorded == found.computed == recorded
        m = runtime.load(graph)
        assert m.content.status == "verified" and m.content_sha256 == recorded and m.card_findings == []
    assert _props(debug)[CONTENT_SHA256] != _props(path)[CONTENT_SHA256]  # each graph its own
    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["content_sha256"] == _props(path)[CONTENT_SHA256]
    info = runtime.inspect_export(path)
    assert info["ok"] and info["findings"] == []
    graph = info["graphs"][0]
    assert graph["content_sha256"] == _props(path)[CONTENT_SHA256]
    assert graph["integrity"].startswith("verified") and graph["findings"] == []
    res = invoke("inspect", path, "--json")
    assert res.exit_code == 0 and json.loads(res.stdout)["ok"], res.output


def test_the_hash_covers_weights_nodes_and_radaredge_metadata_but_not_the_doc_string_or_other_tools_metadata(
    tiny_export, tmp_path
):
    _, _, path, _ = tiny_export

    def edited(name, change):
        proto = onnx.load(str(path))
        change(proto)
        onnx.save(proto, str(tmp_path / name))
        return _hash(tmp_path / name).status

    def set_prop(key, value):
        def change(proto):
            for p in proto.metadata_props:
                if p.key == key:
                    p.value = value

        return change

    def reorder(proto):
        props = [(p.key, p.value) for p in proto.metadata_props][::-1]
        del proto.metadata_props[:]
        for k, v in props:
            proto.metadata_props.add(key=k, value=v)

    assert edited("doc.onnx", lambda p: setattr(p, "doc_string", "described again")) == "verified"
    assert edited("tool.onnx", lambda p: p.metadata_props.add(key="converted_by", value="some tool")) == "verified"
    assert edited("reordered.onnx", reorder) == "verified"
    assert edited("weights-hash.onnx", set_prop("radaredge.weights_sha256", "0" * 64)) == "mismatch"
    assert edited("checks.onnx", set_prop("radaredge.input_errors", "0")) == "mismatch"
    assert edited("node.onnx", lambda p: setattr(p.graph.node[0], "name", "renamed")) == "mismatch"
    assert edited("opset.onnx", lambda p: setattr(p, "ir_version", p.ir_version - 1)) == "mismatch"
    _edit_one_weight(path, tmp_path / "weight.onnx")
    assert _hash(tmp_path / "weight.onnx").status == "mismatch"
    # a hash given twice is not trusted either
    assert (
        edited("twice.onnx", lambda p: p.metadata_props.add(key=CONTENT_SHA256, value=_props(path)[CONTENT_SHA256]))
        == "mismatch"
    )


# ----------------------------------------------------------------------------- an edited graph


@pytest.fixture(scope="module")
def mapped(tmp_path_factory, tiny_export):
    """A tiny place map of one synthetic drive built with the tiny TDFANet graph, the query
    drive, and a copy of the graph with one initializer edited."""
    from radaredge.data.pr_benchmark import make_pr_benchmark

    _, _, onnx_path, _ = tiny_export
    d = tmp_path_factory.mktemp("integrity-map")
    make_pr_benchmark(d / "town", drives=2, frames_per_drive=8, seed=3)
    res = invoke(
        "map",
        "build",
        "--model",
        "tdfanet-tiny",
        "--config",
        TINY_CARD,
        "--onnx",
        onnx_path,
        "--drives",
        d / "town" / "database",
        "--out",
        d / "map",
        "--workers",
        1,
        "--json",
    )
    assert res.exit_code == 0, res.output
    edited = _edit_one_weight(onnx_path, d / "edited.onnx")
    return onnx_path, d / "town", d / "map", edited


def test_a_graph_with_one_initializer_edited_is_refused_by_map_query_eval_and_map_build(mapped, tmp_path):
    good, town, map_dir, edited = mapped
    # the edit changes what the graph computes, and the metadata still claims the map's weights
    assert _props(edited)["radaredge.weights_sha256"] == _props(good)["radaredge.weights_sha256"]
    queries = town / "queries"
    one_error_line(
        invoke("map", "query", "--map", map_dir, "--drive", queries, "--onnx", edited), "edited.onnx", EDITED
    )
    with pytest.raises(InputError) as err:
        runtime.load(edited)
    assert str(err.value) == f"{edited}: {EDITED}"
    one_error_line(
        invoke(
            "eval",
            "--model",
            "tdfanet-tiny",
            "--config",
            TINY_CARD,
            "--onnx",
            edited,
            "--map",
            map_dir,
            "--queries",
            queries,
            "--radius",
            25,
            "--no-reference",
        ),
        "edited.onnx",
        EDITED,
    )
    one_error_line(
        invoke(
            "map",
            "build",
            "--model",
            "tdfanet-tiny",
            "--config",
            TINY_CARD,
            "--onnx",
            edited,
            "--drives",
            town / "database",
            "--out",
            tmp_path / "map2",
            "--workers",
            1,
        ),
        "edited.onnx",
        EDITED,
    )
    assert not (tmp_path / "map2" / "map.json").exists()
    # the unedited graph is the map's own
    res = invoke("map", "query", "--map", map_dir, "--drive", queries, "--onnx", good, "--radius", 25, "--json")
    assert res.exit_code == 0, res.output


def test_inspect_shows_an_edited_graph(mapped):
    good, _, _, edited = mapped
    info = runtime.inspect_export(edited)
    graph = info["graphs"][0]
    assert not info["ok"] and len(info["findings"]) == 1 and info["findings"][0].startswith(f"{edited}: ")
    assert graph["integrity"] == (
        f"MISMATCH: {EDITED} (recorded {_props(good)[CONTENT_SHA256]}, its contents hash to {_hash(edited).computed})"
    )
    assert graph["content_sha256"] == _props(good)[CONTENT_SHA256]
    assert any(EDITED in f for f in graph["findings"])
    res = invoke("inspect", edited)
    assert "MISMATCH" in res.output and EDITED in res.output, res.output
    res = invoke("inspect", edited, "--json")
    doc = json.loads(res.stdout)  # one valid document, the finding in it
    assert doc["ok"] is False and EDITED in doc["findings"][0]


# ----------------------------------------------------------------------------- the embedded card


def test_a_card_that_says_two_frames_on_a_graph_that_takes_three_is_flagged_and_refused(tiny_export, tmp_path):
    _, _, path, _ = tiny_export
    expect = "the card says frames: 2, the graph takes 3 point frame(s) (points_0, points_1, points_2)"
    # the card edited after export: the contents no longer verify, and the card disagrees
    stale = _edit_card(path, tmp_path / "stale.onnx", "\nframes: 3\n", "\nframes: 2\n")
    info = runtime.inspect_export(stale)
    assert not info["ok"] and info["graphs"][0]["integrity"].startswith("MISMATCH")
    assert any(expect in f for f in info["findings"]), info["findings"]
    with pytest.raises(InputError, match="stale.onnx: its contents do not match"):
        runtime.load(stale)
    # a graph that verifies, or records no hash, whose card disagrees with it
    for name, how in (("restamped.onnx", {"restamp": True}), ("older.onnx", {"drop_hash": True})):
        bad = _edit_card(path, tmp_path / name, "\nframes: 3\n", "\nframes: 2\n", **how)
        info = runtime.inspect_export(bad)
        assert not info["ok"] and info["findings"] == [
            f"{bad}: its embedded card disagrees with the graph: {expect}"
        ], info["findings"]
        assert info["graphs"][0]["integrity"].startswith("verified" if how.get("restamp") else "not recorded")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            with pytest.raises(InputError) as err:
                runtime.load(bad)
        assert str(err.value) == f"{bad}: its embedded card disagrees with the graph: {expect}; re-export it"
        res = invoke("inspect", bad)
        assert expect in res.output, res.output
        doc = json.loads(invoke("inspect", bad, "--json").stdout)
        assert doc["ok"] is False and expect in doc["findings"][0]


def test_a_card_of_another_name_is_flagged(tiny_export, tmp_path):
    _, _, path, _ = tiny_export
    bad = _edit_card(path, tmp_path / "renamed.onnx", "name: tdfanet-tiny", "name: tdfanet-other", restamp=True)
    info = runtime.inspect_export(bad)
    assert info["findings"] == [
        f"{bad}: its embedded card disagrees with the graph: its metadata names model "
        f"'tdfanet-tiny', its card 'tdfanet-other'"
    ]


# ----------------------------------------------------------------------------- graphs from before content hashes


def test_a_graph_exported_before_content_hashes_is_accepted_with_a_warning(tiny_export, tmp_path):
    _, _, path, _ = tiny_export
    older = _edit_card(path, tmp_path / "older.onnx", "\nframes: 3\n", "\nframes: 3\n", drop_hash=True)
    assert CONTENT_SHA256 not in _props(older)
    with pytest.warns(RuntimeWarning, match="older.onnx: exported before radaredge recorded content hashes"):
        m = runtime.load(older)
    assert m.content.status == "not recorded" and m.content.recorded is None
    info = runtime.inspect_export(older)
    assert info["ok"] and info["graphs"][0]["content_sha256"] is None
    assert info["graphs"][0]["integrity"].startswith("not recorded")


# ----------------------------------------------------------------------------- the cache


def test_the_hash_is_computed_once_per_file_identity(tiny_export, tmp_path):
    _, _, path, _ = tiny_export
    copy = tmp_path / "copy.onnx"
    shutil.copyfile(path, copy)
    _age(copy)
    from radaredge.runtime import integrity

    integrity.clear_cache()
    runtime.load(copy)
    runtime.load(copy)
    runtime.inspect_export(copy)
    stats = integrity.cache_stats()
    assert stats["computed"] == 1 and stats["cached"] == 2, stats
    _age(copy, 60.0)  # another modification time: hashed again
    runtime.load(copy)
    assert integrity.cache_stats()["computed"] == 2
    # an edit of the same size keeping the modification time would keep the identity, so a file
    # modified within the racy window is hashed at every load
    fresh = tmp_path / "fresh.onnx"
    shutil.copyfile(path, fresh)
    runtime.load(fresh)
    runtime.load(fresh)
    assert integrity.cache_stats()["computed"] == 4


# ----------------------------------------------------------------------------- int8 copies and bundles


def test_int8_copies_record_their_own_content_hash(tmp_path):
    import radaredge

    res = radaredge.export(TINY_CARD, tmp_path / "t.onnx", quantize="int8", calibration_windows=2)
    int8 = tmp_path / "t.int8.onnx"
    assert int8.is_file(), res
    props, fp32 = _props(int8), _props(tmp_path / "t.onnx")
    assert props[CONTENT_SHA256] != fp32[CONTENT_SHA256]
    assert runtime.load(int8).content.status == "verified"


def test_a_bundle_manifest_records_each_parts_content_hash(tiny_export, tmp_path):
    """A bundle of two graphs (the tiny graph and its debug copy as parts; a real multi-graph
    export writes its manifest with the same :func:`write_manifest`)."""
    from radaredge import artifacts
    from radaredge.exporting.graphs import GraphExport, write_manifest
    from radaredge.models import model_spec
    from radaredge.runtime.bundle import read_manifest

    card, _, path, debug = tiny_export
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    graphs = {}
    for name, src in (("main", path), ("traced", debug)):
        dst = bundle / f"{name}.onnx"
        shutil.copyfile(src, dst)
        graphs[name] = GraphExport(dst, dst.with_suffix(".json"), dst.stat().st_size, {}, runtime.load(dst).info)
    write_manifest(card, model_spec(card), artifacts.Bundle(bundle, tuple(graphs)), graphs, 18, "0" * 64)
    manifest = json.loads((bundle / "bundle.json").read_text())
    for part, entry in manifest["parts"].items():
        assert entry["content_sha256"] == _props(bundle / entry["onnx"])[CONTENT_SHA256], part
    assert runtime.inspect_export(bundle)["ok"]
    # one part replaced by an edited copy of itself, then by another (verified) graph
    _edit_one_weight(path, bundle / "main.onnx")
    info = runtime.inspect_export(bundle)
    found = [f for f in info["findings"] if f.startswith(str(bundle / "main.onnx"))]
    assert not info["ok"] and len(found) == 2, info["findings"]
    assert EDITED in found[0] and "parts.main: the contents of main.onnx hash to" in found[1]
    shutil.copyfile(debug, bundle / "main.onnx")
    info = runtime.inspect_export(bundle)
    assert len(info["findings"]) == 1 and "the file was replaced or edited after export" in info["findings"][0]
    with pytest.raises(InputError, match="parts.main: the contents of main.onnx .* the file was replaced or edited"):
        read_manifest(bundle / "bundle.json")


# ----------------------------------------------------------------------------- torch- and onnx-free


def test_the_runtime_checks_without_torch_or_onnx(tiny_export, tmp_path):
    _, _, path, _ = tiny_export
    edited = _edit_one_weight(path, tmp_path / "edited.onnx")
    script = textwrap.dedent(f"""
        import sys
        sys.modules["torch"] = None
        sys.modules["onnx"] = None
        from radaredge import runtime
        from radaredge.errors import InputError
        assert runtime.load({str(path)!r}).content.status == "verified"
        try:
            runtime.load({str(edited)!r})
        except InputError as exc:
            print(exc)
        print(runtime.inspect_export({str(edited)!r})["ok"])
    """)
    res = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert res.stdout.splitlines() == [f"{edited}: {EDITED}", "False"]


def test_eval_checks_the_frames_and_outputs_the_embedded_card_implies(tiny_export):
    """The model family's signature of the embedded card (torch side: ``eval`` and ``map build``)."""
    from types import SimpleNamespace

    from radaredge.eval.places import check_export

    card, _, path, debug = tiny_export
    for graph in (path, debug):  # a debug copy's extra debug.<intermediate> outputs are fine
        check_export(card, runtime.load(graph))
    good = runtime.load(path)
    other = SimpleNamespace(
        card=good.card,
        path=Path("other.onnx"),
        info=good.info,
        frames=good.frames,
        features=good.features,
        output_names=[n for n in good.output_names if n != "descriptor_normalized"],
    )
    with pytest.raises(
        InputError,
        match="other.onnx: its embedded card disagrees with the graph: the card's tdfanet graph takes point frames",
    ):
        check_export(card, other)
