"""A latest-frame slot: a capture thread puts frames, coroutines on the loop take the newest.

Never a queue: a frame put before the previous one was taken replaces it (counted in
``overwritten``), so a slow consumer (an encoder short of CPU) always gets the newest frame and
never works through old ones.
"""

from __future__ import annotations

import asyncio
import threading
from typing import Generic, TypeVar

T = TypeVar("T")


class LatestSlot(Generic[T]):
    """Holds the newest item and its number (1, 2, ...). ``put`` is for any thread; ``get_newer``
    is awaited on ``loop`` (the loop the slot was bound to with :meth:`bind`)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._item: T | None = None
        self._number = 0
        self._taken = 0  # the newest number any consumer took
        self.overwritten = 0  # items replaced before any consumer took them
        self._loop: asyncio.AbstractEventLoop | None = None
        self._event: asyncio.Event | None = None

    def bind(self, loop: asyncio.AbstractEventLoop) -> None:
        """Wake consumers on ``loop`` (call on the loop). Binding again keeps the consumers
        already waiting (a track may start before its source does)."""
        self._loop = loop
        if self._event is None:
            self._event = asyncio.Event()

    @property
    def number(self) -> int:
        return self._number

    def peek(self) -> tuple[int, T | None]:
        with self._lock:
            return self._number, self._item

    def put(self, item: T) -> None:
        with self._lock:
            if self._number > self._taken and self._number > 0:
                self.overwritten += 1
            self._item = item
            self._number += 1
        loop = self._loop
        if loop is not None and not loop.is_closed():
            try:
                loop.call_soon_threadsafe(self._wake)
            except RuntimeError:  # the loop closed in between
                pass

    def _wake(self) -> None:
        ev, self._event = self._event, asyncio.Event()
        if ev is not None:
            ev.set()

    async def get_newer(self, number: int) -> tuple[int, T]:
        """The newest item once its number is above ``number``: (its number, the item)."""
        while True:
            with self._lock:
                if self._number > number and self._item is not None:
                    self._taken = max(self._taken, self._number)
                    return self._number, self._item
            if self._event is None:  # the first consumer binds the slot to its loop
                self.bind(asyncio.get_running_loop())
            assert self._event is not None
            await self._event.wait()
