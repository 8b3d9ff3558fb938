"""Checking the devices one at a time (``humantele devices check``)."""
