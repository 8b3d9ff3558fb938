"""A sensing child's stand-in for the hung-child test, in a module of its own so the spawned
child imports nothing else: it answers its first frame and hangs on the second (a device read
that never returns)."""

import os
import time


def hanging_sensing_main(config, sensing_config, conn, priority) -> None:
    conn.send(("ready", os.getpid(), []))
    answered = 0
    while True:
        msg = conn.recv()
        if msg is None:
            return
        if answered:
            time.sleep(3600)
        answered += 1
        conn.send(("result", msg[0], None, 0.001, 0, {"frames": 1}))
