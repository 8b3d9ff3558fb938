"""Tracking: IR marker probe tracking, frame sources, tool definitions."""
