"""Image2Sim dataengine package."""

__version__ = "0.1.0"
