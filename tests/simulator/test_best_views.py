"""Best-view selection (gaussians.views): each surface point modelled once, by the frame that sees it best.

Analytic scenes: pinhole frames looking at planes, where which frame sees what (and how finely) is
known exactly; a slow per-point reference of the rule; the hard cases (thin walls seen from both
sides, occlusion, identical views, invalid depth, panoramas across the seam).
"""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from image2sim.simulator.gaussians import tiny
from image2sim.simulator.gaussians.config import ConfigError
from image2sim.simulator.gaussians.encoder import identity_gaussians
from image2sim.simulator.gaussians.primitives import FrameInputs, GaussianSet
from image2sim.simulator.gaussians.scene import GaussianScene
from image2sim.simulator.gaussians.views import (
    _pixel_index,
    best_view_mask,
    extent_points,
    keep_best,
    own_geometry,
    select_best_views,
    view_map,
)
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera

H = W = 32
CAM = PinholeCamera.from_fov(90.0, 90.0, H, W)
# Camera axes (columns) in the world for looking along +X and along -X, upright (world Z up).
LOOK_PX = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
LOOK_NX = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.0, -1.0, 0.0]], dtype=torch.float64)


def pose(x: float, look: torch.Tensor, y: float = 0.0) -> torch.Tensor:
    p = torch.eye(4, dtype=torch.float64)
    p[:3, :3] = look
    p[:3, 3] = torch.tensor([x, y, 0.0], dtype=torch.float64)
    return p


def plane_frame(x_cam: float, plane_x: float, look=LOOK_PX, y: float = 0.0, colour=0.5) -> FrameInputs:
    """A pinhole frame at (x_cam, y, 0) looking along +-X at the plane x = plane_x (z-depth)."""
    depth = torch.full((1, 1, H, W), abs(plane_x - x_cam), dtype=torch.float32)
    rgb = torch.full((1, 3, H, W), colour, dtype=torch.float32)
    return FrameInputs(rgb, depth, CAM, pose(x_cam, look, y), f"x{x_cam}")


def cfg(**fusion):
    c = tiny()
    return dataclasses.replace(c, fusion=dataclasses.replace(c.fusion, **fusion))


def select(frames, **fusion):
    c = cfg(**fusion)
    sets = [identity_gaussians(f, c) for f in frames]
    views = [view_map(f, c.fusion) for f in frames]
    return sets, select_best_views(sets, views, c.fusion)


def test_the_nearer_view_keeps_the_shared_surface_and_the_farther_keeps_only_the_rest():
    near, far = plane_frame(0.0, 2.0), plane_frame(-2.0, 2.0)
    (n0, f0), (n1, f1) = select([near, far])
    assert len(n1) == len(n0)  # nothing sees the near view's surface better
    # The far view sees y, z in [-4, 4]; the near one only [-2, 2]: the far keeps the outer ring.
    inner = (f1.means[:, 1].abs() < 1.9) & (f1.means[:, 2].abs() < 1.9)
    assert len(f1) < len(f0) and not bool(inner.any())
    assert bool(((f1.means[:, 1].abs() > 2.1) | (f1.means[:, 2].abs() > 2.1)).all())


def test_the_two_sides_of_a_thin_wall_are_both_kept():
    # Faces 2 cm apart, seen from opposite rooms: inside the depth tolerance of each other, but each
    # faces only its own camera.
    front, back = plane_frame(0.0, 2.0), plane_frame(4.0, 2.02, LOOK_NX)
    (a0, b0), (a1, b1) = select([front, back], same_surface_tolerance=0.05)
    assert len(a1) == len(a0) and len(b1) == len(b0)


def test_a_surface_occluded_for_the_better_view_is_kept():
    # The near camera sees a nearer box face (x = 1), not the plane at x = 2 behind it.
    near = plane_frame(0.0, 1.0)
    far = plane_frame(-2.0, 2.0)
    (_, f0), (_, f1) = select([near, far])
    assert len(f1) == len(f0)


