"""Text helpers that make client-supplied values safe for reasons and logs."""

from hypothesis import given
from hypothesis import strategies as st

from humantele.signaling.messages import (
    MAX_CLOSE_REASON_BYTES,
    MAX_REASON_CHARS,
    clip_utf8,
    printable,
    safe_reason,
)


def test_limits_fit_the_protocol():
    assert MAX_CLOSE_REASON_BYTES + 2 <= 125  # RFC 6455 5.5, with the 2-byte close code
    assert MAX_REASON_CHARS == 200


@given(st.text(max_size=400), st.integers(1, 300))
def test_clip_utf8_keeps_whole_characters_within_the_byte_budget(text, budget):
    clipped = clip_utf8(text, budget)
    data = clipped.encode("utf-8", "backslashreplace")
    assert len(data) <= budget
    full = text.encode("utf-8", "backslashreplace")
    assert full.startswith(data)
    # the longest such prefix: the next character would not fit
    rest = full[len(data) :].decode("utf-8")
    if rest:
        assert len(data) + len(rest[0].encode("utf-8")) > budget


@given(st.text(max_size=400))
def test_printable_and_safe_reason_are_one_line_and_bounded(text):
    p = printable(text)
    assert p.isprintable()
    if text.isprintable():
        assert p == text
    r = safe_reason(text)
    assert r.isprintable() and len(r) <= MAX_REASON_CHARS
    assert "\n" not in r and "\r" not in r
