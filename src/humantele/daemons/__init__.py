"""What both daemons (expert, follower) share above the link and the recording: their run
shape, exit codes and stats (:mod:`.common`), their session recording options
(:mod:`.session`). Below them in the layers: :mod:`humantele.runtime` (processes, pacing,
stats files), :mod:`humantele.transport`, :mod:`humantele.recording`."""
