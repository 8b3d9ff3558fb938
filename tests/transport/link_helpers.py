"""Helpers shared by the transport tests: waiting for a condition, two links running."""

import asyncio
import contextlib

from humantele.transport import PeerLink


@contextlib.asynccontextmanager
async def running_links(expert: PeerLink, follower: PeerLink, timeout: float):
    """Both links running and connected (within ``timeout`` s); closed on exit."""
    tasks = [asyncio.create_task(expert.run()), asyncio.create_task(follower.run())]
    try:
        await expert.wait_state("connected", timeout=timeout)
        await follower.wait_state("connected", timeout=timeout)
        yield
    finally:
        await expert.close()
        await follower.close()
        for t in tasks:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(t, 5)
