"""Lifting RGB-only photos, video and panoramas to a metric posed RGB-D capture.

Stages: ``frames`` (images or video in), ``sfm`` (poses and intrinsics by structure-from-motion),
``depth`` / ``mvs`` (dense depth), ``scale`` (metric scale and gravity), ``capture`` (the
canonical capture out). Importing this package imports none of them.
"""
