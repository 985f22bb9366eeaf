"""Atomic outputs: an export appears complete or not at all, a previous good export survives a
failed or interrupted one, and output paths are checked before the work."""

from __future__ import annotations

import hashlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import onnx
import pytest
import torch
import yaml
from conftest import TINY_CARD, invoke

from radaredge import atomic, runtime
from radaredge.exporting.onnx_call import export_onnx


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_atomic_path_renames_on_success_and_keeps_the_old_file_on_failure(tmp_path):
    target = tmp_path / "sub" / "report.json"
    atomic.write_json(target, {"a": 1})
    assert target.read_text().startswith("{") and oct(target.stat().st_mode & 0o777) != "0o600"
    with pytest.raises(RuntimeError):
        with atomic.atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("interrupted")
    assert '"a": 1' in target.read_text()
    assert sorted(p.name for p in target.parent.iterdir()) == ["report.json"]  # no temporary left


def test_staging_commits_every_file_or_none(tmp_path):
    dest = tmp_path / "bundle"
    with atomic.Staging(dest) as stage:
        stage.path(dest / "a.onnx").write_text("a")
        stage.path(dest / "a.json").write_text("b")
    assert not dest.exists()  # closed without commit: nothing left
    with atomic.Staging(dest) as stage:
        stage.path(dest / "a.onnx").write_text("a")
        stage.commit()
    assert [p.name for p in dest.iterdir()] == ["a.onnx"]  # the staging directory is gone


@pytest.fixture
def ctrl_c():
    """SIGINT raising KeyboardInterrupt, as in an interactive shell: a suite started in the
    background by a non-interactive shell (CI) inherits SIGINT ignored."""
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)


def test_held_signals_arrive_when_the_block_ends(ctrl_c, capfd):
    """A SIGINT inside ``signals_held`` waits for the block (code after the signal still runs),
    says the notice once, and then raises KeyboardInterrupt as Ctrl-C does."""
    ran = []
    with pytest.raises(KeyboardInterrupt):
        with atomic.signals_held("held: finishing first"):
            os.kill(os.getpid(), signal.SIGINT)
            os.kill(os.getpid(), signal.SIGINT)
            sum(range(100_000))  # bytecodes where an unheld interrupt would land
            ran.append("rest of the block")
    assert ran == ["rest of the block"]
    assert capfd.readouterr().err.count("held: finishing first") == 1
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_sigterm_unwinds_like_ctrl_c():
    """The CLI's SIGTERM handler raises SystemExit(143), so cleanups run on the way out."""
    before = signal.getsignal(signal.SIGTERM)
    try:
        atomic.exit_on_sigterm()
        with pytest.raises(SystemExit) as exit_:
            os.kill(os.getpid(), signal.SIGTERM)
            sum(range(100_000))
        assert exit_.value.code == 143
    finally:
        signal.signal(signal.SIGTERM, before)


def test_an_interrupt_during_tracing_waits_for_the_tracer(ctrl_c, tmp_path):
    """Ctrl-C while torch traces a graph arrives after the graph is written: raised inside
    torch.export's dispatch modes it aborts the process or turns into an export error."""
    from torch import nn

    class InterruptedDuringTrace(nn.Module):
        def forward(self, x):
            os.kill(os.getpid(), signal.SIGINT)
            return x * 2

    path = tmp_path / "g.onnx"
    with pytest.raises(KeyboardInterrupt):
        export_onnx(InterruptedDuringTrace(), (torch.ones(3),), path, ["x"], ["y"])
    assert onnx.load(str(path)).graph.node  # the tracer finished first


@pytest.fixture(scope="module")
def good(tmp_path_factory):
    """A good tiny export, and its files' hashes."""
    out = tmp_path_factory.mktemp("good") / "model.onnx"
    res = invoke("export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--output", str(out))
    assert res.exit_code == 0, res.output
    return out, {p.name: _sha(p) for p in out.parent.iterdir()}


def test_a_failed_export_leaves_the_previous_one(good, tmp_path):
    out, hashes = good
    res = invoke("export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--output", str(out), "--opset", "10")
    assert res.exit_code == 2
    assert {p.name: _sha(p) for p in out.parent.iterdir()} == hashes


