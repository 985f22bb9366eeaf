"""The bad-input catalogue, by class: outputs that would destroy an input or a previous result.

Every output-path argument of every command is tried against every input path of that command
(the same path, through a symlink, through a hard link and spelled with ``..``): each is refused
with exit code 2 and one ``error:`` line, before any work, and every file of the inputs is
byte-for-byte what it was. A new command inherits the class by adding a row to ``COMMANDS``.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import pytest
import torch
from conftest import TINY_CARD, invoke

from radaredge.config import refuse_overwriting_inputs, same_path
from radaredge.errors import ConfigError
from radaredge.training.run import prepare_run_output

HERE = Path(__file__).parent
DES4POS_TINY = HERE / "cards" / "des4pos-tiny.yaml"
OPENPCDET = HERE / "fixtures" / "openpcdet"


@pytest.fixture(scope="module")
def inputs(tmp_path_factory, tiny_export):
    """One directory of valid inputs every command below accepts."""
    from radaredge.data.pr_benchmark import make_pr_benchmark

    d = tmp_path_factory.mktemp("outputs")
    _, model, onnx_path, _ = tiny_export
    shutil.copy(onnx_path, d / "tiny.onnx")
    shutil.copy(TINY_CARD, d / "card.yaml")
    shutil.copy(DES4POS_TINY, d / "des4pos.yaml")
    torch.save(model.state_dict(), d / "good.pth")
    make_pr_benchmark(d / "town", drives=2, frames_per_drive=6, seed=0)
    shutil.copytree(OPENPCDET, d / "openpcdet")
    return d


def _fingerprint(root: Path) -> dict:
    """Every file under ``root`` by relative path, with its bytes' sha256."""
    return {
        str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
        for p in sorted(root.rglob("*"))
        if p.is_file()
    }


# command id -> (the arguments with {OUT} for the output and {f} for the inputs' directory,
#                the output option, {input option: its path relative to {f}})
TINY = ["--model", "tdfanet-tiny", "--config", "{f}/card.yaml"]
EVAL = [
    "eval",
    *TINY,
    "--onnx",
    "{f}/tiny.onnx",
    "--database",
    "{f}/town/database",
    "--queries",
    "{f}/town/queries",
    "--checkpoint",
    "{f}/good.pth",
]
EVAL_INPUTS = {
    "--onnx": "tiny.onnx",
    "--database": "town/database",
    "--queries": "town/queries",
    "--config": "card.yaml",
    "--checkpoint": "good.pth",
}
COMMANDS = {
    "export": (
        ["export", *TINY, "--checkpoint", "{f}/good.pth", "--output", "{OUT}"],
        "--output",
        {"--config": "card.yaml", "--checkpoint": "good.pth"},
    ),
    "export-calibrated": (
        ["export", *TINY, "--quantize", "int8", "--calibration", "{f}/town/database/drive-00", "--output", "{OUT}"],
        "--output",
        {"--calibration": "town/database/drive-00"},
    ),
    "bench": (
        [
            "bench",
            *TINY,
            "--onnx",
            "{f}/tiny.onnx",
            "--checkpoint",
            "{f}/good.pth",
            "--runs",
            "1",
            "--no-reference",
            "--save",
            "{OUT}",
        ],
        "--save",
        {"--onnx": "tiny.onnx", "--config": "card.yaml", "--checkpoint": "good.pth"},
    ),
    "eval-report": ([*EVAL, "--report", "{OUT}"], "--report", EVAL_INPUTS),
    "eval-plot": ([*EVAL, "--plot", "{OUT}"], "--plot", EVAL_INPUTS),
    "eval-report-dir": ([*EVAL, "--report-dir", "{OUT}"], "--report-dir", EVAL_INPUTS),
    "train": (
        ["train", *TINY, "--data", "{f}/town", "--checkpoint", "{f}/good.pth", "--output", "{OUT}"],
        "--output",
        {"--data": "town", "--checkpoint": "good.pth", "--config": "card.yaml"},
    ),
    "card-from-openpcdet": (
        ["card", "from-openpcdet", "{f}/openpcdet/maffnet_vod.yaml", "--out", "{OUT}"],
        "--out",
        {"CONFIG": "openpcdet/maffnet_vod.yaml", "_BASE_CONFIG_": "openpcdet/vod_dataset_radar.yaml"},
    ),
    "card-from-openpcdet-dataset": (
        [
            "card",
            "from-openpcdet",
            "{f}/openpcdet/maffnet_vod.yaml",
            "--dataset-config",
            "{f}/openpcdet/tj4d_dataset_radar.yaml",
            "--out",
            "{OUT}",
        ],
        "--out",
        {"--dataset-config": "openpcdet/tj4d_dataset_radar.yaml"},
    ),
    "make-city": (
        ["make-city", "--model", "des4pos-tiny", "--config", "{f}/des4pos.yaml", "--out", "{OUT}"],
        "--out",
        {"--config": "des4pos.yaml"},
    ),
    "run": (
        ["run", "--onnx", "{f}/tiny.onnx", "--data", "{f}/town/database", "--out", "{OUT}"],
        "--out",
        {"--onnx": "tiny.onnx", "--data": "town/database"},
    ),
    "map-build": (
        ["map", "build", *TINY, "--onnx", "{f}/tiny.onnx", "--drives", "{f}/town/database", "--out", "{OUT}"],
        "--out",
        {"--onnx": "tiny.onnx", "--drives": "town/database", "--config": "card.yaml"},
    ),
}
SPELLINGS = ("same", "symlink", "hardlink", "dotdot")
CASES = [
    (cmd, source, how) for cmd, (_, _, sources) in COMMANDS.items() for source in sources.values() for how in SPELLINGS
]


