"""NeuralSimulator with the pixel-flow renderer loaded by path (tiny random weights) vs splat-only."""

from __future__ import annotations

import functools
import math
import types

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("image2sim.simulator.splatting")

from image2sim.simulator.conventions import Action  # noqa: E402
from image2sim.simulator.gaussians import GaussianScene, GaussianSet  # noqa: E402
from image2sim.simulator.geometry.cameras import EquirectCamera, PinholeCamera  # noqa: E402
from image2sim.simulator.navigation import synthetic as syn  # noqa: E402
from image2sim.simulator.navigation.extract import extract_navmap_from_points  # noqa: E402
from image2sim.simulator.renderer import tiny  # noqa: E402
from image2sim.simulator.renderer.model import PixelFlowRenderer, save_renderer  # noqa: E402
from image2sim.simulator.sim import (  # noqa: E402
    GaussianRenderFn,
    NeuralSimulator,
    ObservationSpec,
    PixelFlowRenderFn,
    gaussian_render_fn,
    gaussian_tensors,
    panorama_height_for,
    views_from_panorama,
)

PANO_H = 16


@functools.cache
def navmap():
    w = syn.box_room(spacing=0.04)
    return extract_navmap_from_points(w.points, w.normals, camera_positions=w.camera_positions)


def _gaussians(n: int = 200, seed: int = 0) -> GaussianSet:
    """Random coloured blobs around the agent's eye (x 2..5, y 1..3, z 0.3..2.2 m)."""
    g = torch.Generator().manual_seed(seed)
    q = torch.randn(n, 4, generator=g)
    lo, hi = torch.tensor([2.0, 1.0, 0.3]), torch.tensor([5.0, 3.0, 2.2])
    return GaussianSet(
        means=lo + torch.rand(n, 3, generator=g) * (hi - lo),
        scales=torch.rand(n, 3, generator=g) * 0.1 + 0.05,
        quats=q / q.norm(dim=1, keepdim=True),
        opacities=torch.rand(n, generator=g) * 0.5 + 0.4,
        colors=torch.rand(n, 3, generator=g),
        features=torch.randn(n, 4, generator=g),  # not the renderer's 16: the condition uses zeros
        footprints=torch.rand(n, generator=g) * 0.05,
        weights=torch.ones(n),
        levels=torch.zeros(n, dtype=torch.long),
    )


@pytest.fixture(scope="module")
def scene_and_ckpt(tmp_path_factory):
    root = tmp_path_factory.mktemp("simr")
    folder = root / "scene"
    GaussianScene(gaussians=_gaussians(), info={"camera": EquirectCamera(PANO_H, 2 * PANO_H).to_dict()}).save(
        folder
    )
    navmap().save(folder / "navmap.npz")
    torch.manual_seed(0)
    ckpt = root / "renderer.safetensors"
    save_renderer(PixelFlowRenderer(tiny()), ckpt)
    return folder, ckpt


SPEC = ObservationSpec(
    pano_height=PANO_H, pinhole=True, pinhole_size=12, ultrawide=True, ultrawide_width=20, ultrawide_height=14
)


def test_renderer_by_path_observations_shapes_ranges_and_pose_determinism(scene_and_ckpt):
    folder, ckpt = scene_and_ckpt
    sim = NeuralSimulator.from_scene(folder, observations=SPEC, renderer=ckpt, steps=1, backend="torch")
    assert isinstance(sim.render_fn, PixelFlowRenderFn) and sim.render_fn.steps == 1
    obs, _ = sim.reset(np.array([[3.0, 2.0, 0.0]]), np.array([0.0]))
    o = obs[0]
    shapes = {"panorama": (PANO_H, 2 * PANO_H), "pinhole": (12, 12), "ultrawide": (14, 20)}
    for key, hw in shapes.items():
        assert o[key]["rgb"].shape == (*hw, 3) and o[key]["depth"].shape == hw, key
        assert o[key]["rgb"].dtype == np.float32
        assert np.isfinite(o[key]["rgb"]).all() and np.isfinite(o[key]["depth"]).all()
        assert o[key]["rgb"].min() >= 0.0 and o[key]["rgb"].max() <= 1.0
        assert o[key]["depth"].min() >= 0.0
    # Same pose -> same image (per-pose noise); a turn then back returns to the same pose.
    again = sim.observe(0)
    assert np.array_equal(again["panorama"]["rgb"], o["panorama"]["rgb"])
    sim.step([Action.TURN_LEFT], observe=False)
    turned = sim.observe(0)["panorama"]["rgb"]
    sim.step([Action.TURN_RIGHT], observe=False)
    back = sim.observe(0)["panorama"]["rgb"]
    assert np.array_equal(back, o["panorama"]["rgb"])
    assert not np.array_equal(turned, back)
    # A second simulator (fresh model load) renders the identical image at the same pose.
    sim2 = NeuralSimulator.from_scene(folder, observations=SPEC, renderer=str(ckpt), steps=1, backend="torch")
    obs2, _ = sim2.reset(np.array([[3.0, 2.0, 0.0]]), np.array([0.0]))
    assert np.array_equal(obs2[0]["panorama"]["rgb"], o["panorama"]["rgb"])


