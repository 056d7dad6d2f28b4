"""LPIPS-VGG16 wiring: weight files (random weights in tmp files), parity with a slow reference, n/a."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from image2sim.eval.metrics.lpips import (
    LPIPS,
    LpipsConfig,
    LpipsWeightsError,
    build_lpips,
    load_lpips,
    lpips_distance,
)
from safetensors.torch import save_file

VGG16_CONVS = (0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28)
POOLS_BEFORE = {5, 10, 17, 24}  # a max-pool precedes these convs
TAP_AFTER = {2: 0, 7: 1, 14: 2, 21: 3, 28: 4}  # relu of these convs is tapped


def _random_state(seed: int = 0) -> dict[str, torch.Tensor]:
    torch.manual_seed(seed)
    model = LPIPS()
    for name, p in model.named_parameters():
        if name.startswith("lin"):
            p.data = torch.rand_like(p) * 0.1  # the released heads are non-negative
        elif name.endswith("weight"):
            p.data = torch.randn_like(p) * (2.0 / (p.shape[1] * 9)) ** 0.5
        else:
            p.data = torch.randn_like(p) * 0.01
    return {k: v.clone().contiguous() for k, v in model.state_dict().items()}


@pytest.fixture(scope="module")
def state() -> dict[str, torch.Tensor]:
    return _random_state()


@pytest.fixture(scope="module")
def weights_file(tmp_path_factory: pytest.TempPathFactory, state: dict[str, torch.Tensor]) -> Path:
    path = tmp_path_factory.mktemp("lpips") / "lpips_vgg.safetensors"
    save_file(state, str(path))
    return path


@pytest.fixture(scope="module")
def model(weights_file: Path) -> LPIPS:
    return load_lpips(weights_file)


def reference_lpips(state: dict[str, torch.Tensor], x: torch.Tensor, y: torch.Tensor) -> float:
    """Slow reference for one image pair: explicit VGG16 layer loop + per-pixel numpy head."""
    shift = torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1)
    scale = torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1)

    def features(img: torch.Tensor) -> list[np.ndarray]:
        h = ((2 * img[None] - 1) - shift) / scale
        taps: list[np.ndarray] = []
        slice_of = {0: 1, 2: 1, 5: 2, 7: 2, 10: 3, 12: 3, 14: 3, 17: 4, 19: 4, 21: 4, 24: 5, 26: 5, 28: 5}
        for i in VGG16_CONVS:
            if i in POOLS_BEFORE:
                h = F.max_pool2d(h, 2)
            k = slice_of[i]
            weight, bias = state[f"net.slice{k}.{i}.weight"], state[f"net.slice{k}.{i}.bias"]
            h = F.relu(F.conv2d(h, weight, bias, padding=1))
            if i in TAP_AFTER:
                taps.append(h[0].double().numpy())
        return taps

    total = 0.0
    for layer, (fa, fb) in enumerate(zip(features(x), features(y), strict=True)):
        w = state[f"lin{layer}.model.1.weight"].double().numpy().reshape(-1)
        c, hh, ww = fa.shape
        acc = 0.0
        for r in range(hh):
            for q in range(ww):
                a, b = fa[:, r, q], fb[:, r, q]
                na = a / (np.sqrt((a * a).sum()) + 1e-10)
                nb = b / (np.sqrt((b * b).sum()) + 1e-10)
                acc += float((w * (na - nb) ** 2).sum())
        total += acc / (hh * ww)
    return total


def test_parity_with_reference(model: LPIPS, state: dict[str, torch.Tensor]) -> None:
    g = torch.Generator().manual_seed(1)
    x, y = torch.rand(2, 3, 16, 24, generator=g), torch.rand(2, 3, 16, 24, generator=g)
    got = lpips_distance(x, y, model)
    assert got is not None and got.shape == (2,)
    for i in range(2):
        assert got[i].item() == pytest.approx(reference_lpips(state, x[i], y[i]), rel=1e-4)


def test_properties(model: LPIPS) -> None:
    g = torch.Generator().manual_seed(2)
    x = torch.rand(1, 3, 16, 16, generator=g)
    y = torch.rand(1, 3, 16, 16, generator=g)
    assert lpips_distance(x, x, model).item() == 0.0
    assert lpips_distance(x, y, model).item() > 0.0
    assert lpips_distance(x, y, model).item() == pytest.approx(lpips_distance(y, x, model).item(), rel=1e-6)
    near = (x + 0.02 * torch.randn(x.shape, generator=g)).clamp(0, 1)
    assert lpips_distance(x, near, model).item() < lpips_distance(x, y, model).item()
    assert lpips_distance(x[0], y[0], model).ndim == 0  # single (3, H, W) image


def test_not_configured_is_na_not_zero() -> None:
    assert build_lpips(LpipsConfig()) is None
    x = torch.rand(1, 3, 16, 16)
    assert lpips_distance(x, x, None) is None
    with pytest.raises(LpipsWeightsError, match="backbone_weights given without weights"):
        build_lpips(LpipsConfig(backbone_weights="vgg16.safetensors"))
    with pytest.raises(ValueError, match="unknown key"):
        LpipsConfig.from_dict({"weight": "x"})


def test_split_files_torchvision_backbone_and_torch_load(
    tmp_path: Path, state: dict[str, torch.Tensor]
) -> None:
    heads = {k: v for k, v in state.items() if k.startswith("lin")}
    # torchvision naming for the trunk, plus its classifier (ignored).
    backbone = {}
    for k, v in state.items():
        if k.startswith("net.slice"):
            _, _, idx, kind = k.split(".")
            backbone[f"features.{idx}.{kind}"] = v
    backbone["classifier.0.weight"] = torch.zeros(4, 4)
    torch.save(heads, tmp_path / "vgg.pth")
    save_file(backbone, str(tmp_path / "vgg16.safetensors"))
    model = build_lpips(LpipsConfig.from_dict({"weights": str(tmp_path / "vgg.pth"),
                                               "backbone_weights": str(tmp_path / "vgg16.safetensors")}))
    assert model is not None
    for k, v in model.state_dict().items():
        assert torch.equal(v, state[k]), k


def test_bad_weight_files(tmp_path: Path, state: dict[str, torch.Tensor]) -> None:
    heads = {k: v for k, v in state.items() if k.startswith("lin")}
    save_file(heads, str(tmp_path / "heads.safetensors"))
    with pytest.raises(LpipsWeightsError, match=r"missing 26 LPIPS parameter\(s\)"):
        load_lpips(tmp_path / "heads.safetensors")
    wrong = dict(state)
    wrong["lin0.model.1.weight"] = torch.zeros(1, 32, 1, 1)
    save_file(wrong, str(tmp_path / "wrong.safetensors"))
    with pytest.raises(LpipsWeightsError, match=r"wrong.safetensors: parameter 'lin0.model.1.weight' has"):
        load_lpips(tmp_path / "wrong.safetensors")
    extra = dict(state)
    extra["lin9.model.1.weight"] = torch.zeros(1)
    save_file(extra, str(tmp_path / "extra.safetensors"))
    with pytest.raises(LpipsWeightsError, match="unexpected parameter 'lin9.model.1.weight'"):
        load_lpips(tmp_path / "extra.safetensors")
    with pytest.raises(LpipsWeightsError, match="also given by"):
        load_lpips(tmp_path / "heads.safetensors", tmp_path / "heads.safetensors")
    with pytest.raises(LpipsWeightsError, match="weight file not found"):
        load_lpips(tmp_path / "absent.safetensors")
    (tmp_path / "w.npz").write_bytes(b"x")
    with pytest.raises(LpipsWeightsError, match="unsupported suffix"):
        load_lpips(tmp_path / "w.npz")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(LpipsWeightsError, match="junk.pth: cannot read weights"):
        load_lpips(tmp_path / "junk.pth")


def test_pickled_objects_are_refused(tmp_path: Path) -> None:
    # Any non-tensor object needs pickle execution; weights_only loading must refuse it.
    torch.save({"obj": Fraction(1, 3)}, tmp_path / "evil.pt")
    with pytest.raises(LpipsWeightsError, match="evil.pt: cannot read weights"):
        load_lpips(tmp_path / "evil.pt")