def test_identical_views_saturate_one_frame_keeps_everything():
    frames = [plane_frame(0.0, 2.0) for _ in range(4)]
    sets, kept = select(frames)
    assert [len(k) for k in kept] == [len(sets[0]), 0, 0, 0]
    c = cfg()
    scene = GaussianScene(fusion=c.fusion)
    scene.integrate_many(kept)
    once = GaussianScene(fusion=c.fusion)
    once.integrate_many([sets[0]])
    assert len(scene) == len(once)


def test_invalid_depth_in_the_better_view_replaces_nothing():
    near, far = plane_frame(0.0, 2.0), plane_frame(-2.0, 2.0)
    near.depth[..., : H // 2, :] = 0.0  # the top half has no depth
    near.depth[..., H // 2, 0] = float("nan")
    (_, f0), (_, f1) = select([near, far])
    # The far view keeps the upper part of the shared region (world z > 0 is the image top).
    assert bool(((f1.means[:, 2] > 0.2) & (f1.means[:, 1].abs() < 1.5)).any())
    assert bool(torch.isfinite(f1.means).all())


def test_panorama_points_across_the_seam_find_their_pixel():
    cam = EquirectCamera(16, 32)
    # A point straight behind the camera (longitude +-pi) projects onto the seam columns.
    pts = torch.tensor([[0.0, 0.0, -1.0], [1e-9, 0.0, -1.0], [-1e-9, 0.0, -1.0], [0.0, -1.0, 1e-12]])
    uv, _, ok = cam.project(pts.double())
    row, col, inside = _pixel_index(cam, uv)
    assert bool(ok.all() and inside.all())
    assert int(col.min()) >= 0 and int(col.max()) <= 31 and int(row.max()) <= 15
    assert set(col[:3].tolist()) <= {0, 31}


def reference_mask(means, intervals, normals, own, views, tolerance, step, owner_cos=0.0):
    """The rule point by point, in plain Python (the readable reference of best_view_mask)."""
    keep = []
    for p, q, nrm in zip(
        means.double().tolist(), intervals.double().tolist(), normals.double().tolist(), strict=True
    ):
        facing = nrm
        if all(v == 0 for v in facing):
            c = views[own].centre.tolist()
            d = [c[k] - p[k] for k in range(3)]
            length = math.sqrt(sum(v * v for v in d)) or 1e-12
            facing = [v / length for v in d]
        dropped = False
        for i, view in enumerate(views):
            if i == own:
                continue
            c = view.centre.tolist()
            off = [c[k] - p[k] for k in range(3)]
            if sum(off[k] * facing[k] for k in range(3)) <= 0:
                continue
            if math.sqrt(sum(v * v for v in off)) * view.min_pixel_angle > q:
                continue
            R, t = view.world_to_cam[:3, :3], view.world_to_cam[:3, 3]
            cam_pt = R @ torch.tensor(p, dtype=torch.float64) + t
            uv, rng, ok = view.camera.project(cam_pt[None])
            row, col, inside = _pixel_index(view.camera, uv)
            if not (bool(ok[0]) and bool(inside[0])):
                continue
            d = float(view.depth[row[0], col[0]])
            iv = float(view.interval[row[0], col[0]])
            if not (d > 0 and abs(float(rng[0]) - d) <= tolerance * d + 2.0 * iv):
                continue
            n = view.normals[row[0], col[0]].double().tolist()
            length = math.sqrt(sum(v * v for v in off)) or 1e-12
            if abs(sum(n[k] * off[k] / length for k in range(3))) < owner_cos:
                continue
            mine = q
            if step > 1.0:
                iv, mine = (
                    math.floor(math.log(iv) / math.log(step)),
                    math.floor(math.log(mine) / math.log(step)),
                )
            if iv < mine or (iv == mine and i < own):
                dropped = True
                break
        keep.append(not dropped)
    return torch.tensor(keep)


@pytest.mark.parametrize("step, owner_cos", [(1.0, 0.0), (1.5, 0.0), (1.5, 0.5)])
def test_vectorised_rule_matches_the_reference(step, owner_cos):
    g = torch.Generator().manual_seed(0)
    frames = []
    for k in range(4):
        f = plane_frame(-0.5 * k, 2.0, y=0.3 * k)
        f.depth += 0.05 * torch.rand(f.depth.shape, generator=g)  # a bumpy surface, noisy normals
        frames.append(f)
    frames.append(plane_frame(4.0, 2.01, LOOK_NX))
    c = cfg(interval_step=step)
    views = [view_map(f, c.fusion) for f in frames]
    for own, f in enumerate(frames):
        gs = identity_gaussians(f, c)
        iv, nrm = own_geometry(gs.means, views[own])
        tol = c.fusion.same_surface_tolerance
        slow = reference_mask(gs.means, iv, nrm, own, views, tol, step, owner_cos)
        for backend in backends():
            fast = best_view_mask(
                gs.means, iv, nrm, own, views, tol, step, owner_cos=owner_cos, backend=backend
            )
            assert torch.equal(fast, slow), backend


def backends() -> list[str]:
    """The torch loop, and the compiled kernel where it builds (CI builds it)."""
    from image2sim.simulator.splatting.backends import cpu_kernel

    return ["torch", "cpu"] if cpu_kernel.available() else ["torch"]


def room_frame(centre, camera, seed: int) -> FrameInputs:
    """A frame inside the box room [-3, 3] x [-2, 2] x [-1.4, 1.4] (bumpy walls, a pillar at the
    origin that occludes), with a few invalid pixels: range or z, as the camera stores depth."""
    from image2sim.simulator.geometry.cameras import PinholeCamera as Pin

    g = torch.Generator().manual_seed(seed)
    rays = camera.ray_map(torch.float64)  # (3, H, W), camera frame = world axes here
    c = torch.tensor(centre, dtype=torch.float64)[:, None, None]
    half = torch.tensor([3.0, 2.0, 1.4], dtype=torch.float64)[:, None, None]
    with torch.no_grad():
        t_wall = torch.where(rays != 0, (torch.sign(rays) * half - c) / rays, torch.full_like(rays, math.inf))
        t = t_wall.min(dim=0).values
        # The pillar: a vertical cylinder of radius 0.4 about the z axis.
        a = rays[0] ** 2 + rays[1] ** 2
        b = 2 * (c[0, 0, 0] * rays[0] + c[1, 0, 0] * rays[1])
        cc = c[0, 0, 0] ** 2 + c[1, 0, 0] ** 2 - 0.16
        disc = b * b - 4 * a * cc
        t_pil = (-b - torch.sqrt(disc.clamp_min(0))) / (2 * a.clamp_min(1e-12))
        t = torch.where((disc > 0) & (t_pil > 0), torch.minimum(t, t_pil), t)
        t = t * (1 + 0.01 * torch.rand(t.shape, generator=g, dtype=torch.float64))
        depth = t * rays[2] if isinstance(camera, Pin) else t
    depth = depth.float()[None, None]
    depth[..., 3, 5] = 0.0
    depth[..., 7, 2] = float("nan")
    p = torch.eye(4, dtype=torch.float64)
    p[:3, 3] = torch.tensor(centre, dtype=torch.float64)
    rgb = torch.rand((1, 3, camera.height, camera.width), generator=g)
    return FrameInputs(rgb, depth, camera, p, f"room{seed}")


def test_kernel_matches_the_torch_loop_on_panoramas_and_pinholes_with_carving():
    """The compiled kernel against the torch loop on a room seen by panoramas and pinhole views at
    once: carving with extent points, quantised intervals, the owner test, invalid depth, points
    on the seam, at a camera centre, behind the pinhole cameras and non-finite ones."""
    if backends() == ["torch"]:
        pytest.skip("the compiled CPU kernel does not build here")
    pano, pin = EquirectCamera(24, 48), PinholeCamera.from_fov(80.0, 70.0, 20, 24)
    frames = [
        room_frame((-1.8, 0.5, 0.1), pano, 0),
        room_frame((1.5, -0.9, 0.0), pano, 1),
        room_frame((0.2, 1.3, 0.3), pin, 2),
        room_frame((2.2, 1.0, -0.2), pin, 3),
        room_frame((-0.9, -1.2, 0.0), pano, 4),
    ]
    c = cfg(carve_views=2, interval_step=1.5, owner_cos=0.3)
    views = [view_map(f, c.fusion) for f in frames]
    for own, f in enumerate(frames):
        gs = identity_gaussians(f, c)
        means = torch.cat(
            (
                gs.means.double(),
                torch.tensor(
                    [
                        [-1.8, 0.5, 0.1],
                        [1.5 - 1e-9, -0.9, 0.0],
                        [float("nan"), 0, 0],
                        [0.2, -3.0, 0.3],
                        [9, 9, 9],
                    ],
                    dtype=torch.float64,
                ),
            )
        )
        iv, nrm = own_geometry(means, views[own])
        extent = torch.cat((extent_points(gs, 3.0), means[-5:, None].expand(-1, 4, -1)))
        args = (means, iv, nrm, own, views, c.fusion.same_surface_tolerance, 1.5, 2, 0.3, extent)
        torch_mask = best_view_mask(*args, backend="torch")
        assert torch.equal(best_view_mask(*args, backend="cpu"), torch_mask), own
        assert 0 < int(torch_mask.sum()) < len(torch_mask)  # the case drops some and keeps some


def test_an_unknown_backend_is_refused():
    f = plane_frame(0.0, 2.0)
    v = view_map(f, cfg().fusion)
    pts = torch.zeros(1, 3)
    with pytest.raises(ValueError, match="backend must be one of"):
        best_view_mask(pts, torch.ones(1), pts, 0, [v, v], 0.02, backend="gpu")


def test_keep_best_edge_cases():
    c = cfg()
    f = plane_frame(0.0, 2.0)
    g = identity_gaussians(f, c)
    v = view_map(f, c.fusion)
    assert len(keep_best(g, 0, [v], c.fusion)) == len(g)  # one view: nothing to compare with
    empty = g.index(torch.zeros(len(g), dtype=torch.bool))
    assert len(keep_best(empty, 0, [v, v], c.fusion)) == 0
    with pytest.raises(ValueError, match="2 Gaussian sets but 1 views"):
        select_best_views([g, g], [v], c.fusion)


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("views", "some", "fusion.views"),
        ("same_surface_tolerance", 0.0, "same_surface_tolerance"),
        ("grazing_cos", 0.0, "grazing_cos"),
        ("interval_step", 0.5, "interval_step"),
        ("owner_cos", 1.5, "owner_cos"),
    ],
)
def test_bad_best_view_config_is_refused(field, value, message):
    with pytest.raises(ConfigError, match=message):
        cfg(**{field: value}).validate()


