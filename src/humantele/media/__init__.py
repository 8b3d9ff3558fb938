"""Media: the follower's two video tracks (``us``, ``pov``) on the session's peer connection.

- :mod:`humantele.media.config`: the follower's ``[follower.video]`` and the expert's
  ``[expert.video]`` settings (sources, codec, degradation, recording rates);
- :mod:`humantele.media.frameinfo`: the per-frame record (track, seq, capture time) sent on the
  ``video`` data channel, so the expert knows each frame's capture time;
- :mod:`humantele.media.slot`: a latest-frame slot between a capture thread and the loop;
- :mod:`humantele.media.sender`: the follower side (capture threads, tracks, degradation);
- :mod:`humantele.media.receiver`: the expert side (latest decoded frame of each track, its
  capture time on the expert's clock, frame age).

See docs/video.md.
"""