@pytest.mark.parametrize(
    "output, expect",
    [
        ("model.json", "a graph is written to a file ending in .onnx"),
        ("model.int8.onnx", "are the int8 and debug copies"),
        ("model.debug.onnx", "are the int8 and debug copies"),
    ],
)
def test_output_paths_are_checked_first(tmp_path, output, expect):
    res = invoke("export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--output", str(tmp_path / output))
    assert res.exit_code == 2 and expect in res.output, res.output
    assert list(tmp_path.iterdir()) == []


def test_a_directory_output_receives_the_card_name(tmp_path):
    res = invoke("export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--output", f"{tmp_path / 'new'}/")
    assert res.exit_code == 0, res.output
    assert sorted(p.name for p in (tmp_path / "new").iterdir()) == ["tdfanet-tiny.json", "tdfanet-tiny.onnx"]
    (tmp_path / "existing").mkdir()
    res = invoke(
        "export", "--model", "tdfanet-tiny", "--config", str(TINY_CARD), "--output", str(tmp_path / "existing")
    )
    assert res.exit_code == 0 and (tmp_path / "existing" / "tdfanet-tiny.onnx").is_file(), res.output


def test_sigint_never_leaves_a_partial_graph_or_changes_the_previous_one(good, tmp_path):
    """`radaredge export` interrupted (SIGINT) at moments spread over its run, over a previous
    good export of other weights (the card with another seed): the files are the previous export
    byte for byte, or the complete new one as an uninterrupted run writes it (the ``good``
    export); never a mix, a partial file, a graph without its radaredge metadata or a leftover
    staging directory."""
    reseeded = tmp_path / "tdfanet-tiny.yaml"
    reseeded.write_text(yaml.safe_dump({**yaml.safe_load(TINY_CARD.read_text()), "seed": 7}))
    run = [sys.executable, "-m", "radaredge.cli", "export", "--model", "tdfanet-tiny"]
    work, previous = tmp_path / "work", tmp_path / "previous"
    start = time.perf_counter()
    subprocess.run(
        run + ["--config", str(reseeded), "--output", str(previous / "model.onnx")], check=True, capture_output=True
    )
    full = time.perf_counter() - start
    new = good[1]
    old = {p.name: _sha(p) for p in previous.iterdir()}
    assert old.keys() == new.keys() and old != new
    outcomes = []
    for fraction in (0.2, 0.8, 0.95):
        shutil.rmtree(work, ignore_errors=True)
        shutil.copytree(previous, work)
        # SIGINT back to its default in the child: a suite started in the background by a
        # non-interactive shell inherits SIGINT ignored, and the interrupt would never arrive
        proc = subprocess.Popen(
            run + ["--config", str(TINY_CARD), "--output", str(work / "model.onnx")],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )
        time.sleep(full * fraction)
        proc.send_signal(signal.SIGINT)
        proc.communicate(timeout=120)
        now = {p.name: _sha(p) for p in work.iterdir()}
        assert now in (old, new), f"SIGINT at {fraction:.0%} of the export left {sorted(now)}"
        graph = onnx.load(str(work / "model.onnx"), load_external_data=False)
        assert "radaredge.card" in {p.key for p in graph.metadata_props}
        runtime.load(work / "model.onnx")
        outcomes.append("kept" if now == old else "replaced")
    assert "kept" in outcomes  # most moments fall before the commit


def test_a_ctrl_c_while_exiting_prints_no_traceback(tmp_path):
    """A Ctrl-C that lands in an exit handler (here one registered before the command, so it runs
    after the CLI's) is ignored once the command has finished: no 'Exception ignored in atexit
    callback' traceback, and the command's own exit code."""
    script = tmp_path / "late.py"
    script.write_text(
        "import atexit, os, signal, sys, time\nimport radaredge.cli\n"
        "atexit.register(lambda: (os.kill(os.getpid(), signal.SIGINT), time.sleep(0.3)))\n"
        "sys.argv = ['radaredge', 'list']\nradaredge.cli.main()\n"
    )
    res = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0 and "Traceback" not in res.stderr and "KeyboardInterrupt" not in res.stderr, res.stderr
