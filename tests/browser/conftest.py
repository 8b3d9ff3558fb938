"""Browser tests: scenarios run in a fresh network namespace with headless Chromium (see
netns.py); skipped with the reason where Chromium, playwright or unshare is missing. One that
starts the daemons or a demo holds the suite's slot for a whole session (tests/session_slot.py);
its deadline scales with the machine's load (``session_slot.time_scale``)."""

import contextlib
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from netns import SCENARIOS, ScenarioResult, run_scenario, skip_reason  # noqa: E402

from session_slot import scaled, whole_session_slot  # noqa: E402


def starts_a_session(name: str) -> bool:
    """Whether ``scenarios/<name>.py`` starts the daemons or a demo (its ``ctx.daemons()`` or
    ``ctx.demo(...)``): a whole session beside its Chromium, one at a time across the lanes."""
    text = (SCENARIOS / f"{name}.py").read_text()
    return "ctx.daemons(" in text or "ctx.demo(" in text


@pytest.fixture(scope="session")
def browser_scenario(tmp_path_factory):
    """``browser_scenario(name, **args) -> ScenarioResult``: run ``scenarios/<name>.py``."""
    reason = skip_reason()
    if reason:
        pytest.skip(f"browser tests: {reason}")

    def run(name: str, timeout_s: float = 300.0, **args) -> ScenarioResult:
        slot = whole_session_slot() if starts_a_session(name) else contextlib.nullcontext()
        with slot:  # its deadline from when it starts, scaled to the machine's load then
            return run_scenario(name, tmp_path_factory.mktemp(name), args, scaled(timeout_s))

    return run