def test_renderer_noise_seed_and_steps_change_the_image(scene_and_ckpt):
    folder, ckpt = scene_and_ckpt
    spec = ObservationSpec(pano_height=PANO_H)
    pose = [[3.0, 2.0, 0.0]]
    ims = {}
    for steps, seed in ((1, 0), (1, 1), (2, 0)):
        sim = NeuralSimulator.from_scene(folder, spec, renderer=ckpt, steps=steps, seed=seed, backend="torch")
        ims[(steps, seed)] = sim.reset(np.array(pose), np.array([0.0]))[0][0]["panorama"]["rgb"]
    assert not np.array_equal(ims[(1, 0)], ims[(1, 1)])
    assert not np.array_equal(ims[(1, 0)], ims[(2, 0)])


def test_without_renderer_splat_only_is_used(scene_and_ckpt):
    folder, _ = scene_and_ckpt
    sim = NeuralSimulator.from_scene(
        folder, observations=ObservationSpec(pano_height=PANO_H), backend="torch"
    )
    assert isinstance(sim.render_fn, GaussianRenderFn) and sim.render_fn.renderer is None
    obs, _ = sim.reset(np.array([[3.0, 2.0, 0.0]]), np.array([0.0]))
    # Splat-only equals a direct splat of the scene at the agent's camera pose, as expected colour
    # and range (the composite divided by alpha: eval render's splat_only).
    from image2sim.simulator.renderer.condition import unpremultiply
    from image2sim.simulator.sim import OBSERVATION_MIN_TRANSMITTANCE

    scene = GaussianScene.load(folder)
    ref = scene.render(
        EquirectCamera(PANO_H, 2 * PANO_H),
        torch.as_tensor(sim.camera_pose(0), dtype=torch.float32),
        backend="torch",
        min_transmittance=OBSERVATION_MIN_TRANSMITTANCE,
    )
    rgb, depth = unpremultiply(ref.rgb, ref.depth, ref.alpha)
    np.testing.assert_allclose(obs[0]["panorama"]["rgb"], rgb[0].permute(1, 2, 0).numpy(), atol=1e-6)
    np.testing.assert_allclose(obs[0]["panorama"]["depth"], depth[0, 0].numpy(), atol=1e-5)


def test_bad_renderer_path_names_the_file(scene_and_ckpt, tmp_path):
    folder, _ = scene_and_ckpt
    with pytest.raises(FileNotFoundError, match="nope.safetensors"):
        NeuralSimulator.from_scene(folder, renderer=tmp_path / "nope.safetensors")


def test_pixel_flow_render_fn_rejects_non_panoramic_cameras(scene_and_ckpt):
    _, ckpt = scene_and_ckpt
    from image2sim.simulator.renderer.model import load_renderer

    g = _gaussians()
    fn = PixelFlowRenderFn(
        {k: getattr(g, k) for k in ("means", "scales", "quats", "opacities", "colors")}, load_renderer(ckpt)
    )
    with pytest.raises(ValueError, match="panoramas only"):
        fn(PinholeCamera.from_fov(90, 90, 8, 8), np.eye(4))
    with pytest.raises(ValueError, match="steps"):
        PixelFlowRenderFn(
            {k: getattr(g, k) for k in ("means", "scales", "quats", "opacities", "colors")},
            load_renderer(ckpt),
            steps=0,
        )


