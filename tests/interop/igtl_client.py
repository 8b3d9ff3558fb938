"""A small asyncio OpenIGTLink reader for the tests: splits the stream with pyigtl's header
parser and unpacks each message with pyigtl (the same library Slicer users script with)."""

import asyncio
import time

import pyigtl
from pyigtl.messages import MessageBase


async def read_messages(reader: asyncio.StreamReader, out: list, stop_after: int | None = None):
    """Append (receive wall time, message) to ``out`` until EOF (or ``stop_after`` messages)."""
    size = MessageBase.IGTL_HEADER_SIZE
    while stop_after is None or len(out) < stop_after:
        try:
            header = await reader.readexactly(size)
        except (asyncio.IncompleteReadError, ConnectionError):
            return
        fields = MessageBase.parse_header(header)
        body = await reader.readexactly(fields["body_size"])
        msg = MessageBase.create_message(fields["message_type"])
        msg.unpack(fields, body)
        out.append((time.time(), msg))


def by_name(messages: list, name: str) -> list:
    return [m for _, m in messages if m.device_name == name]


__all__ = ["pyigtl", "read_messages", "by_name"]