def _spell(inputs: Path, workdir: Path, source: str, how: str) -> str:
    """The input ``source`` named as an output path: itself, a symlink or hard link to it in the
    working directory, or its path through a ``..``."""
    target = inputs / source
    if how == "same":
        return str(target)
    if how == "symlink":
        link = workdir / f"link-{target.name}"
        link.symlink_to(target)
        return str(link)
    if how == "hardlink":
        if target.is_dir():  # directories have no hard links: the path through '.'
            return str(target.parent / "." / target.name)
        link = workdir / f"hard-{target.name}"
        os.link(target, link)
        return str(link)
    return str(target.parent / ".." / target.parent.name / target.name)


@pytest.mark.parametrize("command, source, how", CASES, ids=[f"{c}-{s.replace('/', '.')}-{h}" for c, s, h in CASES])
def test_an_output_never_replaces_an_input(inputs, tmp_path, monkeypatch, command, source, how):
    monkeypatch.chdir(tmp_path)
    args, option, _ = COMMANDS[command]
    out = _spell(inputs, tmp_path, source, how)
    before, here = _fingerprint(inputs), set(tmp_path.iterdir())
    res = invoke(*[a.replace("{f}", str(inputs)).replace("{OUT}", out) for a in args])
    lines = [ln for ln in res.stderr.splitlines() if ln.strip()]
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output and len(lines) == 1 and lines[0].startswith("error:"), res.output
    assert option in lines[0] or "--output" in lines[0], lines[0]
    assert _fingerprint(inputs) == before, "an input changed"
    assert set(tmp_path.iterdir()) == here, "a file was left behind"


def test_two_outputs_of_one_command_are_refused(inputs, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    args = [a.replace("{f}", str(inputs)) for a in EVAL]
    res = invoke(*args, "--report", "r.json", "--plot", "r.json")
    assert res.exit_code == 2 and "--report writes the same file" in res.stderr, res.output
    assert not Path("r.json").exists()


@pytest.mark.parametrize("held", ["best.pth", "last.pth", "train-log.json"])
def test_train_keeps_a_previous_run_unless_told(inputs, tmp_path, monkeypatch, held):
    monkeypatch.chdir(tmp_path)
    run = tmp_path / "run"
    run.mkdir()
    (run / held).write_bytes(b"a previous run's file")
    args = ["train", *[a.replace("{f}", str(inputs)) for a in TINY], "--data", str(inputs / "town"), "--output", "run"]
    res = invoke(*args)
    assert res.exit_code == 2 and "holds a previous run" in res.stderr and "--overwrite" in res.stderr, res.output
    res = invoke(*args, "--resume", "--overwrite")
    assert res.exit_code == 2 and "choose one" in res.stderr, res.output
    assert [p.name for p in run.iterdir()] == [held] and (run / held).read_bytes() == b"a previous run's file"


def test_a_card_name_cannot_leave_the_export_directory(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    card = tmp_path / "evil.yaml"
    card.write_text(TINY_CARD.read_text().replace("name: tdfanet-tiny", "name: ../../escaped"))
    res = invoke("export", "--model", "x", "--config", card)
    assert res.exit_code == 2 and "a card name becomes file names" in res.stderr, res.output
    assert not list(tmp_path.parent.glob("escaped*")) and not (tmp_path / "export").exists()


def test_same_path_follows_links_and_spellings(tmp_path):
    a = tmp_path / "a.txt"
    a.write_text("x")
    (tmp_path / "s").symlink_to(a)
    os.link(a, tmp_path / "h")
    (tmp_path / "d").mkdir()
    for other in (a, tmp_path / "s", tmp_path / "h", tmp_path / "." / "a.txt", tmp_path / "d" / ".." / "a.txt"):
        assert same_path(a, other), other
    assert not same_path(a, tmp_path / "b.txt")
    assert same_path(tmp_path / "new.txt", tmp_path / "." / "new.txt")  # neither exists yet
    with pytest.raises(ConfigError, match="--out .*is the --in input"):
        refuse_overwriting_inputs({"--out": [tmp_path / "x", tmp_path / "s"]}, {"--in": a, "--none": None})
    refuse_overwriting_inputs({"--out": tmp_path / "b.txt"}, {"--in": [a, None]})


def test_overwrite_removes_the_previous_run_before_the_new_one_starts(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    for name in ("best.pth", "last.pth", "train-log.json", "notes.txt"):
        (run / name).write_text("old")
    prepare_run_output(run, resume=False, overwrite=True, inputs={"--data": tmp_path / "data"})
    assert sorted(p.name for p in run.iterdir()) == ["notes.txt"]  # the run's files only
