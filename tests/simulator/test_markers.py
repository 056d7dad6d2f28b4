"""Goal marker: analytic ray/cylinder hits against ray marching, depth conventions, occlusion, seams."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from image2sim.simulator.config import ConfigError
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera
from image2sim.simulator.markers import GoalMarker, MarkedRenderFn, composite_marker, ray_cylinder_distance


def _march(origin, d, base, radius, height, step=1e-3, far=12.0):
    """Reference (slow, readable): the first crossing of the side surface along the ray, entering or
    leaving, whose height lies in the band (an open tube: through the top one sees the inner wall)."""
    s = np.arange(0.0, far, step)
    p = origin[None] + s[:, None] * d[None]
    outside = np.hypot(p[:, 0] - base[0], p[:, 1] - base[1]) > radius
    cross = np.nonzero(outside[1:] != outside[:-1])[0]
    for k in cross:
        z = p[k + 1, 2]
        if base[2] <= z <= base[2] + height:
            return s[k + 1]
    return math.inf


def test_head_on_hit_distance_and_normal():
    s, n = ray_cylinder_distance(
        np.array([-2.0, 0.0, 1.0]), np.array([[1.0, 0.0, 0.0]]), np.zeros(3), 0.5, 2.0
    )
    assert s[0] == pytest.approx(1.5)
    np.testing.assert_allclose(n[0], [-1.0, 0.0, 0.0], atol=1e-12)


def test_random_rays_match_ray_marching():
    rng = np.random.default_rng(0)
    base = np.array([0.3, -0.2, 0.0])
    checked_hits = 0
    for _ in range(300):
        o = np.array([rng.uniform(-3, 3), rng.uniform(-3, 3), rng.uniform(-0.5, 2.5)])
        if rng.random() < 0.2:  # some rays start inside the tube
            o[:2] = base[:2] + rng.uniform(-0.25, 0.25, size=2)
        d = base + np.array([rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6), rng.uniform(-0.5, 2.0)]) - o
        d /= np.linalg.norm(d)
        s, _ = ray_cylinder_distance(o, d[None], base, 0.4, 1.5)
        ref = _march(o, d, base, 0.4, 1.5)
        if math.isinf(ref) or math.isinf(s[0]):
            # disagreement is allowed only for a grazing hit within one marching step of the band edge
            if math.isinf(ref) != math.isinf(s[0]):
                z = o[2] + (s[0] if math.isfinite(s[0]) else ref) * d[2]
                assert min(abs(z - base[2]), abs(z - base[2] - 1.5)) < 2e-3
        else:
            checked_hits += 1
            assert s[0] == pytest.approx(ref, abs=2e-3)
    assert checked_hits > 100


def test_inside_start_hits_far_wall_and_misses():
    base = np.zeros(3)
    s, _ = ray_cylinder_distance(np.array([0.0, 0.0, 1.0]), np.array([[0.0, 1.0, 0.0]]), base, 0.3, 2.0)
    assert s[0] == pytest.approx(0.3)
    # straight up / down: parallel to the axis, no side hit; passing over the top: miss
    s, n = ray_cylinder_distance(
        np.array([-2.0, 0.0, 3.0]),
        np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]]),
        base,
        0.3,
        2.0,
    )
    assert np.all(np.isinf(s)) and np.all(n == 0)


@pytest.mark.parametrize(
    "camera",
    [PinholeCamera.from_fov(90.0, 90.0, 48, 64), EquirectCamera(32, 64)],
    ids=["pinhole-z-depth", "equirect-range"],
)
@pytest.mark.parametrize("yaw", [0.0, math.pi], ids=["ahead", "behind-seam"])
def test_composited_depth_unprojects_onto_the_cylinder(camera, yaw):
    """Depth follows each camera's convention: unprojected marker pixels lie on the surface; a
    marker directly behind a panorama straddles the seam (columns 0 and W-1 both see it)."""
    from image2sim.simulator.conventions import camera_rotation_for_heading

    pose = np.eye(4)
    pose[:3, :3] = camera_rotation_for_heading(0.0)
    pose[:3, 3] = [0.0, 0.0, 1.2]
    if isinstance(camera, PinholeCamera) and yaw:
        pytest.skip("a pinhole camera does not see behind itself")
    base = np.array([2.0 * math.cos(yaw), 2.0 * math.sin(yaw), 0.0])
    marker = GoalMarker(radius=0.25, height=1.6)
    h, w = camera.height, camera.width
    out = composite_marker(
        {"rgb": np.zeros((h, w, 3), np.float32), "depth": np.zeros((h, w), np.float32)},
        camera,
        pose,
        base,
        marker,
    )
    mask = np.all(np.abs(out["rgb"] - 0) > 0, axis=-1) | (out["depth"] > 0)
    assert mask.sum() > 10
    pts = camera.unproject(torch.from_numpy(out["depth"]).double()).numpy()[mask]
    world = pts @ pose[:3, :3].T + pose[:3, 3]
    radial = np.hypot(world[:, 0] - base[0], world[:, 1] - base[1])
    np.testing.assert_allclose(radial, 0.25, atol=1e-4)
    assert world[:, 2].min() >= -1e-6 and world[:, 2].max() <= 1.6 + 1e-6
    # magenta, shaded: the red and blue channels equal, green zero
    rgb = out["rgb"][mask]
    np.testing.assert_allclose(rgb[:, 0], rgb[:, 2])
    assert np.all(rgb[:, 1] == 0) and rgb[:, 0].min() >= 0.55 - 1e-6
    if isinstance(camera, EquirectCamera) and yaw:
        assert mask[:, 0].any() and mask[:, -1].any()


def test_scene_in_front_occludes_the_marker_and_invalid_depth_does_not():
    camera = PinholeCamera.from_fov(90.0, 90.0, 16, 16)
    from image2sim.simulator.conventions import camera_rotation_for_heading

    pose = np.eye(4)
    pose[:3, :3] = camera_rotation_for_heading(0.0)
    pose[:3, 3] = [0.0, 0.0, 1.0]
    base = np.array([3.0, 0.0, 0.0])
    rgb = np.full((16, 16, 3), 0.5, np.float32)
    near = composite_marker(
        {"rgb": rgb, "depth": np.full((16, 16), 1.0, np.float32)}, camera, pose, base, GoalMarker()
    )
    np.testing.assert_array_equal(near["rgb"], rgb)  # a wall at 1 m hides a pillar at 3 m
    far = {"rgb": rgb, "depth": np.full((16, 16), 5.0, np.float32), "extra": 1}
    for depth in (
        np.full((16, 16), 5.0, np.float32),
        np.zeros((16, 16), np.float32),
        np.full((16, 16), np.nan, np.float32),
    ):
        res = composite_marker({**far, "depth": depth}, camera, pose, base, GoalMarker(radius=0.4))
        hit = res["rgb"][..., 1] == 0  # magenta has no green; the scene is grey
        assert (
            hit[:, 7:9].any(axis=0).all() and not hit[:, 0].any()
        )  # centre columns see it, the edge does not
        assert res["depth"][hit].min() == pytest.approx(3.0 - 0.4, abs=0.05)
        assert np.all(res["depth"][hit] < 3.0) and np.all(np.isfinite(res["depth"][hit]))
    assert res["extra"] == 1
    with pytest.raises(ValueError, match="does not match"):
        composite_marker({"rgb": rgb[:8], "depth": depth[:8]}, camera, pose, base, GoalMarker())


def test_marked_render_fn_and_simulator_set_goal():
    calls = []

    def render(camera, pose):
        calls.append(1)
        return {
            "rgb": np.zeros((camera.height, camera.width, 3), np.float32),
            "depth": np.zeros((camera.height, camera.width), np.float32),
        }

    fn = MarkedRenderFn(render, GoalMarker())
    cam = PinholeCamera.from_fov(90.0, 90.0, 8, 8)
    pose = np.eye(4)
    np.testing.assert_array_equal(fn(cam, pose)["rgb"], 0)  # no goal: the wrapped output
    with pytest.raises(ValueError, match="finite world point"):
        fn.set_goal([0.0, np.nan, 0.0])
    with pytest.raises(ValueError, match="finite world point"):
        fn.set_goal([0.0, 1.0])
    fn.set_goal([0.0, 0.0, 0.0])
    fn.set_goal(None)
    assert fn.goal is None and len(calls) == 1


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"radius": 0.0}, "radius"),
        ({"height": float("nan")}, "height"),
        ({"colour": [1.0, 2.0, 0.0]}, "colour"),
        ({"colour": [1.0, 0.0]}, "colour"),
    ],
)
def test_marker_config_errors_name_the_field(kwargs, field):
    with pytest.raises(ConfigError, match=field):
        GoalMarker(**kwargs)
