"""The study's analysis of recorded sessions (``humantele analyze``); see docs/analysis.md."""