def test_points_another_view_saw_through_are_carved_and_silhouettes_are_not():
    c = cfg(carve_views=1)
    wall = plane_frame(0.0, 3.0)
    views = [view_map(wall, c.fusion), view_map(plane_frame(-1.0, 3.0), c.fusion)]
    # Frame 1's points: a floater 1 m in front of the wall on frame 0's central ray, a point on the
    # wall, and one behind it (occluded for frame 0: kept).
    pts = torch.tensor([[2.0, 0.01, 0.01], [3.0, 0.01, 0.01], [3.5, 0.01, 0.01]], dtype=torch.float64)
    iv = torch.full((3,), 0.01, dtype=torch.float64)
    normals = torch.tensor([[-1.0, 0.0, 0.0]] * 3, dtype=torch.float64)
    keep = best_view_mask(pts, iv, normals, 1, views, c.fusion.same_surface_tolerance, 1.0, carve_views=1)
    assert keep.tolist() == [False, True, True]
    assert best_view_mask(pts, iv, normals, 1, views, 0.02, 1.0, carve_views=0).tolist() == [True, True, True]
    # A view with a hole next to the ray does not vouch for the space there (silhouette rule).
    holed = plane_frame(0.0, 3.0)
    holed.depth[..., H // 2 - 1 : H // 2 + 1, W // 2 - 1 : W // 2 + 1] = 0.0
    views[0] = view_map(holed, c.fusion)
    assert best_view_mask(pts, iv, normals, 1, views, 0.02, 1.0, carve_views=1)[0]


def _gaussians(means, scales, quats) -> GaussianSet:
    n = len(means)
    return GaussianSet(
        means=torch.tensor(means, dtype=torch.float32),
        scales=torch.tensor(scales, dtype=torch.float32),
        quats=torch.tensor(quats, dtype=torch.float32),
        opacities=torch.ones(n),
        colors=torch.zeros(n, 3),
        features=torch.zeros(n, 0),
        footprints=torch.ones(n),
        weights=torch.ones(n),
        levels=torch.zeros(n, dtype=torch.int64),
    )


def test_extent_points_lie_k_sigma_out_along_the_two_largest_axes():
    s = math.sqrt(0.5)
    g = _gaussians(
        [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0]],
        [[0.1, 0.3, 0.01], [0.2, 0.05, 0.01]],
        [[1.0, 0.0, 0.0, 0.0], [s, 0.0, 0.0, s]],  # identity; 90 degrees about Z (local x -> world y)
    )
    pts = extent_points(g, 3.0)
    assert pts.shape == (2, 4, 3)
    off = (pts - g.means.double()[:, None]).numpy().round(6)
    # First: largest axis local y (0.3), then local x (0.1); both ways.
    assert sorted(map(tuple, off[0].tolist())) == sorted(
        [(0.0, 0.9, 0.0), (0.3, 0.0, 0.0), (0.0, -0.9, 0.0), (-0.3, 0.0, 0.0)]
    )
    # Second: local x (0.2) is world y after the rotation, local y (0.05) is world -x.
    assert sorted(map(tuple, off[1].tolist())) == sorted(
        [(0.0, 0.6, 0.0), (-0.15, 0.0, 0.0), (0.0, -0.6, 0.0), (0.15, 0.0, 0.0)]
    )


