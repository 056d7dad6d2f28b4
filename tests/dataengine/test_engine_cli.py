"""CLI (`data episodes`, `data stats`, `data mine`) and the VLM annotation path of a scene task."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest
from image2sim.simulator.cli import build_app
from typer.testing import CliRunner


@pytest.fixture(scope="module")
def scenes_root(tmp_path_factory):
    from image2sim.dataengine.procedural import preset, synthesize

    root = tmp_path_factory.mktemp("cli_synth")
    synthesize(preset("tiny"), root, scenes=2, seed=11, progress=False)
    return root


def test_cli_episodes_then_stats(scenes_root, tmp_path):
    runner = CliRunner()
    app = build_app()
    out = tmp_path / "out"
    # A single capture folder is accepted as --scenes too.
    res = runner.invoke(
        app,
        [
            "data",
            "episodes",
            "--sampling",
            "min_path_length=0.5",  # tiny houses hold no 3 m path
            "--scenes",
            str(scenes_root / "scene_001"),
            "--out",
            str(out),
            "--per-scene",
            "3",
            "--executor",
            "local",
            "--obs-height",
            "24",
            "--view",
            "ultrawide",
        ],
    )
    assert res.exit_code == 0, res.output
    summary = json.loads(res.output[res.output.index("{") :])
    assert summary["scenes_done"] == 1 and summary["failed"] == [] and summary["episodes"] > 0
    res = runner.invoke(app, ["data", "stats", str(out)])
    assert res.exit_code == 0, res.output
    stats = json.loads((out / "train" / "stats" / "stats.json").read_text())
    assert stats["episodes"] == summary["episodes"]
    assert sum(v["count"] for v in stats["style_mix"].values()) == stats["episodes"]
    assert sum(stats["steps"]["histogram"]["counts"]) == stats["episodes"]
    png = (out / "train" / "stats" / "stats.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    # Ultra-wide frames keep the 512:336 aspect.
    from image2sim.dataengine.distributed import read_shard_list

    shard = read_shard_list(out / "shards.json")[0]
    with np.load(f"{shard}/frames/000000.npz") as z:
        assert z["rgb"].shape[1:] == (24, 37, 3)


def test_cli_rejects_bad_arguments(scenes_root, tmp_path):
    runner = CliRunner()
    app = build_app()
    res = runner.invoke(
        app,
        [
            "data",
            "episodes",
            "--sampling",
            "min_path_length=0.5",  # tiny houses hold no 3 m path
            "--scenes",
            str(scenes_root),
            "--out",
            str(tmp_path / "o"),
            "--per-scene",
            "lots",
            "--executor",
            "local",
        ],
    )
    assert res.exit_code == 2 and "--per-scene" in res.output
    res = runner.invoke(
        app,
        [
            "data",
            "episodes",
            "--sampling",
            "min_path_length=0.5",  # tiny houses hold no 3 m path
            "--scenes",
            str(tmp_path / "nowhere"),
            "--out",
            str(tmp_path / "o"),
            "--executor",
            "local",
        ],
    )
    assert res.exit_code == 2 and "not found" in res.output
    bad = tmp_path / "gauss.yaml"
    bad.write_text("fusion:\n  footprint_factr: 2\n")
    for config, says in ((str(bad), "footprint_factr"), (str(tmp_path / "none.yaml"), "none.yaml")):
        res = runner.invoke(
            app,
            [
                "data",
                "episodes",
                "--scenes",
                str(scenes_root),
                "--out",
                str(tmp_path / "o"),
                "--gaussian-config",
                config,
            ],
        )
        assert res.exit_code == 2 and "--gaussian-config" in res.output and says in res.output, res.output
        assert not (tmp_path / "o").exists()  # refused before anything is written


def test_cli_mine_writes_object_database(scenes_root, tmp_path):
    from image2sim.dataengine.mining import load_objects

    out = tmp_path / "objects.json"
    res = CliRunner().invoke(build_app(), ["data", "mine", str(scenes_root / "scene_000"), "--out", str(out)])
    assert res.exit_code == 0, res.output
    objs = load_objects(out)
    assert objs and all(o.sightings >= 1 for o in objs)


class _Handler(BaseHTTPRequestHandler):
    replies: list = []
    seen: list = []

    def log_message(self, *args):
        pass

    def do_POST(self):
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        n = len(self.seen)
        self.seen.append(body)
        text = (
            "REASONING: consistent frames.\nVERDICT: VALID\nINSTRUCTION: Walk ahead and stop there."
            if n % 2 == 0
            else "REASONING: the view froze.\nVERDICT: INVALID\nISSUES: visual_freezing\nINSTRUCTION: none"
        )
        data = json.dumps({"choices": [{"message": {"content": text}}]}).encode()
        self.send_response(200)
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)


def test_scene_task_with_openai_annotator_applies_the_gate(scenes_root, tmp_path):
    from image2sim.dataengine.engine_config import EngineConfig
    from image2sim.dataengine.pipeline import process_scene

    _Handler.seen = []
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), _Handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    try:
        cfg = EngineConfig(
            per_scene=4,
            sampling={"min_path_length": 1.0},  # tiny houses hold no 3 m path
            annotator="openai",
            obs_height=24,
            annotation_view_height=24,
            annotator_options={
                "base_url": f"http://127.0.0.1:{httpd.server_address[1]}/v1",
                "max_concurrency": 1,
                "timeout": 5.0,
            },
        )
        summary = process_scene(scenes_root / "scene_000", tmp_path, cfg)
    finally:
        httpd.shutdown()
        httpd.server_close()
    n_req = summary["rolled_out_ok"]
    assert n_req >= 2 and len(_Handler.seen) == n_req
    assert summary["episodes"] == (n_req + 1) // 2  # every second reply was INVALID
    assert summary["drops"].get("annotation: invalid verdict (visual_freezing)") == n_req // 2
    # Each request carried one 180-degree view per macro-step, interleaved with the movements.
    parts = _Handler.seen[0]["messages"][1]["content"]
    assert sum(p["type"] == "image_url" for p in parts) == sum(
        p["type"] == "text" and p["text"].startswith(("[movement", "[STOP]")) for p in parts
    )
    doc = json.loads((tmp_path / "scenes" / "scene_000" / "episodes.json").read_text())
    assert all(e["instruction"]["instruction_text"] == "Walk ahead and stop there." for e in doc["episodes"])
    manifest = json.loads((tmp_path / "scenes" / "scene_000" / "shard" / "manifest.json").read_text())
    assert manifest["num_trajectories"] == summary["episodes"]


def test_cli_episodes_exits_non_zero_when_no_scene_yields_an_episode(tmp_path):
    """A one-room house of 2.6 m x 2.6 m holds no path of the shortest bucket (3 m): 0 episodes is an
    error, with the per-scene reason, not a silent empty dataset."""
    import dataclasses

    from image2sim.dataengine.procedural import preset, synthesize

    cfg = preset("tiny")
    one_room = dataclasses.replace(
        cfg.layout, rooms_min=1, rooms_max=1, room_size_max=cfg.layout.room_size_min
    )
    synthesize(dataclasses.replace(cfg, layout=one_room), tmp_path / "s", scenes=1, seed=0, progress=False)
    res = CliRunner().invoke(
        build_app(),
        ["data", "episodes", "--scenes", str(tmp_path / "s" / "scene_000"), "--out", str(tmp_path / "o"),
         "--per-scene", "2", "--executor", "local", "--render", "none"],
    )  # fmt: skip
    assert res.exit_code == 1, res.output
    assert "scene scene_000: 0 episodes" in res.output and "infeasible" in res.output
    assert "no episode was produced" in res.output and "min_path_length" in res.output


def test_an_unreachable_annotator_fails_the_scene_instead_of_finishing_it_empty(scenes_root, tmp_path):
    """Connection refused on every attempt: the scene raises (not marked done, so a resume retries it)."""
    import socket

    from image2sim.dataengine.annotate.openai_vlm import TransportError
    from image2sim.dataengine.engine_config import EngineConfig
    from image2sim.dataengine.pipeline import process_scene

    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    cfg = EngineConfig(
        per_scene=2,
        sampling={"min_path_length": 1.0},
        annotator="openai",
        obs_height=24,
        annotation_view_height=24,
        annotator_options={"base_url": f"http://127.0.0.1:{port}/v1", "retries": 0, "backoff": 0.0},
    )
    with pytest.raises(TransportError, match="connection"):
        process_scene(scenes_root / "scene_000", tmp_path, cfg)
    assert not (tmp_path / "scenes" / "scene_000" / "done.json").exists()
