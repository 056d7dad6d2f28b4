"""`sim export-renderer`: a renderer checkpoint as renderer.safetensors + renderer.json, read back by
`load_renderer` (and every place that takes renderer weights) with the same outputs."""

from __future__ import annotations

import json

import pytest
import torch
from image2sim.simulator import cli
from image2sim.simulator.renderer import tiny
from image2sim.simulator.renderer.model import RENDERER_CONFIG, RENDERER_WEIGHTS, load_renderer
from image2sim.simulator.renderer.splat_data import TRAINING_RECORD, find_training_record

H, W = 16, 32


@pytest.fixture(scope="module")
def run_checkpoint(tmp_path_factory):
    """A Lightning checkpoint of a `sim train` run (random weights), with the run's training record."""
    from image2sim.simulator.renderer.module import RendererModule

    run = tmp_path_factory.mktemp("run")
    torch.manual_seed(0)
    module = RendererModule(tiny())
    with torch.no_grad():  # residual heads start at zero: make every weight count
        for p in module.renderer.parameters():
            p.add_(0.01 * torch.randn_like(p))
    ckpt = run / "checkpoints" / "last.ckpt"
    ckpt.parent.mkdir()
    # Lightning's layout: the module's state under "state_dict", its saved hyperparameters beside it.
    torch.save({"state_dict": module.state_dict(), "hyper_parameters": dict(module.hparams)}, ckpt)
    (run / TRAINING_RECORD).write_text(json.dumps({"condition_source": "splat"}))
    return ckpt


def _render(model) -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    cond = torch.rand(1, 24, H, W, generator=g)
    noise = torch.randn(1, 4, H, W, generator=g)
    with torch.no_grad():
        out = model.render(cond, steps=2, noise=noise)
    return torch.cat([out.rgb, out.depth], 1)


def _export(ckpt, out) -> None:
    with pytest.raises(SystemExit) as info:
        cli.main(["sim", "export-renderer", str(ckpt), "--out", str(out)])
    assert info.value.code == 0


def test_export_round_trip_gives_the_checkpoints_outputs(run_checkpoint, tmp_path, capsys):
    out = tmp_path / "renderer"
    _export(run_checkpoint, out)
    assert "training record" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [RENDERER_WEIGHTS, RENDERER_CONFIG, TRAINING_RECORD]
    )
    doc = json.loads((out / RENDERER_CONFIG).read_text())
    assert doc["format"] == "image2sim-renderer-v1" and doc["source"] == "last.ckpt"
    ref, again = load_renderer(run_checkpoint), load_renderer(out)
    assert again.cfg == ref.cfg
    assert torch.equal(_render(again), _render(ref))
    # The folder carries the run's training conditions, as the checkpoint's run folder did.
    assert find_training_record(out) == find_training_record(run_checkpoint) == {"condition_source": "splat"}
    # A second export replaces the folder whole (no temp left beside it).
    _export(run_checkpoint, out)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["renderer"]


def test_every_renderer_consumer_accepts_the_folder(run_checkpoint, tmp_path):
    from image2sim.simulator.renderer.model import PixelFlowRenderer
    from image2sim.simulator.sim import load_pixel_flow

    out = tmp_path / "renderer"
    _export(run_checkpoint, out)
    ref = _render(load_renderer(run_checkpoint))
    # NeuralSimulator.from_scene(renderer=...), nav train/from-episodes --renderer and the data
    # engine's --renderer all go through load_renderer / load_pixel_flow.
    assert isinstance(load_pixel_flow(out), PixelFlowRenderer)
    assert torch.equal(_render(load_pixel_flow(out)), ref)
    bench = pytest.importorskip("image2sim.eval.render_bench")  # eval render --checkpoint
    assert torch.equal(_render(bench.load_renderer(tiny(), out)), ref)


def test_broken_folders_name_the_file_and_the_problem(run_checkpoint, tmp_path, capsys):
    out = tmp_path / "renderer"
    _export(run_checkpoint, out)
    (out / RENDERER_CONFIG).write_text(json.dumps({"format": "something-else"}))
    with pytest.raises(ValueError, match=rf"{RENDERER_CONFIG}: not an image2sim renderer config"):
        load_renderer(out)
    (out / RENDERER_CONFIG).write_text("{not json")
    with pytest.raises(ValueError, match=rf"{RENDERER_CONFIG}: cannot parse"):
        load_renderer(out)
    (out / RENDERER_CONFIG).unlink()
    with pytest.raises(FileNotFoundError, match=rf"{RENDERER_CONFIG} not found"):
        load_renderer(out)
    with pytest.raises(SystemExit) as info:  # bad input: exit 2, one line
        cli.main(["sim", "export-renderer", str(tmp_path / "none.ckpt"), "--out", str(tmp_path / "x")])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "none.ckpt" in err and "Traceback" not in err and not (tmp_path / "x").exists()
