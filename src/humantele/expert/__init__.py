"""The expert side: daemon, servo process wiring, console page."""
