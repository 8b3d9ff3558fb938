"""The follower side: daemon, calibration, sensing, headset page."""
