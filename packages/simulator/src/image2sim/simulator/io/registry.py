"""Capture formats by name, auto-detection and :func:`open_capture`.

A format is a reader ``reader(path, *, strict=True, **options) -> Capture`` plus a cheap
``detect(path) -> bool`` that looks only at file names. Built-in formats (``image2sim``,
``hm3d_360``, ``realsee``, ``pinhole_dir``) are registered on first use; others can be added with
:func:`register_format`. Detection tries formats in registration order and uses the first match.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from image2sim.simulator.io.records import Capture, CaptureError

__all__ = ["CaptureFormat", "register_format", "available_formats", "detect_format", "open_capture"]


@dataclass(frozen=True)
class CaptureFormat:
    """A registered capture format."""

    name: str
    """Name used by ``open_capture(path, format=name)`` and ``--format``."""
    reader: Callable[..., Capture]
    """``reader(path, *, strict=True, **options) -> Capture``."""
    detect: Callable[[Path], bool]
    """Cheap test on a folder: does it look like this format?"""
    description: str = ""
    """One line shown in error messages and ``--help``."""


_FORMATS: dict[str, CaptureFormat] = {}
_BUILTINS_LOADED = False


def register_format(
    name: str,
    reader: Callable[..., Capture],
    detect: Callable[[Path], bool],
    description: str = "",
    *,
    replace: bool = False,
) -> CaptureFormat:
    """Register a capture format; re-registering a name needs ``replace=True``."""
    _load_builtins()
    if not name or not isinstance(name, str):
        raise ValueError(f"format name must be a non-empty string, got {name!r}")
    if name in _FORMATS and not replace:
        raise ValueError(f"capture format {name!r} is already registered (pass replace=True to override)")
    fmt = CaptureFormat(name, reader, detect, description)
    _FORMATS[name] = fmt
    return fmt


def _load_builtins() -> None:
    global _BUILTINS_LOADED
    if _BUILTINS_LOADED:
        return
    _BUILTINS_LOADED = True
    from image2sim.simulator.io import canonical, hm3d360, pinhole_dir, realsee

    builtins = [
        CaptureFormat(
            "image2sim",
            canonical.read_canonical,
            canonical.is_canonical,
            "canonical capture: manifest.json + frames/",
        ),
        CaptureFormat(
            "hm3d_360",
            hm3d360.read_hm3d_360,
            hm3d360.is_hm3d_360,
            "NNNNN_{rgb.png,depth.png,pose.txt} equirect panoramas (habitat-sim, OpenGL camera)",
        ),
        CaptureFormat(
            "realsee",
            realsee.read_realsee,
            realsee.is_realsee,
            "viewpoints.txt + viewpoints/<id>/{panoImage_1600.jpg,depth_image.png,extrinsics.txt}",
        ),
        CaptureFormat(
            "pinhole_dir",
            pinhole_dir.read_pinhole_dir,
            pinhole_dir.is_pinhole_dir,
            "ScanNet export: color/, depth/, pose/, intrinsic/intrinsic_depth.txt",
        ),
    ]
    for fmt in builtins:
        _FORMATS.setdefault(fmt.name, fmt)


def available_formats() -> dict[str, str]:
    """Registered format names -> descriptions, in detection order."""
    _load_builtins()
    return {name: fmt.description for name, fmt in _FORMATS.items()}


def _known_formats_text() -> str:
    return "; ".join(f"{n} ({d})" if d else n for n, d in available_formats().items())


def detect_format(path: str | Path) -> str:
    """Name of the first registered format whose detector accepts ``path``."""
    path = Path(path)
    if not path.exists():
        raise CaptureError(f"{path}: no such file or directory")
    if not path.is_dir():
        raise CaptureError(f"{path}: a capture is a directory, this is a file")
    _load_builtins()
    for name, fmt in _FORMATS.items():
        if fmt.detect(path):
            return name
    raise CaptureError(f"{path}: unknown capture format; known formats: {_known_formats_text()}")


def open_capture(path: str | Path, format: str | None = None, *, strict: bool = True, **options) -> Capture:
    """Open a capture folder as a lazily loaded :class:`Capture`.

    ``format`` selects a registered format by name; ``None`` auto-detects. ``strict=False`` makes
    readers list unusable frames in ``Capture.skipped`` instead of raising. Extra keyword
    ``options`` go to the reader (e.g. ``half_pixel`` for ``realsee``, ``depth_scale`` for
    ``pinhole_dir``).
    """
    path = Path(path)
    _load_builtins()
    if format is None:
        format = detect_format(path)
    elif format not in _FORMATS:
        raise CaptureError(
            f"{path}: unknown capture format {format!r}; known formats: {_known_formats_text()}"
        )
    elif not path.exists():
        raise CaptureError(f"{path}: no such file or directory")
    try:
        return _FORMATS[format].reader(path, strict=strict, **options)
    except TypeError as err:
        if "unexpected keyword argument" in str(err):
            raise CaptureError(
                f"{path}: format {format!r} does not accept option(s) {sorted(options)}: {err}"
            ) from None
        raise
