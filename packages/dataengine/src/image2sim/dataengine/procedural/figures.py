"""Documentation figures: a rendered panorama (RGB / depth / semantics) and a top-down GT map.

Run ``python -m image2sim.dataengine.procedural.figures docs/img`` to regenerate
``procedural_panorama.png`` and ``procedural_topdown.png`` (deterministic for a given seed).
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
from image2sim.dataengine.procedural.capture import pose_matrix, sample_viewpoints
from image2sim.dataengine.procedural.config import preset
from image2sim.dataengine.procedural.gt import OBSTACLE
from image2sim.dataengine.procedural.render import render
from image2sim.dataengine.procedural.scene import ProceduralScene, generate_scene, seed_streams
from image2sim.simulator.geometry.cameras import EquirectCamera

__all__ = ["label_colors", "panorama_figure", "topdown_figure", "main"]


def label_colors(labels: np.ndarray) -> np.ndarray:
    """Stable pseudo-random RGB colour per integer label (0 -> black)."""
    lab = labels.astype(np.uint32)
    h = lab * np.uint32(2654435761)
    rgb = np.stack([(h >> np.uint32(s)) & np.uint32(255) for s in (0, 8, 16)], axis=-1).astype(np.uint8)
    rgb = (rgb // 2 + 96).astype(np.uint8)
    rgb[labels == 0] = 0
    return rgb


def _depth_colors(depth: np.ndarray, max_depth: float) -> np.ndarray:
    scaled = np.clip(depth / max_depth * 255.0, 0, 255).astype(np.uint8)
    bgr = cv2.applyColorMap(255 - scaled, cv2.COLORMAP_TURBO)
    bgr[depth <= 0] = 0
    return bgr[..., ::-1]


def panorama_figure(scene: ProceduralScene, pose: np.ndarray, height: int = 256) -> np.ndarray:
    """RGB over depth (turbo colour map) over category colours, one equirectangular panorama each."""
    out = render(scene, EquirectCamera(height, 2 * height), pose)
    return np.concatenate(
        [out["rgb"], _depth_colors(out["depth"], float(out["depth"].max())), label_colors(out["semantics"])],
        axis=0,
    )


def topdown_figure(scene: ProceduralScene, views: list, scale: int = 4) -> np.ndarray:
    """Top-down ground truth: navigable floor (white), unsafe free floor (light grey), object footprints
    (category colours), walls/outside (dark), doors (green), camera positions (red, in capture order)."""
    g = scene.grid
    h, w = g.occupancy.shape
    img = np.full((h, w, 3), 40, dtype=np.uint8)
    img[g.occupancy == 1] = (190, 190, 190)
    img[g.navigable] = (250, 250, 250)
    cat = np.zeros((h, w), dtype=np.int32)
    for obj in sorted(scene.objects, key=lambda o: o.aabb[1][2]):
        if obj.support:
            continue
        lo, hi = obj.aabb
        ix0, iy0 = np.floor((lo[:2] - g.origin) / g.resolution).astype(int)
        ix1, iy1 = np.ceil((hi[:2] - g.origin) / g.resolution).astype(int)
        cat[max(iy0, 0) : iy1, max(ix0, 0) : ix1] = obj.category.id
    colors = label_colors(cat)
    sel = (cat > 0) & ((g.occupancy == OBSTACLE) | (g.occupancy == 1))
    img[sel] = colors[sel]
    img = np.repeat(np.repeat(img, scale, axis=0), scale, axis=1)

    def px(x: float, y: float) -> tuple[int, int]:
        return int(round((x - g.origin[0]) / g.resolution * scale)), int(
            round((y - g.origin[1]) / g.resolution * scale)
        )

    t = scene.layout.wall_thickness
    for d in scene.layout.doors:
        x0, y0, x1, y1 = d.passage(t)
        cv2.rectangle(img, px(x0, y0), px(x1, y1), (40, 170, 60), thickness=-1)
    pts = [px(v.position[0], v.position[1]) for v in views]
    for a, b in zip(pts[:-1], pts[1:], strict=False):
        cv2.line(img, a, b, (220, 60, 60), 1, lineType=cv2.LINE_AA)
    for p in pts:
        cv2.circle(img, p, max(2, scale), (220, 30, 30), -1, lineType=cv2.LINE_AA)
    img = img[::-1].copy()  # world +Y up; labels are drawn after the flip
    H = img.shape[0]
    for room in scene.layout.rooms:
        x0, y0, x1, y1 = room.interior(t)
        cx, cy = px(0.5 * (x0 + x1), 0.5 * (y0 + y1))
        cv2.putText(
            img,
            room.room_type,
            (cx - 30, H - cy),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.4,
            (20, 20, 120),
            1,
            cv2.LINE_AA,
        )
    return img


def main(argv: list[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    out_dir = Path(argv[0] if argv else "docs/img")
    seed = int(argv[1]) if len(argv) > 1 else 0
    out_dir.mkdir(parents=True, exist_ok=True)
    cfg = preset("default")
    scene = generate_scene(cfg, seed)
    views = sample_viewpoints(scene, cfg.capture.views, seed_streams(seed)["capture"])
    pano = panorama_figure(scene, pose_matrix(views[0]))
    cv2.imwrite(str(out_dir / "procedural_panorama.png"), pano[..., ::-1])
    top = topdown_figure(scene, views)
    cv2.imwrite(str(out_dir / "procedural_topdown.png"), top[..., ::-1])
    print(f"wrote {out_dir / 'procedural_panorama.png'} and {out_dir / 'procedural_topdown.png'}")


if __name__ == "__main__":
    main()
