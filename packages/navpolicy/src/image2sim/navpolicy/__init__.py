"""Image2Nav: the Qwen3-VL navigation policy (see ``docs/navpolicy.md``).

Modules (imported on demand; transformers is heavy): ``actions`` (action words <-> token ids),
``tokenizer`` (offline tiny BPE / local Qwen tokenizer), ``config`` (presets tiny, paper, paper-wide),
``model`` (build/freeze/LoRA/export), ``prompting`` (prompt ids + action-only labels), ``data``
(trajectories, shard format, samples, collator), ``train`` (Lightning BC + DeepSpeed ZeRO-2),
``agent`` (streaming KV-cache agent, batched agent), ``dagger`` (online DAgger), ``baselines``
(forward-then-turn; random/forward/oracle re-exported from eval), ``act`` (``nav act``/``nav compare``),
``serve`` (``nav serve``: HTTP policy server), ``client`` (its httpx client), ``cli`` (``image2sim nav ...``).
"""

__version__ = "0.1.0"
