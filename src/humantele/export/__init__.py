"""``humantele export``: a recording's video per scan as MP4 (H.264) and, with the poses and
force, as an MCAP Foxglove plays (docs/export.md)."""
