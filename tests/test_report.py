"""docs/results.md is what `python bench/report.py` writes from bench/results/*.json, and the README shows its table."""

from __future__ import annotations

import importlib.util
import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _report():
    spec = importlib.util.spec_from_file_location("bench_report", ROOT / "bench" / "report.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_results_page_regenerates_identically():
    assert (ROOT / "docs" / "results.md").read_text(encoding="utf-8") == _report().render(), (
        "docs/results.md is out of date: run python bench/report.py"
    )


def test_readme_holds_the_generated_table():
    assert _report().readme_table() in (ROOT / "README.md").read_text(encoding="utf-8")


def test_readme_holds_the_generated_mapping_table():
    assert _report().readme_mapping_table() in (ROOT / "README.md").read_text(encoding="utf-8")


def test_mapping_tables_follow_the_json(tmp_path):
    """The README's mapping table and the selection section are made from their results files."""
    report = _report()
    results = tmp_path / "results"
    results.mkdir()
    d = json.loads((ROOT / "bench" / "results" / "mapping_sequences.json").read_text(encoding="utf-8"))
    d["sequences"]["hololens"]["fscore"] = 0.987
    (results / "mapping_sequences.json").write_text(json.dumps(d), encoding="utf-8")
    assert "| HoloLens walk (94 frames) | exact | **0.987** |" in report.readme_mapping_table(results)
    selection = {
        "choose_on": "hololens",
        "fields": {
            "gp.lengthscale": {
                "values": {
                    "32.0": {"7scenes": {"fscore": 0.402}, "hololens": {"fscore": 0.303}},
                    "64.0": {"7scenes": {"fscore": 0.412}, "hololens": {"fscore": 0.351}},
                },
                "chosen": "64.0",
            }
        },
    }
    text = report.section_mapping_selection(selection)
    assert (
        "| `gp.lengthscale` | **64.0** | HoloLens walk | 0.412 | 0.351 |" in text
        and "| `gp.lengthscale` | 32.0 | HoloLens walk | 0.402 | 0.303 |" in text
    )


def test_every_table_names_its_run():
    text = (ROOT / "docs" / "results.md").read_text(encoding="utf-8")
    sections = text.split("\n## ")[1:]
    assert len(sections) >= 10
    for section in sections:
        assert re.search(r"\*`python bench/\w+\.py[^`]*`; run .+?; machine: .+?; load average", section), section[:80]


def test_tables_follow_the_json(tmp_path):
    """A number changed in a results file changes the page: nothing is copied by hand."""
    report = _report()
    results = tmp_path / "results"
    results.mkdir()
    d = json.loads((ROOT / "bench" / "results" / "eval_7scenes.json").read_text(encoding="utf-8"))
    row = next(r for r in d["uniform"] if r["method"] == "gp_default" and r["level"] == 50)
    row["rmse"] = 123.0
    (results / "eval_7scenes.json").write_text(json.dumps(d), encoding="utf-8")
    assert "| **GP default** (`DepthGPConfig()`) | 123 / " in report.readme_table(results)
    assert "123 / " in report.render(results)


def test_no_development_history_in_the_docs():
    """No numbered session labels or dated lab notes in the README, docs and results."""
    files = [
        ROOT / "README.md",
        ROOT / "CHANGELOG.md",
        *(ROOT / "docs").glob("*.md"),
        *(ROOT / "bench" / "results").glob("*.json"),
    ]
    for path in files:
        if path.is_file():
            text = path.read_text(encoding="utf-8")
            assert not re.search(r"\b[Ss]essions? \d+|\bsession-\d+", text), path.name