def test_gaussian_render_fn_picks_the_render_function_and_keeps_optional_features(scene_and_ckpt):
    _, ckpt = scene_and_ckpt
    g = _gaussians()
    assert set(gaussian_tensors(g)) == {"means", "scales", "quats", "opacities", "colors", "features"}
    no_features = types.SimpleNamespace(**{**g.__dict__, "features": None})  # a scene saved without them
    assert "features" not in gaussian_tensors(no_features)
    assert isinstance(gaussian_render_fn(g), GaussianRenderFn)
    assert isinstance(gaussian_render_fn(g, ckpt, steps=2), PixelFlowRenderFn)
    after = gaussian_render_fn(g, lambda out: out.rgb * 0)  # another callable: applied after splatting
    assert isinstance(after, GaussianRenderFn) and after.renderer is not None
    with pytest.raises(ValueError, match="missing"):
        GaussianRenderFn({"means": g.means})


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the error on a machine without CUDA")
def test_a_cuda_render_device_without_cuda_is_a_clear_error(scene_and_ckpt):
    folder, ckpt = scene_and_ckpt
    with pytest.raises(ValueError, match="render device 'cuda'.*no CUDA device"):
        NeuralSimulator.from_scene(folder, renderer=ckpt, device="cuda")
    with pytest.raises(ValueError, match="no CUDA device"):
        gaussian_render_fn(_gaussians(), device="cuda:0")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device (GPU machines only)")
@pytest.mark.parametrize("with_renderer", [False, True])
def test_cuda_observations_match_the_cpu_ones(scene_and_ckpt, with_renderer):
    """The same scene and pose rendered on CUDA and on the CPU: the same numpy observations (the
    per-pose noise is drawn on the CPU), up to float rounding of the two splat backends."""
    folder, ckpt = scene_and_ckpt
    renderer = ckpt if with_renderer else None
    obs = {}
    for device in ("cpu", "cuda"):
        sim = NeuralSimulator.from_scene(folder, SPEC, renderer=renderer, backend="torch", device=device)
        obs[device] = sim.reset(np.array([[3.0, 2.0, 0.0]]), np.array([0.3]))[0][0]
    for view in ("panorama", "pinhole"):
        for key in ("rgb", "depth"):
            a, b = obs["cpu"][view][key], obs["cuda"][view][key]
            assert isinstance(b, np.ndarray) and b.dtype == a.dtype and b.shape == a.shape
            np.testing.assert_allclose(b, a, atol=2e-3 if key == "rgb" else 2e-3 * max(1.0, float(a.max())))


@pytest.mark.parametrize(
    "pixels, fov, height",
    [(64, 90.0, 128), (48, 90.0, 96), (98, 180.0, 98), (100, 79.0, 228), (8, 90.0, 32), (512, 360.0, 256)],
)
def test_panorama_height_matches_the_views_angular_resolution(pixels, fov, height):
    h = panorama_height_for(pixels, fov)
    assert h == height
    if h > 32:  # above the floor: one view pixel per panorama pixel across the view
        assert abs(2 * h * fov / 360.0 - pixels) <= 1.0


@pytest.mark.parametrize("pixels, fov", [(0, 90.0), (64, 0.0), (64, 400.0), (64, float("nan"))])
def test_panorama_height_rejects_bad_views(pixels, fov):
    with pytest.raises(ValueError, match="panorama_height_for"):
        panorama_height_for(pixels, fov)


def _analytic_pano(h: int) -> dict:
    """Panorama whose rgb encodes the unit ray (x, y, z) -> (x+1)/2 ... and depth = range of a
    plane z = 2 in front (inf-free: range capped at 10 m behind the camera)."""
    rays = EquirectCamera(h, 2 * h).ray_map(torch.float64).permute(1, 2, 0).numpy()
    with np.errstate(divide="ignore"):
        rng = np.where(rays[..., 2] > 1e-3, 2.0 / np.maximum(rays[..., 2], 1e-3), 10.0)
    return {"rgb": ((rays + 1) / 2).astype(np.float32), "depth": rng.astype(np.float32)}


def test_views_from_panorama_match_ray_geometry():
    pano = _analytic_pano(256)
    spec = ObservationSpec(
        pinhole=True, pinhole_size=32, ultrawide=True, ultrawide_width=64, ultrawide_height=42
    )
    v = views_from_panorama(pano, spec)
    cam = PinholeCamera.from_fov(90, 90, 32, 32)
    rays = cam.ray_map(torch.float64).permute(1, 2, 0).numpy()
    # Pinhole RGB = its own rays (bilinear resampling error only); depth is z = 2 on the plane.
    np.testing.assert_allclose(v["pinhole"]["rgb"], (rays + 1) / 2, atol=0.01)
    np.testing.assert_allclose(v["pinhole"]["depth"], 2.0, atol=0.05)
    # Ultra-wide: the crop centre looks forward, its left/right edges at about -+90 degrees.
    u = v["ultrawide"]["rgb"]
    assert u[21, 32, 2] == pytest.approx(1.0, abs=0.02)  # forward: z = 1
    assert u[21, 0, 0] == pytest.approx((1 - math.sin(math.radians(90 - 90 / 64))) / 2, abs=0.02)
    assert u[21, -1, 0] == pytest.approx((1 + math.sin(math.radians(90 - 90 / 64))) / 2, abs=0.02)


