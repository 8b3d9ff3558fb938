"""The WAN emulator's bandwidth cap: datagrams leave no faster than the rate, and a burst
beyond what the queue holds is dropped and counted (tail drop), never queued without end."""

import functools
import struct
import time

import pytest
from pydantic import ValidationError
from test_netem import _endpoint, _seqs

from humantele.transport.netem import NetemConfig, UdpRelay
from waits import until

_until = functools.partial(until, timeout=10.0, poll=0.01)
SIZE = 1000  # bytes per datagram


async def test_a_capped_link_spaces_datagrams_by_their_size_at_the_rate():
    sink = await _endpoint()
    kbps = 400.0  # 1000 B -> 20 ms each on the link
    cfg = NetemConfig(bandwidth_kbps=kbps, queue_s=5.0)
    async with UdpRelay(sink.address, cfg) as relay:
        client = await _endpoint(remote=relay.address)
        t0 = time.monotonic()
        for i in range(10):  # one burst
            client.transport.sendto(struct.pack("!I", i) + bytes(SIZE - 4))
        await _until(lambda: len(sink.got) == 10)
        assert relay.counters.up.overflow == 0
    per = SIZE * 8 / (kbps * 1e3)
    # a lower bound, whatever the machine's load (a late sender thread only adds): the last
    # leaves after all ten have had their time on the link, counted from the first's arrival
    assert sink.got[-1][0] - t0 >= 10 * per - 2e-3
    assert _seqs(sink) == list(range(10))  # a FIFO link
    client.transport.close()
    sink.transport.close()


async def test_a_burst_beyond_the_queue_is_dropped_and_counted():
    sink = await _endpoint()
    cfg = NetemConfig(bandwidth_kbps=80.0, queue_s=0.2)  # 100 ms per datagram, 0.2 s queue
    async with UdpRelay(sink.address, cfg) as relay:
        client = await _endpoint(remote=relay.address)
        for i in range(100):
            client.transport.sendto(struct.pack("!I", i) + bytes(SIZE - 4))
            if i % 20 == 19:  # never overrun the socket buffers, however loaded the machine
                await _until(lambda i=i: relay.counters.up.received == i + 1)
        await _until(lambda: relay.counters.up.received == 100)
        c = relay.counters.up
        # the burst arrives within a second even on a busy machine: at most ~13 fit
        assert c.overflow >= 80
        await _until(lambda: len(sink.got) == 100 - c.overflow)
        assert _seqs(sink)[:3] == [0, 1, 2]  # the first ones went, the tail was dropped
    client.transport.close()
    sink.transport.close()


def test_bandwidth_settings_are_checked():
    with pytest.raises(ValidationError, match="bandwidth_kbps"):
        NetemConfig(bandwidth_kbps=-1.0)
    with pytest.raises(ValidationError, match="queue_s"):
        NetemConfig(queue_s=0.0)
