"""The daemons' runtime: pacing (:mod:`.pacing`), the process's life (:mod:`.process`), the
stats file and figures (:mod:`.stats`), the session recording (:mod:`.session`) and what both
daemons share (:mod:`.daemon`). The demo (:mod:`humantele.demo`) only starts processes."""
