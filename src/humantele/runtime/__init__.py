"""The processes' runtime: pacing (:mod:`.pacing`), the process's life (:mod:`.process`), child
processes (:mod:`.child`), the stats file and figures (:mod:`.stats`), which simulator modules
a process loaded (:mod:`.simulator`). What both daemons share above this is
:mod:`humantele.daemons`; the demo (:mod:`humantele.demo`) only starts processes."""
