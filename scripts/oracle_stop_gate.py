"""How much of a policy's failure is its STOP? (docs/sim2real.md, "Pilot 2026-12-07 (session 47)")

Runs an exported Image2Nav policy on episodes with the exact renderer, as `image2sim eval nav
--backend exact` does (same protocol, same per-episode seeds), but with a privileged STOP gate: the
agent may decode STOP only while its geodesic distance to the goal is below ``--radius`` (the
protocol's success radius by default); elsewhere it takes its best actions other than STOP
(``Image2NavAgent.act(allow_stop=False)``). With ``--gate none`` it is the plain policy, which must
reproduce the evaluation's per-episode results. The gate reads the goal, so this is a ceiling for
any learned STOP decision on top of the same walking, not an agent.

    .venv/bin/python scripts/oracle_stop_gate.py --model <export> --config <policy yaml> \\
        --scenes outputs/sim2real/captures/heldout --episodes outputs/sim2real/heldout/train/train.json.gz \\
        --protocol-from outputs/sim2real/eval/neural/image2nav/run.json --scene scene_000 --out gate_000.jsonl

One JSON line per episode (success, steps, whether it stopped, final distance); rerunning skips the
episodes already in ``--out``. Run one process per scene to use several cores.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", required=True, help="exported policy folder")
    ap.add_argument("--config", required=True, help="policy config the model trained with")
    ap.add_argument("--scenes", required=True, help="folder of procedural captures (one per scene)")
    ap.add_argument("--episodes", required=True, help="episode file (.json.gz, data engine / VLN-CE)")
    ap.add_argument("--protocol-from", required=True, help="an eval run.json whose protocol to use")
    ap.add_argument("--scene", required=True, help="scene folder name to run")
    ap.add_argument("--out", required=True, help="JSONL file of per-episode results")
    ap.add_argument("--gate", choices=("oracle", "none"), default="oracle")
    ap.add_argument("--radius", type=float, default=None, help="metres (default: the success radius)")
    ap.add_argument("--seed", type=int, default=0, help="run seed (episode seeds as eval nav's)")
    args = ap.parse_args()

    from image2sim.eval.datasets import load_image2sim_episodes
    from image2sim.eval.nav_agents import Image2NavAdapter
    from image2sim.eval.nav_env import load_exact_backend
    from image2sim.eval.protocols import Protocol
    from image2sim.eval.runner import episode_seed, run_episode
    from image2sim.navpolicy.agent import Image2NavAgent
    from image2sim.navpolicy.config import load_config
    from image2sim.navpolicy.model import build_policy
    from image2sim.simulator.conventions import Action

    run = json.loads(Path(args.protocol_from).read_text())
    if "protocol" not in run:
        raise SystemExit(f"{args.protocol_from}: no 'protocol' (expected an eval run.json)")
    proto = Protocol.from_dict(run["protocol"])
    radius = proto.success_distance_m if args.radius is None else float(args.radius)
    episodes = [e for e in load_image2sim_episodes(args.episodes).episodes if e.scene_id == args.scene]
    if not episodes:
        raise SystemExit(f"{args.episodes}: no episode in scene {args.scene!r}")
    out = Path(args.out)
    done = set()
    if out.is_file():
        done = {json.loads(line)["episode_id"] for line in out.read_text().splitlines() if line.strip()}
    cfg = load_config(args.config, {"model": {"source": args.model}})

    class Gated(Image2NavAdapter):
        """The runner's Image2Nav adapter, asking for STOP only within ``radius`` of the goal."""

        def stop_allowed(self, obs) -> bool:
            near = obs.distance_to_goal is not None and obs.distance_to_goal < radius
            return args.gate == "none" or near

    agent = Gated.from_agent(Image2NavAgent(build_policy(cfg, seed=0), cfg.agent, cfg.system_prompt))
    backend = load_exact_backend(Path(args.scenes) / args.scene, proto, render=True)
    backend.render_at((cfg.observation.height, cfg.observation.width))
    for ep in episodes:
        if ep.episode_id in done:
            continue
        res, actions = run_episode(backend, agent, ep, proto, episode_seed(args.seed, ep.episode_id))
        rec = {
            "episode_id": ep.episode_id,
            "success": res.metrics["success"],
            "steps": len(actions),
            "stopped": actions[-1] == int(Action.STOP),
            "distance_to_goal": res.metrics.get("distance_to_goal"),
        }
        with open(out, "a", encoding="utf-8") as f:  # one line per finished episode: resumable
            f.write(json.dumps(rec) + "\n")
            f.flush()
            os.fsync(f.fileno())
    print(f"{args.scene}: {len(episodes)} episodes, gate {args.gate}, results in {out}")


if __name__ == "__main__":
    main()
