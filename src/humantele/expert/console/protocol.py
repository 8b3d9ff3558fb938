"""The page protocol's replies, shared by the console's parts: what became of a click
(``result``, with the click's ``id``), the session's commands (scan, clutch) and JSON without
NaN (the message types are in :mod:`.messages`; the dispatch of the page's messages is the
server's ``on_page_message``)."""

from __future__ import annotations

import json
import logging
import math
from collections import Counter
from typing import Any

import numpy as np

from humantele.expert.console.messages import ClutchCommand, ScanCommand
from humantele.expert.console.session import ConsoleSession
from humantele.web.pagesocket import PageClient

log = logging.getLogger(__name__)


def clean(obj: Any) -> Any:
    """JSON-able copy with non-finite floats as null (JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [clean(v) for v in obj]
    if isinstance(obj, np.generic):
        return clean(obj.item())
    if hasattr(obj, "tolist"):
        return clean(obj.tolist())
    return obj


def result(client: PageClient, of: str, ok: bool, detail: str, **more: Any) -> None:
    """Tell page ``client`` what became of ``of`` (``ok``, ``detail``; ``id``: the click's)."""
    msg = {"type": "result", "of": of, "ok": ok, "detail": detail, **more}
    if msg.get("id") is None:
        msg.pop("id", None)
        key = f"result:{of}"
    else:  # each click's answer is sent (not replaced by a later one's)
        key = f"result:{of}:{msg['id']}"
    client.post(key, json.dumps(clean(msg)))


def ack(client: PageClient, of: str, ok: bool, detail: str, cmd_id: int | None) -> None:
    """The answer to a click that asked for one (``cmd_id``); the session's state shows the
    effect either way."""
    if cmd_id is not None:
        result(client, of, ok, detail, id=cmd_id)


def session_command(
    session: ConsoleSession, client: PageClient, m: ScanCommand | ClutchCommand, events: Counter
) -> None:
    """A click on the session's controls: a scan started or stopped, the clutch held or
    released, done on ``session``, counted in ``events`` and answered to ``client``; a scan
    that fails is said on the page (the daemon goes on)."""
    if isinstance(m, ClutchCommand):
        session.set_clutch(m.on)
        events["clutch_on" if m.on else "clutch_off"] += 1
        ack(client, "clutch", True, "held" if m.on else "released", m.id)
        return
    try:
        if m.action == "start":
            detail = f"scan {session.start_scan()} started"
        else:
            session.stop_scan()
            detail = "scan stopped"
    except Exception as exc:  # noqa: BLE001 - said on the page, the daemon goes on
        log.exception("console: scan %s failed", m.action)
        ack(client, "scan", False, f"not done: {exc}", m.id)
        return
    events[f"scan_{m.action}"] += 1
    ack(client, "scan", True, detail, m.id)
