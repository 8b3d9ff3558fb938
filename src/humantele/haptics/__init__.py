"""Haptics: ellipsoid patient model, force law, servo loop, haptic device backends."""
