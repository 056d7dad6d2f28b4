"""How much of a policy's failure is its STOP? (docs/sim2real.md, "Pilot 2026-12-07 (session 47)")

Runs an exported Image2Nav policy on episodes with the exact renderer, as `image2sim eval nav
--backend exact` does (same protocol, same per-episode seeds), but with a privileged STOP gate: the
agent may decode STOP only while its geodesic distance to the goal is below ``--radius`` (the
protocol's success radius by default); elsewhere it takes its best actions other than STOP
(``Image2NavAgent.act(allow_stop=False)``). With ``--gate none`` it is the plain policy, which must
reproduce the evaluation's per-episode results. The gate reads the goal, so this is a ceiling for
any learned STOP decision on top of the same walking, not an agent. ``--gate detector`` lets a
goal detector saved by ``scripts/goal_detector_probe.py`` decide instead (a learned gate; the goal
category is read from the episodes' extras, which the template instruction names).

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
    ap.add_argument("--gate", choices=("oracle", "none", "detector"), default="oracle")
    ap.add_argument("--detector", default=None, help="--gate detector: folder of goal_detector_probe.py")
    ap.add_argument("--threshold", type=float, default=0.5, help="--gate detector: least probability")
    ap.add_argument("--memory", type=int, default=1, help="--gate detector: max over the last N views")
    ap.add_argument("--extras", default=None, help="--gate detector: episodes' extras (goal category)")
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

    detector = None
    if args.gate == "detector":
        import importlib.util

        import torch

        # The detector lives in its probe script (a measurement, not a package feature).
        spec = importlib.util.spec_from_file_location(
            "goal_detector_probe", Path(__file__).with_name("goal_detector_probe.py")
        )
        probe = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(probe)
        if args.detector is None or args.extras is None:
            raise SystemExit("--gate detector needs --detector and --extras")
        detector = probe.load_detector(args.detector)
        extras = json.loads(Path(args.extras).read_text())

    class Gated(Image2NavAdapter):
        """The runner's Image2Nav adapter with a STOP gate: ``oracle``, STOP only within ``radius``
        of the goal; ``detector``, only while the detector's probability for the episode's goal
        category (its extras) reached ``threshold`` in one of the last ``memory`` views it was
        asked about; ``none``, always."""

        def reset(self, episode, backend, seed):
            self.history: list[float] = []
            self.category = None
            if detector is not None:
                name = extras[episode.episode_id]["goal_object"]["category"]
                self.category = detector.categories.index(name) if name in detector.categories else None
            return super().reset(episode, backend, seed)

        def stop_allowed(self, obs) -> bool:
            if args.gate == "none":
                return True
            if args.gate == "oracle":
                return obs.distance_to_goal is not None and obs.distance_to_goal < radius
            if self.category is None:  # a category the detector never saw: no gate
                return True
            with torch.no_grad():
                logits = detector(probe.as_batch(obs.rgb[None]))
            self.history.append(float(torch.sigmoid(logits)[0, self.category]))
            return max(self.history[-args.memory :]) >= args.threshold

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
