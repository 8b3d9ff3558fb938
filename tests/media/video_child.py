"""A follower process with the two video tracks (small sim sources), until killed.

Usage: python video_child.py SIGNALING_URL ROOM (token from $HUMANTELE_TOKEN)."""

import asyncio
import os
import sys

from video_helpers import video_follower


async def main(url: str, room: str) -> None:
    link, sender = video_follower(url, room, os.environ["HUMANTELE_TOKEN"])
    await asyncio.to_thread(sender.open)
    sender.start(asyncio.get_running_loop())
    await link.run()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], sys.argv[2]))
