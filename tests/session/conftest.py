from session_helpers import session  # noqa: F401 - the fixture
