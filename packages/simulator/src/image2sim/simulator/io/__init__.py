"""Capture readers: typed Frame/Capture records and `open_capture` with format auto-detection."""
