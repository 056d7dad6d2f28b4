"""Image2Sim navpolicy package."""

__version__ = "0.1.0"
