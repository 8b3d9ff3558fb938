"""``humantele study``: the 750 km study again in simulation, over a range of network
conditions (conditions file, one recorded session per condition and seed, the table and
charts). See docs/study.md."""
