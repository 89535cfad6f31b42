"""The README's test command is the fast suite; the slow real-data suites run in .ci/run (issue: a newcomer's
`python -m pytest -q` took 19 min on 2 busy cores)."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_default_run_skips_the_slow_tests_and_ci_runs_them():
    pyproject = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    addopts = re.search(r'^addopts = "(.*)"$', pyproject, flags=re.M).group(1)
    assert "-m 'not slow'" in addopts
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8").splitlines()
    assert "python3 -m pytest -q" in ci and "python3 -m pytest -q -m slow" in ci  # both halves, in CI
    assert "bash scripts/setup-dev.sh && python -m pytest -q" in (ROOT / "README.md").read_text(encoding="utf-8")


def test_real_data_smoke_tests_stay_in_the_default_run():
    """A few fast real-data tests are not marked slow: the default run still reads ../shared/data."""
    smoke = [
        ROOT / "tests" / "cli" / "test_cli.py",
        ROOT / "tests" / "completion" / "test_complete.py",
        ROOT / "tests" / "datasets" / "test_datasets.py",
    ]
    for path in smoke:
        text = path.read_text(encoding="utf-8")
        assert "shared_data" in text or "seven_scenes_frame" in text, path
        assert "pytestmark = [pytest.mark.shared_data, pytest.mark.slow]" not in text, path
