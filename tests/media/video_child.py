"""A follower process with the two video tracks (small sim sources), until killed.

Usage: python video_child.py SIGNALING_URL ROOM (token from $HUMANTELE_TOKEN)."""

import asyncio
import os
import sys

from media_helpers import small_video_config, video_follower


async def main(url: str, room: str) -> None:
    config = small_video_config(process=True)  # as the daemon runs it: a video process
    link, sender = video_follower(url, room, os.environ["HUMANTELE_TOKEN"], config)
    await asyncio.to_thread(sender.open)
    sender.start(asyncio.get_running_loop())
    await link.run()


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1], sys.argv[2]))
