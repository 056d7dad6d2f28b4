"""Capture readers: typed Frame/Capture records and `open_capture` with format auto-detection."""

from image2sim.simulator.io.canonical import read_canonical, write_capture
from image2sim.simulator.io.fusion import backproject_frame, fuse_frames
from image2sim.simulator.io.ply import read_ply, write_ply
from image2sim.simulator.io.records import Capture, CaptureError, Frame
from image2sim.simulator.io.registry import available_formats, detect_format, open_capture, register_format

__all__ = [
    "Capture",
    "CaptureError",
    "Frame",
    "available_formats",
    "backproject_frame",
    "detect_format",
    "fuse_frames",
    "open_capture",
    "read_canonical",
    "read_ply",
    "register_format",
    "write_capture",
    "write_ply",
]
