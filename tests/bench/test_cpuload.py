"""The benchmarks' busy-loop load: N processes that run for the block and are gone after it."""

import time

from humantele.bench.cpuload import cpu_load


def test_cpu_load_starts_n_busy_processes_and_stops_them_at_the_end_of_the_block():
    with cpu_load(2, time.monotonic() + 120) as procs:
        assert len(procs) == 2
        assert all(p.is_alive() for p in procs)
    assert not any(p.is_alive() for p in procs)
    with cpu_load(0, time.monotonic() + 120) as none:
        assert none == []