def test_cli_sim_render_with_renderer_matches_the_simulator_render_fn(scene_and_ckpt, tmp_path):
    from image2sim.simulator.cli import sim_app
    from image2sim.simulator.io.images import read_rgb
    from image2sim.simulator.renderer.model import load_renderer
    from typer.testing import CliRunner

    folder, ckpt = scene_and_ckpt
    out = tmp_path / "r.png"
    args = ["render", str(folder), "--pose", "3 2 1.25 1 0 0 0", "--out", str(out), "--backend", "torch"]
    res = CliRunner().invoke(sim_app, [*args, "--renderer", str(ckpt), "--steps", "1"])
    assert res.exit_code == 0, res.output
    assert "pixel-flow renderer" in res.output
    scene = GaussianScene.load(folder)
    g = scene.gaussians
    fn = PixelFlowRenderFn(
        {k: getattr(g, k) for k in ("means", "scales", "quats", "opacities", "colors", "features")},
        load_renderer(ckpt),
        backend="torch",
    )
    pose = np.eye(4)
    pose[:3, 3] = (3.0, 2.0, 1.25)
    want = (fn(EquirectCamera(PANO_H, 2 * PANO_H), pose)["rgb"] * 255 + 0.5).astype(np.uint8)
    np.testing.assert_array_equal(read_rgb(out), want)
    res = CliRunner().invoke(sim_app, [*args, "--renderer", str(tmp_path / "missing.safetensors")])
    assert res.exit_code == 2 and "missing.safetensors" in res.output


def test_cli_sim_render_writes_the_simulators_splat_image_in_each_mode(scene_and_ckpt, tmp_path):
    """Without --renderer, `sim render` writes what the splat-only simulator shows (`--splat
    normalised` by default, GaussianRenderFn's image) at metric precision (min_transmittance 1e-4,
    not the observations' early finish); raw and filled differ where alpha < 1; a bad mode is a
    clear error."""
    from image2sim.simulator.cli import sim_app
    from image2sim.simulator.io.images import read_rgb
    from image2sim.simulator.splatting.project import T_MIN
    from typer.testing import CliRunner

    folder, _ = scene_and_ckpt
    g = GaussianScene.load(folder).gaussians
    tensors = {k: getattr(g, k) for k in ("means", "scales", "quats", "opacities", "colors")}
    pose = np.eye(4)
    pose[:3, 3] = (3.0, 2.0, 1.25)
    images = {}
    for mode in ("normalised", "raw", "filled"):
        out = tmp_path / f"{mode}.png"
        args = ["render", str(folder), "--pose", "3 2 1.25 1 0 0 0", "--out", str(out), "--backend", "torch"]
        res = CliRunner().invoke(
            sim_app,
            [*args, "--height", str(PANO_H), "--width", str(2 * PANO_H)]
            + ([] if mode == "normalised" else ["--splat", mode]),
        )
        assert res.exit_code == 0, res.output
        assert f"splat {mode}" in res.output
        images[mode] = read_rgb(out)
        fn = GaussianRenderFn(tensors, backend="torch", mode=mode, min_transmittance=T_MIN)
        want = (fn(EquirectCamera(PANO_H, 2 * PANO_H), pose)["rgb"] * 255 + 0.5).astype(np.uint8)
        np.testing.assert_array_equal(images[mode], want)
    alpha = read_rgb(tmp_path / "raw_alpha.png")[..., 0]
    partial = (alpha > 0) & (alpha < 250)
    assert partial.any()
    assert (
        images["raw"][partial].astype(int).sum(-1) < images["normalised"][partial].astype(int).sum(-1)
    ).mean() > 0.9
    assert (images["filled"][partial] != images["normalised"][partial]).any()
    res = CliRunner().invoke(
        sim_app,
        ["render", str(folder), "--frame", "0", "--out", str(tmp_path / "x.png"), "--splat", "premultiplied"],
    )
    assert res.exit_code == 2 and "--splat must be one of raw, normalised, filled" in res.output
