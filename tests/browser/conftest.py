"""Browser tests: scenarios run in a fresh network namespace with headless Chromium (see
netns.py); skipped with the reason where Chromium, playwright or unshare is missing."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from netns import ScenarioResult, run_scenario, skip_reason  # noqa: E402


@pytest.fixture(scope="session")
def browser_scenario(tmp_path_factory):
    """``browser_scenario(name, **args) -> ScenarioResult``: run ``scenarios/<name>.py``."""
    reason = skip_reason()
    if reason:
        pytest.skip(f"browser tests: {reason}")

    def run(name: str, timeout_s: float = 300.0, **args) -> ScenarioResult:
        return run_scenario(name, tmp_path_factory.mktemp(name), args, timeout_s)

    return run
