"""Compiled CPU rasteriser: C++ (``csrc/splat_cpu.cpp``) JIT-built with torch's cpp_extension.

The same extension holds the best-view selection of Gaussian fusion (``csrc/views_cpu.cpp``,
:func:`best_view_mask`; ``gaussians/views.py`` keeps the torch version it is tested against).

Multi-threaded over tiles with OpenMP (thread count = ``torch.get_num_threads()``), 16-lane
vectorised pixel rows, hand-written backward for means2d, conics, opacities, values and
background, exposed as a ``torch.autograd.Function``; :func:`render` is the fused inference path
(projection, depth sort, binning and rasterisation in one C++ call). The build is automatic and
cached under ``$TORCH_EXTENSIONS_DIR`` or ``~/.cache/image2sim/torch_extensions`` (keyed by a hash
of the source and its path, the torch version, the compiler flags and this CPU's instruction-set
flags, since it is built with ``-march=native``; edits rebuild, and two checkouts never rebuild
over each other's library). Builds go through :func:`image2sim.simulator.extensions.build_guard`,
so a lock file torch left behind by a killed build cannot stall the next one. If the build fails,
:func:`available` is False and ``backend="auto"`` falls back to the torch backend with a warning.
"""

from __future__ import annotations

import hashlib
import os
import platform
import threading
from pathlib import Path

import torch
from image2sim.simulator.extensions import build_guard
from image2sim.simulator.splatting.backends.torch_tiles import TILE_SIZE
from image2sim.simulator.splatting.project import NEAR, T_MIN

__all__ = [
    "available",
    "load_error",
    "load",
    "rasterize",
    "bin_gaussians",
    "sort_valid",
    "project",
    "render",
    "best_view_mask",
]

_SOURCE = Path(__file__).with_name("csrc") / "splat_cpu.cpp"
_SOURCES = (_SOURCE, _SOURCE.with_name("views_cpu.cpp"))
_HEADERS = (_SOURCE.with_name("workers.h"),)  # included by the sources: part of the build key
_lock = threading.Lock()
_module = None
_error: str | None = None


_CFLAGS = ["-O3", "-march=native", "-fopenmp", "-fno-math-errno"]


def _cpu_flags() -> bytes:
    """The instruction-set flags of this CPU (part of the cache key: the build uses -march=native)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith(("flags", "Features")):
                return line.encode()
    except OSError:
        pass
    return platform.machine().encode() + platform.processor().encode()


def _build_dir() -> Path:
    root = os.environ.get("TORCH_EXTENSIONS_DIR")
    base = Path(root) if root else Path.home() / ".cache" / "image2sim" / "torch_extensions"
    # The source's path is part of the key: torch's ninja file names it, so two checkouts sharing one
    # folder would rebuild the library in place under each other's running processes.
    key = (
        b"".join(src.read_bytes() for src in (*_SOURCES, *_HEADERS))
        + str(_SOURCE.resolve()).encode()
        + torch.__version__.encode()
        + " ".join(_CFLAGS).encode()
        + _cpu_flags()
    )
    digest = hashlib.sha256(key).hexdigest()[:12]
    path = base / f"image2sim_splat_cpu_{digest}"
    path.mkdir(parents=True, exist_ok=True)
    return path


def load():
    """Build (first time, ~1 min) or load the extension; raises ``RuntimeError`` on failure."""
    global _module, _error
    with _lock:
        if _module is not None:
            return _module
        if _error is not None:
            raise RuntimeError(_error)
        try:
            from torch.utils.cpp_extension import load as _load

            build = _build_dir()
            with build_guard(build):
                _module = _load(
                    name=f"image2sim_splat_cpu_{build.name.rsplit('_', 1)[-1]}",
                    sources=[str(src) for src in _SOURCES],
                    extra_cflags=_CFLAGS,
                    extra_ldflags=["-fopenmp"],
                    build_directory=str(build),
                    verbose=False,
                )
        except Exception as err:  # compiler missing, headers missing, link error ...
            _error = f"{type(err).__name__}: {str(err).strip().splitlines()[-1] if str(err).strip() else err}"
            raise RuntimeError(_error) from err
        return _module


def available() -> bool:
    """True if the extension builds/loads on this machine (the first call may compile it)."""
    if os.environ.get("IMAGE2SIM_DISABLE_CPU_KERNEL"):
        return False
    try:
        load()
        return True
    except RuntimeError:
        return False


def load_error() -> str:
    """Why the extension is unavailable (empty string if it loaded)."""
    if os.environ.get("IMAGE2SIM_DISABLE_CPU_KERNEL"):
        return "disabled by IMAGE2SIM_DISABLE_CPU_KERNEL"
    return _error or ""


def bin_gaussians(means2d, radii, height: int, width: int, wrap_width: float, tile: int = TILE_SIZE):
    """Per-tile index lists (offsets (n_tiles + 1,), ids (pairs,)), like the torch backend's."""
    return load().bin_gaussians(means2d.detach().cpu(), radii.detach().cpu(), height, width, wrap_width, tile)


