"""The ``humantele devices`` command's tools: recording a clinic's devices (:mod:`.record`),
checking them one at a time (:mod:`.check`), the hl2ss calibration (:mod:`.hl2ss_calibration`).
They sit above the device packages they drive (tracking, forcesense, video) and the follower's
sensing; the recording file they write is :mod:`humantele.recording.device_file`."""