def test_a_splat_reaching_across_a_silhouette_is_carved_by_its_extent():
    """Frame 0 sees a plate 2 m ahead on its left half (world +Y) and the wall 3 m ahead on its right.
    Frame 1's Gaussian sits on the plate 1-2 pixels from the silhouette, so its centre passes the
    carving; its 3-sigma reach (0.3 m along Y) lies in front of the wall where frame 0 saw through."""
    c = cfg(carve_views=1)
    scene = plane_frame(0.0, 3.0)
    scene.depth[..., : W // 2] = 2.0  # image columns grow towards world -Y: the left half is +Y
    views = [view_map(scene, c.fusion), view_map(plane_frame(-1.0, 3.0), c.fusion)]
    g = _gaussians([[2.0, 0.15, 0.0]], [[0.01, 0.1, 0.1]], [[1.0, 0.0, 0.0, 0.0]])
    iv = torch.full((1,), 0.01, dtype=torch.float64)
    normals = torch.tensor([[-1.0, 0.0, 0.0]], dtype=torch.float64)
    args = (g.means, iv, normals, 1, views, c.fusion.same_surface_tolerance, 1.0)
    assert best_view_mask(*args, carve_views=1).tolist() == [True]  # the centre alone passes
    assert best_view_mask(*args, carve_views=1, extent=extent_points(g, 3.0)).tolist() == [False]
    # Kept when the reach stays on the plate (the Gaussian farther from the silhouette), or when
    # frame 0 does not carve.
    inner = _gaussians([[2.0, 0.6, 0.0]], [[0.01, 0.1, 0.1]], [[1.0, 0.0, 0.0, 0.0]])
    assert best_view_mask(
        inner.means, iv, normals, 1, views, 0.02, 1.0, carve_views=1, extent=extent_points(inner, 3.0)
    ).tolist() == [True]
    assert best_view_mask(*args, carve_views=0, extent=extent_points(g, 3.0)).tolist() == [True]


def test_centres_and_extents_of_many_gaussians_are_carved_together():
    """The probes of several Gaussians go through one look-up per view: each Gaussian is dropped
    when its centre *or* any extent point was seen through, and only then (same scene as above)."""
    c = cfg(carve_views=1)
    scene = plane_frame(0.0, 3.0)
    scene.depth[..., : W // 2] = 2.0
    views = [view_map(scene, c.fusion), view_map(plane_frame(-1.0, 3.0), c.fusion)]
    one = [[0.01, 0.1, 0.1]]
    g = _gaussians(
        # a floater before the wall (centre seen through), the plate's rim (reach seen through),
        # the plate's inside (kept), a point behind the wall (occluded for frame 0: kept)
        [[2.5, -0.6, 0.0], [2.0, 0.15, 0.0], [2.0, 0.6, 0.0], [3.5, -0.6, 0.0]],
        one * 4,
        [[1.0, 0.0, 0.0, 0.0]] * 4,
    )
    iv = torch.full((4,), 0.01, dtype=torch.float64)
    normals = torch.tensor([[-1.0, 0.0, 0.0]] * 4, dtype=torch.float64)
    args = (g.means, iv, normals, 1, views, c.fusion.same_surface_tolerance, 1.0)
    assert best_view_mask(*args, carve_views=1, extent=extent_points(g, 3.0)).tolist() == [
        False,
        False,
        True,
        True,
    ]
    assert best_view_mask(*args, carve_views=1).tolist() == [False, True, True, True]


def test_a_grazing_view_does_not_replace_a_frontal_one_it_samples_more_finely():
    """owner_cos: a near view seeing the wall at a grazing angle (cos ~0.2) has a finer interval
    than a far frontal one only by the clamp; with owner_cos 0.5 it may not replace the frontal one."""
    c0, c5 = cfg(owner_cos=0.0, grazing_cos=0.05), cfg(owner_cos=0.5, grazing_cos=0.05)
    frontal = plane_frame(-8.0, 2.0)
    # A camera 0.5 m from the wall, looking along it (+Y): the wall x = 2 is at a grazing angle.
    look_py = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]], dtype=torch.float64)
    grazing = FrameInputs(
        torch.full((1, 3, H, W), 0.5), torch.zeros(1, 1, H, W), CAM, pose(1.5, look_py, -3.0), "graze"
    )
    # Its depth: z-distance along +Y to the wall x = 2 for the pixels that see it, else invalid.
    rays = CAM.ray_map(torch.float64)  # camera frame (x right, y down, z forward)
    world = torch.einsum("ij,jhw->ihw", look_py, rays)
    t = (2.0 - 1.5) / world[0].clamp_min(1e-9)
    z = torch.where(world[0] > 1e-3, t * rays[2], torch.zeros_like(t))
    grazing.depth[0, 0] = z.float()
    sets = [identity_gaussians(f, c0) for f in (frontal, grazing)]
    views0 = [view_map(f, c0.fusion) for f in (frontal, grazing)]
    views5 = [view_map(f, c5.fusion) for f in (frontal, grazing)]
    kept0 = select_best_views(sets, views0, c0.fusion)
    kept5 = select_best_views(sets, views5, c5.fusion)
    # Near its camera the grazing view samples the wall more finely than the far frontal one and
    # takes those Gaussians over; with the rule it keeps only those it sees at a cosine >= 0.5.
    assert len(kept0[0]) < len(kept5[0]) <= len(sets[0])
    assert len(kept0[1]) >= len(kept5[1])
