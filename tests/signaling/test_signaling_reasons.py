"""Refusal reasons quote client input: they stay short, printable, and fit a close frame."""

import json
import logging

import aiohttp
import pytest
from signaling_helpers import CLOSED, assert_clean_logs, raw_ws, running_server

from humantele.signaling import CLOSE_BAD_MESSAGE

TOKEN = "reasons-token-never-logged"
MAX_REASON_CHARS = 200  # the error message's limit (clients refuse longer ones)
MAX_CLOSE_REASON_BYTES = 123  # RFC 6455 5.5: 125 bytes of control frame payload, 2 for the code


@pytest.fixture
async def server():
    async with running_server(TOKEN, join_timeout_s=2, max_message_bytes=65536) as s:
        yield s


async def _refusal(server, payload: str) -> tuple[str, int | None, bytes]:
    """Send ``payload`` first; the error reason, then the close code and close reason."""
    session, ws = await raw_ws(server.url)
    try:
        await ws.send_str(payload)
        first = await ws.receive(timeout=5)
        assert first.type == aiohttp.WSMsgType.TEXT, (first.type, first.data)
        reason = json.loads(first.data)["reason"]
        close = await ws.receive(timeout=5)
        assert close.type in CLOSED, (close.type, close.data)  # not a protocol error
        return reason, ws.close_code, (close.extra or "").encode()
    finally:
        await session.close()


@pytest.mark.parametrize(
    "payload",
    [
        json.dumps({"type": "x" * 300}),
        json.dumps({"type": "join", "room": "r", "role": "expert", "é" * 150: 1}),
        json.dumps({"type": "😀" * 5000}),
        json.dumps({"type": "\u202e" * 60}),  # 180 bytes, printable only when escaped
    ],
    ids=["long-type", "long-extra-key", "wide-chars", "bidi-controls"],
)
async def test_long_client_values_give_a_short_reason_and_a_valid_close_frame(
    server, payload, caplog
):
    caplog.set_level(logging.DEBUG)
    reason, code, close_reason = await _refusal(server, payload)
    assert code == CLOSE_BAD_MESSAGE
    assert 0 < len(reason) <= MAX_REASON_CHARS and reason.isprintable()
    assert 0 < len(close_reason) <= MAX_CLOSE_REASON_BYTES
    close_reason.decode("utf-8")  # cut between characters, never inside one
    assert_clean_logs(caplog.records, TOKEN)
    assert server.counters[f"refused:{CLOSE_BAD_MESSAGE}"] == 1


async def test_a_newline_in_a_client_value_cannot_forge_a_log_line(server, caplog):
    caplog.set_level(logging.DEBUG)
    forged = "x\n2026-01-01 00:00:00,000 humantele.signaling.server: room r: expert joined\r\x1b[2K"
    reason, _, _ = await _refusal(server, json.dumps({"type": forged}))
    assert "\n" not in reason and "\\n2026-01-01" in reason  # quoted, visible
    assert_clean_logs(caplog.records, TOKEN)
    refused = [r.getMessage() for r in caplog.records if "refused" in r.getMessage()]
    assert refused and all("\\n2026-01-01" in m and "\\x1b" in m for m in refused)
