"""Backend registry and the ``backend="auto"`` rule: which implementation renders a ``splat`` call.

A backend is one of two kinds:

* ``rasterizer``: implements the shared rasterisation contract of
  :mod:`image2sim.simulator.splatting.backends` (depth-sorted, projected screen Gaussians -> image
  planes); :func:`~image2sim.simulator.splatting.api.splat` does the projection, culling and
  sorting in front of it (``reference``, ``torch``, ``cpu``).
* ``renderer``: takes the 3D Gaussians and the cameras and does everything itself (``gsplat``,
  whose CUDA kernels project and rasterise in one go). Signature::

      fn(means, scales, quats, opacities, colors, features, camera, poses (B, 4, 4), *, near, far,
         background (3,)) -> (rgb (B, 3, H, W), depth (B, 1, H, W), alpha (B, 1, H, W),
                              features (B, C, H, W))

Each entry says which device types and camera classes it handles, whether it is available on this
machine, and its priority for ``auto``. ``auto`` picks the available entry with the highest priority
that handles the tensors' device type and the camera. So a GPU kernel for panoramas is added by one
:func:`register_backend` call (device ``cuda``, camera :class:`EquirectCamera`, a priority above the
torch backend's) and every caller of ``splat(..., backend="auto")`` gets it without a change.

Built-in rule (registered in :mod:`image2sim.simulator.splatting.api`): on CPU the compiled
``cpu`` kernel (falling back with a warning to ``torch`` if it cannot be built); on CUDA pinhole
cameras go to ``gsplat`` when it is importable (optional extra), panoramas (and pinholes without
gsplat) to ``torch``; any other device to ``torch``.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import torch

__all__ = [
    "Backend",
    "register_backend",
    "unregister_backend",
    "get_backend",
    "registered_backends",
    "resolve_backend",
    "device_type",
]


@dataclass(frozen=True)
class Backend:
    """One registered splatting implementation."""

    name: str
    kind: str
    """``"rasterizer"`` or ``"renderer"`` (see the module docstring)."""
    fn: Callable
    devices: frozenset[str] | None = None
    """Device types (``torch.device.type``) it runs on; None means any."""
    cameras: tuple[type, ...] = ()
    """Camera classes it renders; empty means every camera."""
    available: Callable[[], bool] = field(default=lambda: True)
    """Whether it can run on this machine (may build or import something the first time)."""
    unavailable_reason: Callable[[], str] = field(default=lambda: "")
    auto_priority: int | None = None
    """Rank for ``backend="auto"`` (higher wins); None: only used when asked for by name."""
    warn_on_fallback: bool = False
    """Warn when ``auto`` skips it because it is unavailable (True for a default backend that failed
    to build; False for optional extras such as gsplat)."""

    def handles(self, device: str, camera: object | None) -> bool:
        """True if this backend renders ``camera`` on device type ``device``."""
        if self.devices is not None and device not in self.devices:
            return False
        return camera is None or not self.cameras or isinstance(camera, self.cameras)


_REGISTRY: dict[str, Backend] = {}
_ALIASES: dict[str, str] = {}


def register_backend(backend: Backend, *, aliases: tuple[str, ...] = (), replace: bool = False) -> None:
    """Add ``backend`` (and optional alias names) to the registry."""
    if backend.kind not in ("rasterizer", "renderer"):
        raise ValueError(
            f"splat: backend {backend.name!r} has kind {backend.kind!r}; use rasterizer or renderer"
        )
    if backend.name in _REGISTRY and not replace:
        raise ValueError(f"splat: backend {backend.name!r} is already registered (pass replace=True)")
    _REGISTRY[backend.name] = backend
    for alias in aliases:
        _ALIASES[alias] = backend.name


def unregister_backend(name: str) -> None:
    """Remove a backend (and its aliases); unknown names are ignored."""
    _REGISTRY.pop(name, None)
    for alias in [a for a, n in _ALIASES.items() if n == name]:
        del _ALIASES[alias]


def get_backend(name: str) -> Backend:
    """The registered backend called ``name`` (or one of its aliases)."""
    key = _ALIASES.get(name, name)
    if key not in _REGISTRY:
        raise ValueError(f"splat: unknown backend {name!r}; choose from auto, {', '.join(_REGISTRY)}")
    return _REGISTRY[key]


def registered_backends() -> list[Backend]:
    """Every registered backend, in registration order."""
    return list(_REGISTRY.values())


def device_type(device: torch.device) -> str:
    """The device type dispatch keys on (one function, so tests can stand in a CUDA device)."""
    return torch.device(device).type


def resolve_backend(backend: str, device: torch.device, camera: object | None = None) -> str:
    """Map a requested backend name (or ``"auto"``) to a registered name for ``device`` and ``camera``.

    A name asked for explicitly must handle the device and camera and be available, else
    ``ValueError`` says why. ``auto`` takes the highest-priority available candidate, warning
    (``RuntimeWarning``) when it skips a failed default backend.
    """
    dev = device_type(device)
    if backend != "auto":
        entry = get_backend(backend)
        if entry.devices is not None and dev not in entry.devices:
            raise ValueError(
                f"splat: backend {entry.name!r} needs tensors on {'/'.join(sorted(entry.devices))}, "
                f"got device {device}"
            )
        if not entry.handles(dev, camera):
            names = ", ".join(c.__name__ for c in entry.cameras)
            raise ValueError(
                f"splat: backend {entry.name!r} renders only {names}, got {type(camera).__name__}"
            )
        if not entry.available():
            raise ValueError(f"splat: backend {entry.name!r} is unavailable: {entry.unavailable_reason()}")
        return entry.name
    candidates = sorted(
        (b for b in _REGISTRY.values() if b.auto_priority is not None and b.handles(dev, camera)),
        key=lambda b: -b.auto_priority,
    )
    skipped: list[Backend] = []
    for entry in candidates:
        if entry.available():
            for s in skipped:
                if s.warn_on_fallback:
                    warnings.warn(
                        f"splat: backend {s.name!r} unavailable ({s.unavailable_reason()}); using the "
                        f"slower {entry.name!r} backend",
                        RuntimeWarning,
                        stacklevel=3,
                    )
            return entry.name
        skipped.append(entry)
    raise ValueError(f"splat: no registered backend renders {type(camera).__name__} on device {device}")
