from session_helpers import demo_run, session  # noqa: F401 - the fixtures