def sort_valid(depths: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Indices of the valid Gaussians sorted front to back (stable: ties keep input order)."""
    return load().sort_valid(depths.detach().contiguous(), valid.contiguous())


class _Rasterize(torch.autograd.Function):
    @staticmethod
    def forward(
        ctx,
        means2d,
        conics,
        opacities,
        values,
        background,
        radii,
        offsets,
        ids,
        height,
        width,
        wrap,
        tile,
        t_min,
    ):
        ext = load()
        args = [t.detach().contiguous() for t in (means2d, radii, conics, opacities, values, background)]
        image, alpha, t_final, n_contrib = ext.rasterize_forward(
            *args, offsets, ids, height, width, wrap, tile, t_min
        )
        ctx.save_for_backward(*args, offsets, ids, alpha, t_final, n_contrib)
        ctx.grid = (height, width, wrap, tile)
        return image, alpha

    @staticmethod
    def backward(ctx, g_image, g_alpha):
        means2d, radii, conics, opacities, values, background, offsets, ids, alpha, t_final, n_contrib = (
            ctx.saved_tensors
        )
        height, width, wrap, tile = ctx.grid
        dtype = values.dtype
        g_image = torch.zeros_like(alpha.expand(values.shape[1], -1, -1)) if g_image is None else g_image
        g_alpha = torch.zeros_like(alpha) if g_alpha is None else g_alpha
        d_mean, d_conic, d_opac, d_vals, d_bg = load().rasterize_backward(
            means2d,
            radii,
            conics,
            opacities,
            values,
            background,
            offsets,
            ids,
            height,
            width,
            wrap,
            tile,
            alpha,
            t_final,
            n_contrib,
            g_image.to(dtype).contiguous(),
            g_alpha.to(dtype).contiguous(),
        )
        return d_mean, d_conic, d_opac, d_vals, d_bg, None, None, None, None, None, None, None, None


def rasterize(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    values: torch.Tensor,
    background: torch.Tensor,
    height: int,
    width: int,
    wrap_width: float,
    radii: torch.Tensor | None = None,
    tile: int = TILE_SIZE,
    t_min: float = T_MIN,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Compiled tile-parallel compositing; same contract and result as the dense reference."""
    if means2d.device.type != "cpu":
        raise ValueError(f"cpu kernel needs CPU tensors, got {means2d.device}")
    if radii is None:
        from image2sim.simulator.splatting.project import CUTOFF_SIGMA

        a, b, c = conics.detach().unbind(-1)
        det = a * c - b * b
        radii = CUTOFF_SIGMA * torch.sqrt(torch.stack((c / det, a / det), dim=-1))
    offsets, ids = bin_gaussians(means2d, radii, height, width, wrap_width, tile)
    radii = radii.detach().to(values.dtype)
    return _Rasterize.apply(
        means2d,
        conics,
        opacities,
        values,
        background,
        radii,
        offsets,
        ids,
        int(height),
        int(width),
        float(wrap_width),
        int(tile),
        float(t_min),
    )


def _dense(*tensors: torch.Tensor) -> tuple[torch.Tensor, ...]:
    return tuple(t.detach().contiguous() for t in tensors)


def _camera_tail(camera, cam_to_world, near, far, finite_mask) -> tuple:
    """The kernel's (finite mask, pose, equirect, fx, fy, cx, cy, H, W, near, far) arguments."""
    from image2sim.simulator.geometry.cameras import EquirectCamera

    equirect = isinstance(camera, EquirectCamera)
    fx, fy, cx, cy = (0.0,) * 4 if equirect else (camera.fx, camera.fy, camera.cx, camera.cy)
    mask = torch.empty(0, dtype=torch.bool) if finite_mask is None else finite_mask.contiguous()
    far_arg = -1.0 if far is None else float(far)
    h, w = int(camera.height), int(camera.width)
    return (
        mask,
        cam_to_world.detach().cpu(),
        equirect,
        float(fx),
        float(fy),
        float(cx),
        float(cy),
        h,
        w,
        float(near),
        far_arg,
    )


def project(
    means, scales, quats, opacities, camera, cam_to_world, *, near: float = NEAR, far=None, finite_mask=None
):
    """Inference-only fused projection (no autograd); same result as :func:`project_gaussians`."""
    from image2sim.simulator.geometry.cameras import EquirectCamera
    from image2sim.simulator.splatting.project import ProjectedGaussians

    uv, conic, cov, depth, radii, valid = load().project_forward(
        *_dense(means, scales, quats, opacities), *_camera_tail(camera, cam_to_world, near, far, finite_mask)
    )
    return ProjectedGaussians(
        means2d=uv,
        conics=conic,
        cov2d=cov,
        depths=depth,
        radii=radii,
        valid=valid,
        wrap_width=float(camera.width) if isinstance(camera, EquirectCamera) else 0.0,
    )


def render(
    means: torch.Tensor,
    scales: torch.Tensor,
    quats: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    features: torch.Tensor,
    camera,
    cam_to_world: torch.Tensor,
    background: torch.Tensor,
    *,
    near: float = NEAR,
    far=None,
    finite_mask=None,
    t_min: float = T_MIN,
    blocks: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Inference-only fused render of one camera (no autograd): ``(image (4 + C, H, W), alpha)``.

    ``background`` has 4 + C entries (rgb, depth, features). Same result as projecting with
    :func:`project_gaussians`, sorting, and :func:`rasterize`. ``blocks``: ``(block_of (N,) int64,
    keep (B,) bool)`` from :meth:`~image2sim.simulator.splatting.culling.FrustumBlocks.keep`: the
    Gaussians of blocks not kept are skipped before projection (a conservative cull: same image).
    """
    empty = torch.empty(0, dtype=torch.int64)
    block_of, keep = blocks if blocks is not None else (empty, empty.bool())
    image, alpha = load().render_forward(
        *_dense(means, scales, quats, opacities, colors, features),
        *_camera_tail(camera, cam_to_world, near, far, finite_mask),
        background.detach().contiguous(),
        float(t_min),
        block_of.contiguous(),
        keep.contiguous(),
    )
    return image, alpha


def best_view_mask(
    probes, own_iv, facing, own: int, views, carvers, tolerance, step, owner_cos
) -> torch.Tensor:
    """The compiled :func:`image2sim.simulator.gaussians.views.best_view_mask` (same arguments, as
    that function prepares them: ``probes`` (N, P, 3) float64 with the means first, ``facing`` with
    unknown normals already replaced, ``carvers`` the set of carving view indices)."""
    cams, w2c, centres, angles = [], [], [], []
    for v in views:
        cam = v.camera
        if getattr(cam, "model", None) == "equirect":
            cams.append((1.0, 0.0, 0.0, 0.0, 0.0))
        else:
            cams.append((0.0, float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy)))
        w2c.append(v.world_to_cam.cpu())
        centres.append(v.centre.cpu())
        angles.append(v.min_pixel_angle)
    carve = torch.tensor([i in carvers for i in range(len(views))], dtype=torch.bool)
    return load().best_view_mask(
        probes.detach().cpu().double().contiguous(),
        own_iv.detach().cpu().double().contiguous(),
        facing.detach().cpu().double().contiguous(),
        int(own),
        w2c,
        torch.tensor(cams, dtype=torch.float64),
        [v.depth.cpu() for v in views],
        [v.interval.cpu() for v in views],
        [v.normals.cpu() for v in views],
        [v.free.cpu() for v in views],
        torch.stack(centres).double(),
        torch.tensor(angles, dtype=torch.float64),
        carve,
        float(tolerance),
        float(step),
        float(owner_cos),
        int(torch.get_num_threads()),
    )
