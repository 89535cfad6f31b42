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


def test_readme_numbers_are_the_generated_blocks():
    """`python bench/report.py` rewrites the README's tables; the README holds what it would write."""
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert _report().render_readme(readme) == readme, "README.md is out of date: run python bench/report.py"


def test_reliability_counts_are_generated_from_the_sweeps_run():
    """docs/reliability.md's sweep table is what `bench/report.py` writes from bench/results/reliability.json."""
    report = _report()
    page = (ROOT / "docs" / "reliability.md").read_text(encoding="utf-8")
    assert report.render_readme(page, blocks={"reliability": report.reliability_table}) == page
    d = json.loads((ROOT / "bench" / "results" / "reliability.json").read_text(encoding="utf-8"))
    assert f"| {sum(d['sweeps']['api_cases'].values())} | typed errors:" in page


def test_readme_mapping_numbers_come_from_its_own_commands_on_this_version():
    import gpdepth3d

    d = json.loads((ROOT / "bench" / "results" / "map_recipes.json").read_text(encoding="utf-8"))
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    ran = [s["command"] for s in d["sequences"].values() if s["command"] in readme]
    assert ran and all(line in readme for line in re.findall(r"^gpdepth3d map [^\n]*", readme, flags=re.M))
    assert set(re.findall(r"^gpdepth3d map [^\n]*", readme, flags=re.M)) <= set(ran)
    assert d.get("version") == gpdepth3d.__version__, "bench/results/map_recipes.json ran another version"


def test_mapping_tables_follow_the_json(tmp_path):
    """The README's mapping table and the selection section are made from their results files."""
    report = _report()
    results = tmp_path / "results"
    results.mkdir()
    d = json.loads((ROOT / "bench" / "results" / "map_recipes.json").read_text(encoding="utf-8"))
    d["sequences"]["map_hololens"]["fscore_map"] = 0.987
    (results / "map_recipes.json").write_text(json.dumps(d), encoding="utf-8")
    assert "| **0.987** |" in report.readme_mapping_table(results)
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


def test_sfm_section_follows_the_json():
    """The images-alone table and the sigma coverage come from bench/results/sfm.json's fields."""
    run = {
        "frames": 94,
        "registered": 88,
        "pieces": [
            {
                "frames": 32,
                "frames_fused": 32,
                "fscore": 0.123,
                "scale": {"scale": 0.4047, "sigma": 0.0105, "mad": 0.127},
            },
            {"frames": 8, "frames_fused": 8, "fscore": 0.623, "scale": {"scale": 0.4, "sigma": 0.01, "mad": 0.1}},
        ],
        "fscore_map": 0.123,
        "fscore_mde_only": 0.111,
        "process_wall_s": 300.0,
        "process_cpu_s": 150.0,
        "loadavg_before": [2.0, 1.0, 1.0],
        "loadavg_after": [3.0, 1.0, 1.0],
    }
    rule = {"relative": 0.03, "geometric": 4.0, "min_error_px": 0.5}
    cov = {"coverage_2sigma": 0.951, "median_sigma_rel": 0.049}
    sigma = {
        "fitted_on": "7scenes",
        "rules": {"fitted": rule},
        "sequences": {
            "hololens": {
                "observations": 100,
                "median_abs_rel_error": 0.02,
                "scale_error": [-0.18],
                "fitted": cov,
                "as mapped": {"coverage_2sigma": 0.5, "median_abs_rel_error": 0.18},
            }
        },
    }
    text = _report().section_sfm({"runs": {"hololens": run}, "sigma": sigma})
    assert (
        "| HoloLens walk | 88 / 94 (2) | 32 | 0.4047 ± 0.0105 (MAD 12.7%) | 0.123 | 0.223 | 0.111 | 300 / 150 | 160 |"
        in text
    )
    assert "| HoloLens walk | 100 | 2.0% | 95.1% (σ 4.9%) |" in text and "HoloLens walk -18.0%" in text
