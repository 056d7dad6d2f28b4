"""Capture readers: typed Frame/Capture records and `open_capture` with format auto-detection."""

from image2sim.simulator.io.canonical import read_canonical, write_capture
from image2sim.simulator.io.records import Capture, CaptureError, Frame

__all__ = ["Capture", "CaptureError", "Frame", "read_canonical", "write_capture"]
