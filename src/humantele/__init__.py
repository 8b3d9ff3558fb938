"""humantele: remote ultrasound by human teleoperation."""

__version__ = "0.1.0"
