"""Tile-binned pure-torch rasteriser (autograd for every input, runs on any device).

Gaussians are binned into square tiles by the bounding box of their 3.5-sigma footprint (wrapping
around the panorama seam); each tile composites only its own depth-sorted list. Because the cut is
the per-pixel ellipse test (not the box), the result equals the dense reference exactly. Tiles are
processed in chunks whose padded (tiles x pixels x list-length) working set stays bounded.
"""

from __future__ import annotations

import math

import torch
from image2sim.simulator.splatting.backends.reference import composite
from image2sim.simulator.splatting.project import T_MIN, wrap_offset

__all__ = ["TILE_SIZE", "tile_ranges", "bin_gaussians", "rasterize"]

TILE_SIZE = 16
"""Tile edge in pixels."""
_CHUNK_ELEMENTS = 1 << 22  # padded tile x pixel x list entries per chunk (memory bound)


def tile_ranges(
    means2d: torch.Tensor,
    radii: torch.Tensor,
    height: int,
    width: int,
    wrap_width: float,
    tile: int = TILE_SIZE,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Inclusive tile index ranges (tx0, tx1, ty0, ty1) of every footprint box, each (M,) int64.

    Rows are clipped to the image. Columns are clipped for pinhole images; for panoramas they are
    left unclipped (callers wrap them modulo the tile count) unless the box spans every column,
    in which case the full range [0, n_tx - 1] is returned.
    """
    n_tx = math.ceil(width / tile)
    n_ty = math.ceil(height / tile)
    u, v = means2d[:, 0].detach(), means2d[:, 1].detach()
    ru, rv = radii[:, 0], radii[:, 1]
    ty0 = torch.floor((v - rv) / tile).clamp(0, n_ty - 1).long()
    ty1 = torch.floor((v + rv) / tile).clamp(0, n_ty - 1).long()
    tx0 = torch.floor((u - ru) / tile)
    tx1 = torch.floor((u + ru) / tile)
    if wrap_width > 0:
        full = (tx1 - tx0 + 1) >= n_tx
        tx0 = torch.where(full, torch.zeros_like(tx0), tx0).long()
        tx1 = torch.where(full, torch.full_like(tx1, n_tx - 1), tx1).long()
    else:
        tx0 = tx0.clamp(0, n_tx - 1).long()
        tx1 = tx1.clamp(0, n_tx - 1).long()
    return tx0, tx1, ty0, ty1


def bin_gaussians(
    means2d: torch.Tensor,
    radii: torch.Tensor,
    height: int,
    width: int,
    wrap_width: float,
    tile: int = TILE_SIZE,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-tile lists of Gaussian indices in input (depth) order.

    Returns ``offsets`` (n_tiles + 1,) and ``ids`` (pairs,): tile t owns ids[offsets[t]:offsets[t+1]].
    """
    device = means2d.device
    n_tx = math.ceil(width / tile)
    n_ty = math.ceil(height / tile)
    m = means2d.shape[0]
    tx0, tx1, ty0, ty1 = tile_ranges(means2d, radii, height, width, wrap_width, tile)
    nx = tx1 - tx0 + 1
    ny = ty1 - ty0 + 1
    counts = nx * ny
    gid = torch.repeat_interleave(torch.arange(m, device=device), counts)
    start = torch.cumsum(counts, 0) - counts
    local = torch.arange(gid.numel(), device=device) - start[gid]
    tx = torch.remainder(tx0[gid] + local % nx[gid], n_tx)
    ty = ty0[gid] + local // nx[gid]
    key = (ty * n_tx + tx) * max(m, 1) + gid  # sort by tile, then by depth rank
    key, order = torch.sort(key)
    ids = gid[order]
    tiles = key // max(m, 1)
    offsets = torch.zeros(n_tx * n_ty + 1, dtype=torch.long, device=device)
    offsets[1:] = torch.cumsum(torch.bincount(tiles, minlength=n_tx * n_ty), 0)
    return offsets, ids


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
    """Tile-binned compositing; same contract and result as the dense reference."""
    from image2sim.simulator.splatting.project import CUTOFF_SIGMA

    dtype, device = means2d.dtype, means2d.device
    d = values.shape[1]
    if radii is None:  # recover the footprint box from the conic (inverse of the covariance)
        a_, b_, c_ = conics.detach().unbind(-1)
        det = a_ * c_ - b_ * b_
        radii = CUTOFF_SIGMA * torch.sqrt(torch.stack((c_ / det, a_ / det), dim=-1))
    n_tx = math.ceil(width / tile)
    n_ty = math.ceil(height / tile)
    n_tiles = n_tx * n_ty
    offsets, ids = bin_gaussians(means2d, radii, height, width, wrap_width, tile)
    lengths = offsets[1:] - offsets[:-1]

    # Pixel centres of every tile (tiles may overhang the image; those pixels are dropped).
    ly, lx = torch.meshgrid(
        torch.arange(tile, device=device), torch.arange(tile, device=device), indexing="ij"
    )
    ly, lx = ly.reshape(-1), lx.reshape(-1)
    tile_idx = torch.arange(n_tiles, device=device)
    pix_x = (tile_idx % n_tx).unsqueeze(1) * tile + lx  # (n_tiles, tile^2) integer columns
    pix_y = (tile_idx // n_tx).unsqueeze(1) * tile + ly
    inside = (pix_x < width) & (pix_y < height)

    out = torch.zeros(n_tiles, tile * tile, d, dtype=dtype, device=device)
    alpha_out = torch.zeros(n_tiles, tile * tile, dtype=dtype, device=device)
    out_parts, alpha_parts, tiles_done = [], [], []
    busy = torch.nonzero(lengths > 0).squeeze(1)
    if busy.numel():
        lens = lengths[busy]
        # Chunk busy tiles so that chunk_tiles * tile^2 * max_len stays bounded.
        pos = 0
        lens_list = lens.tolist()
        while pos < busy.numel():
            kmax = lens_list[pos]
            end = pos + 1
            while end < busy.numel():
                k_new = max(kmax, lens_list[end])
                if (end - pos + 1) * tile * tile * k_new > _CHUNK_ELEMENTS:
                    break
                kmax = k_new
                end += 1
            t = busy[pos:end]
            slot = torch.arange(kmax, device=device)
            valid_slot = slot.unsqueeze(0) < lengths[t].unsqueeze(1)  # (Tc, K)
            gather = torch.where(valid_slot, offsets[t].unsqueeze(1) + slot, torch.zeros_like(slot))
            g = torch.where(
                valid_slot, ids[gather.clamp_max(max(ids.numel() - 1, 0))], torch.zeros_like(gather)
            )
            mu = means2d[g]  # (Tc, K, 2)
            px = pix_x[t].to(dtype) + 0.5
            py = pix_y[t].to(dtype) + 0.5
            dx = wrap_offset(px.unsqueeze(-1) - mu[:, None, :, 0], wrap_width)  # (Tc, P, K)
            dy = py.unsqueeze(-1) - mu[:, None, :, 1]
            op = torch.where(valid_slot, opacities[g], torch.zeros_like(opacities[g]))
            w = composite(dx, dy, conics[g].unsqueeze(1), op.unsqueeze(1), t_min)
            out_parts.append(torch.einsum("tpk,tkd->tpd", w, values[g]))
            alpha_parts.append(w.sum(-1))
            tiles_done.append(t)
            pos = end
        t_all = torch.cat(tiles_done)
        out = out.index_put((t_all,), torch.cat(out_parts))
        alpha_out = alpha_out.index_put((t_all,), torch.cat(alpha_parts))

    out = out + (1.0 - alpha_out).unsqueeze(-1) * background
    # Scatter tiles back into the image, dropping overhanging pixels.
    flat = (pix_y * width + pix_x)[inside]
    image = torch.zeros(height * width, d, dtype=dtype, device=device).index_put((flat,), out[inside])
    alpha_img = torch.zeros(height * width, dtype=dtype, device=device).index_put((flat,), alpha_out[inside])
    return image.transpose(0, 1).reshape(d, height, width), alpha_img.reshape(1, height, width)
