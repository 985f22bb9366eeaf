"""A model family declares what every verb needs in its own package (radaredge.registry,
radaredge.models.spec): a family registered from outside radaredge/ is exported, checked and
timed by the verbs unchanged, and no verb keeps a table keyed by family names."""

from __future__ import annotations

import importlib
import pkgutil
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import pytest

import radaredge
from radaredge import api
from radaredge.cards import load_card
from radaredge.errors import ConfigError
from radaredge.registry import registered

TOY = Path(__file__).parent / "toy"
sys.path.insert(0, str(TOY))
import toy_family  # noqa: E402  (registers the family "toy")


def test_a_family_registered_outside_the_package_runs_export_parity_and_bench(tmp_path):
    card = TOY / "toy.yaml"
    out = tmp_path / "toy.onnx"
    exported = api.export(card, out)
    assert exported.path == out and out.with_suffix(".json").is_file()
    report = api.parity(card, out, cases=6)
    assert report, "\n".join(report.lines())
    judged = report.graphs["toy"]
    assert [c.name for c in judged.comparators] == ["descriptor"]
    bench = api.bench(card, onnx=out, runs=2, threads=1, reference=True, openvino=False)
    rows = {r.backend: r for r in bench.tasks["toy"].rows}
    assert {"torch reference", "torch export", "onnxruntime"} <= set(rows) and all(rows.values())


def test_the_family_s_comparators_decide_the_verdict(tmp_path, monkeypatch):
    """Parity reads the tolerances from the family's spec: an impossible budget fails."""
    from radaredge.models.comparators import Dense

    card = TOY / "toy.yaml"
    out = tmp_path / "toy.onnx"
    api.export(card, out)
    off = replace(
        toy_family.SPEC.graphs[0],
        judges=lambda c: (Dense("descriptor", atol=1e-4, rtol=0.0),),
        run_reference=lambda m, f, trace=None: {"descriptor": m(toy_family._points(f)) + 1e-3},
    )
    monkeypatch.setattr(toy_family, "SPEC", replace(toy_family.SPEC, graphs=(off,)))
    report = api.parity(card, out, cases=2)
    assert not report and "FAILED" in "\n".join(report.lines())


def test_card_sections_come_from_the_family(tmp_path):
    text = (TOY / "toy.yaml").read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("toy: {hidden: 12}", "toi: {hidden: 12}"))
    with pytest.raises(ConfigError, match=r"'toi' \(did you mean 'toy'\?\)"):
        load_card(str(bad))
    assert load_card(str(TOY / "toy.yaml")).section("toy", toy_family.ToyConfig).hidden == 12


def test_a_family_without_evaluation_or_recipe_says_so(tmp_path):
    card = TOY / "toy.yaml"
    with pytest.raises(ConfigError, match="no evaluation"):
        api.evaluate(card, tmp_path / "toy.onnx", data=tmp_path)
    with pytest.raises(ConfigError, match="no training recipe"):
        api.train(card, tmp_path, tmp_path / "run")


def _modules_outside_the_families():
    families = set(registered())
    for info in pkgutil.walk_packages(radaredge.__path__, "radaredge."):
        parts = info.name.split(".")
        if parts[:2] == ["radaredge", "models"] and len(parts) > 2 and parts[2] in families:
            continue  # a family's own package holds its knowledge
        if info.name == "radaredge.registry":
            continue  # the registry itself
        yield info.name


def test_no_verb_keeps_a_table_keyed_by_family_names():
    families = set(registered())
    assert {"tdfanet", "maffnet", "des4pos", "toy"} <= families
    found = []
    for name in _modules_outside_the_families():
        module = importlib.import_module(name)
        for attr, value in vars(module).items():
            if isinstance(value, dict) and families & {k for k in value if isinstance(k, str)}:
                found.append(f"{name}.{attr}: {sorted(families & set(value))}")
    assert not found, f"tables keyed by model family names outside radaredge/models/<family>/: {found}"


def test_the_table_check_finds_a_table(monkeypatch):
    """The check above can fail: a dict keyed by a family name in a verb's module is found."""
    import radaredge.eval.tasks as tasks

    monkeypatch.setattr(tasks, "PER_MODEL", {"maffnet": 1}, raising=False)
    with pytest.raises(AssertionError, match="eval.tasks.PER_MODEL"):
        test_no_verb_keeps_a_table_keyed_by_family_names()


def test_families_are_discovered_and_import_no_torch():
    code = (
        "import sys, radaredge; from radaredge.registry import registered; print(registered(), 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "['des4pos', 'maffnet', 'tdfanet'] False"
