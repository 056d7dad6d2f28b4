"""Typed configuration of Image2Nav (model, observations, data, training, agent).

Two presets: ``tiny`` (a from-scratch Qwen3-VL of ~0.2M parameters with an offline tokenizer, for CPU
tests and demos) and ``paper`` (Qwen3-VL-4B-Instruct loaded from a *local* folder, 336x336 pinhole
observations, DeepSpeed ZeRO-2, bf16, gradient checkpointing). Configs load from YAML or dicts and
reject unknown keys, naming the offending key path.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from image2sim.simulator.config import (  # one error type and field checks repository-wide
    ConfigError,
    require_at_least,
    require_in_range,
    require_one_of,
    require_render_device,
)
from image2sim.simulator.markers import GoalMarker

TOKENIZER_CORPORA = ("builtin", "instructions")
"""Values of ``model.tiny.tokenizer_corpus``."""
GOAL_LABELS = ("in_view", "near_end")
"""What the grounding head learns per frame (``data.goal_label``)."""


@dataclass
class TinyModelConfig:
    """Sizes of the from-scratch tiny Qwen3-VL (used when ``ModelConfig.source == "tiny"``)."""

    text_hidden_size: int = 64
    """Language-model width (also the vision merger's output width)."""
    text_layers: int = 2
    """Number of decoder layers."""
    text_heads: int = 4
    """Attention heads of the language model."""
    text_kv_heads: int = 2
    """Key/value heads (grouped-query attention)."""
    text_head_dim: int = 16
    """Per-head width; M-RoPE sections must sum to half of it."""
    text_intermediate_size: int = 128
    """MLP width of the language model."""
    mrope_section: list[int] = field(default_factory=lambda: [2, 3, 3])
    """M-RoPE split of the rotary frequencies into (t, h, w); sum == text_head_dim / 2."""
    vision_hidden_size: int = 32
    """Vision-tower width."""
    vision_layers: int = 2
    """Vision-tower depth."""
    vision_heads: int = 2
    """Vision attention heads."""
    vision_intermediate_size: int = 64
    """Vision MLP width."""
    patch_size: int = 8
    """Vision patch size in pixels (Qwen3-VL: 16)."""
    num_position_embeddings: int = 64
    """Learned vision position table size; must be a perfect square."""
    deepstack_visual_indexes: list[int] = field(default_factory=lambda: [0])
    """Vision layers whose features are added to the first decoder layers (DeepStack)."""
    tokenizer_vocab_size: int = 512
    """Target BPE vocabulary of the offline tokenizer."""
    tokenizer_corpus: str = "builtin"
    """What the offline tokenizer's merges are learned on. ``builtin``: a few lines of navigation
    prose, so most words of a task's instructions split into bytes ("toilet" -> to/i/le/t, "vase"
    -> v/a/s/e) that a 2-layer model must put back together. ``instructions``: that prose plus the
    instructions of the training shards (``data.shards``), so the task's words are whole tokens,
    as they are in a pretrained tokenizer. The tokenizer is saved with every export."""


@dataclass
class LoraSettings:
    """Optional LoRA adapters on the language model only (the vision tower is never adapted)."""

    enabled: bool = False
    """Wrap the language model's projections with LoRA and train only the adapters (+ merger)."""
    r: int = 16
    """LoRA rank."""
    alpha: int = 32
    """LoRA scaling numerator (scale = alpha / r)."""
    dropout: float = 0.05
    """Dropout on the LoRA input."""
    target_modules: str = r".*language_model.*\.(q_proj|k_proj|v_proj|o_proj|gate_proj|up_proj|down_proj)"
    """Regex (peft full-match semantics) selecting the adapted linear layers."""


@dataclass
class ModelConfig:
    """Which Qwen3-VL to build and which parts of it train."""

    source: str = "tiny"
    """``"tiny"`` to build from scratch, or a local folder with a Qwen3-VL checkpoint (never a hub id)."""
    tiny: TinyModelConfig = field(default_factory=TinyModelConfig)
    """Sizes used when ``source == "tiny"``."""
    freeze_vision: bool = True
    """Freeze the vision tower (patch embedding, blocks). The paper trains only LLM + projector."""
    vision_weights: str = ""
    """Optional ``image2sim nav pretrain-vision`` output (its folder or ``vision.safetensors``) loaded
    into the vision tower and its mergers when the model is built: the recognition prior that the
    paper's pretrained Qwen3-VL has and a from-scratch tiny tower lacks. Empty: the built weights."""
    train_merger: bool = True
    """Keep the vision-language merger/projector (and DeepStack mergers) trainable."""
    lora: LoraSettings = field(default_factory=LoraSettings)
    """LoRA on the language model."""
    gradient_checkpointing: bool = False
    """Recompute activations in the backward pass (memory for compute)."""
    dtype: str = "float32"
    """Parameter dtype: float32 (CPU) or bfloat16 (GPU)."""
    attn_implementation: str = "sdpa"
    """transformers attention backend: sdpa, eager or flash_attention_2 (GPU only)."""


@dataclass
class ObservationConfig:
    """The rendered observation fed to the policy."""

    camera: str = "pinhole"
    """``pinhole`` (paper: 336x336 at 90 deg HFOV/VFOV) or ``equirect`` (512x336 at 180x118 deg)."""
    height: int = 64
    """Image height in pixels (a multiple of patch_size * merge_size avoids resampling)."""
    width: int = 64
    """Image width in pixels."""
    hfov_deg: float = 90.0
    """Horizontal field of view in degrees."""
    vfov_deg: float = 90.0
    """Vertical field of view in degrees."""
    image_mean: list[float] = field(default_factory=lambda: [0.5, 0.5, 0.5])
    """Per-channel mean for normalisation (Qwen3-VL uses 0.5)."""
    image_std: list[float] = field(default_factory=lambda: [0.5, 0.5, 0.5])
    """Per-channel std for normalisation (Qwen3-VL uses 0.5)."""


@dataclass
class DataConfig:
    """Training samples drawn from trajectory shards."""

    shards: list[str] = field(default_factory=list)
    """Shard folders (see :mod:`image2sim.navpolicy.data` for the format)."""
    val_shards: list[str] = field(default_factory=list)
    """Validation shards (e.g. episodes of houses the policy never trains on): every
    ``train.val_every`` steps the same ``train.val_batches`` batches of them (no jitter) are scored,
    logged as ``val/loss`` and ``val/action_acc`` beside the training curves, so over- and
    under-fitting show while the run goes. Empty: no validation."""
    shard_weights: list[float] = field(default_factory=list)
    """Sample ratios of the shards (e.g. human annotations : generated data). Empty: every trajectory
    of every shard is equally likely (the plain epoch order). Else one weight >= 0 per entry of
    ``shards``: a drawn trajectory comes from shard ``k`` with probability ``w_k / sum(w)``, whatever
    the shards' sizes; inside a shard every trajectory is drawn once before any is drawn again. The
    order stays a pure function of (seed, position), so resume is exact. Behaviour cloning on
    ``shards`` only (DAgger's aggregated buffer draws every trajectory equally)."""
    max_observations: int = 32
    """Observations sampled uniformly along a trajectory per sample (paper: 32)."""
    max_action_labels: int = 64
    """Action labels per sample (paper: 64 = two per observation)."""
    jitter: bool = True
    """Stratified random sampling inside each uniform bin (False: bin centres, deterministic)."""
    observation_stride: int = 1
    """Sample observations only at steps that are multiples of this; 2 matches the streaming agent,
    which observes once per two actions (stride 1 shows every step of short trajectories)."""
    sampling: str = "uniform"
    """Sample layout. ``uniform`` (the paper): observations spread over the whole trajectory, the last
    one at its end. ``streaming``: the agent's sparse-dense context (``agent.sparse_frames``,
    ``agent.dense_frames``) at a uniformly drawn point of the trajectory, i.e. what the streaming
    agent sees when it is asked there (see :func:`image2sim.navpolicy.data.make_sample`)."""
    max_trajectories: int | None = None
    """Behaviour cloning on the first N trajectories of ``shards`` only (in shard order; data-scaling
    curves). None: all. Not combinable with ``shard_weights``."""
    shuffle_instructions: bool = False
    """Control run: each training trajectory gets the instruction of another one (a fixed random
    permutation, seeded by ``train.seed``), so nothing ties instructions to paths. A policy trained so
    is the instruction-blind baseline: whatever it reaches, it reaches without reading."""
    end_cut_probability: float = 0.0
    """``streaming`` only: probability that a sample is cut at the trajectory's end (its last label the
    final STOP) instead of at a uniform point; 0 leaves STOP as rare as in the trajectories."""
    late_start_probability: float = 0.0
    """``streaming`` only: probability that a sample's episode starts at a later frame, as if the agent
    had been placed there, with the number of frames seen drawn independently of whether the cut is
    the end: the context's length is then no cue to STOP, only the view is. 0 = every sample starts at
    the episode's start."""
    wrong_goal_stop_probability: float = 0.0
    """Probability that a sample is replaced by a *wrong-goal end sample*: the trajectory cut at its
    end (where the expert stops beside its goal), told the instruction of a trajectory whose goal is
    another category (same scene when one exists), with no action labels, only a penalty on the
    model's probability of STOP there (``-log(1 - P(STOP))``). With the regular end samples it
    makes STOP depend on the instruction, not only on the view. Needs the data engine's
    ``extra.goal_category`` in the shard records (written since 2026-11-28); trajectories without
    one are never swapped. 0 = off."""
    goal_label: str = "in_view"
    """What ``train.goal_aux_weight``'s head learns per frame: ``in_view`` (the data engine's
    ``goal_in_view``: the goal object within 5 m, in the view and unoccluded) or ``near_end`` (at most
    ``near_end_forward_steps`` forward moves remain before the trajectory's final STOP: "the goal is
    reached", what ``agent.stop_gate`` asks; computed from the actions, so DAgger's finished
    trajectories have it too, and it does not depend on the instruction)."""
    near_end_forward_steps: int = 10
    """``near_end``'s reach in forward moves (10 x 0.25 m = 2.5 m of path, inside the 3 m success
    radius of the evaluation)."""
    num_workers: int = 0
    """DataLoader worker processes."""
    cache_frames: bool = False
    """Keep each trajectory's decoded frames in memory after its first read, instead of reading and
    decompressing its frame file for every sample (the sim2real shards: ~150 MB of 64x64 frames;
    each DataLoader worker keeps its own copy). Off by default: paper-scale shards do not fit."""


@dataclass
class TrainConfig:
    """Stage 1 behaviour cloning (Lightning)."""

    seed: int = 0
    """Seed of model init (tiny), data order and sampling."""
    batch_size: int = 2
    """Samples per device and step."""
    accumulate_grad_batches: int = 1
    """Gradient accumulation."""
    max_steps: int = 20
    """Optimizer steps."""
    max_minutes: float = 0.0
    """Wall-clock cap on fitting, in minutes (0: none). Training stops at the cap, keeps its last
    checkpoint and exports as if it had finished; the LR schedule still spans ``max_steps``, and
    ``nav train`` prints the step reached (``global_step``). For time-boxed machines (a lent GPU's
    minutes), not for results that must be reproducible step for step."""
    lr: float = 1e-3
    """Peak AdamW learning rate."""
    weight_decay: float = 0.0
    """AdamW weight decay."""
    goal_aux_weight: float = 0.0
    """Weight of an auxiliary grounding loss: a linear head on the language model's state at each
    image's last token predicts whether the instruction's goal is in that view (binary
    cross-entropy; labels from the shard records' ``goal_in_view``; samples without them add
    nothing). Only a model that ties the instruction's words to the image can lower it. The head is
    exported with the policy (``goal_head.safetensors``, which ``agent.stop_gate`` reads), and a
    source export's head trains on. 0: off (a source's head is then dropped from the export)."""
    goal_aux_layer: int = -1
    """Which language-model state the grounding head reads, as an index into the model's hidden
    states (embeddings, then each layer's output): -1 the final state, -2 the output of the layer
    before the last, and so on. In a causal model no later token can read the final state of the
    image's last token, so a fact the head finds there can never reach the action tokens; -2 asks
    for it where the last layer's attention at the action tokens can read it."""
    stop_weight: float = 1.0
    """Weight of the STOP decision in the action loss: the tokens of the expert's final STOP and each
    wrong-goal sample's "not STOP" (``data.wrong_goal_stop_probability``) count this many labels in
    the token mean. A streaming sample holds ~100 movement tokens and at most one STOP decision, the
    one place where the named goal must be matched against the view, so at 1 that decision is about
    1 % of the gradient. 1: the plain token mean."""
    warmup_steps: int = 2
    """Linear warm-up steps before cosine decay."""
    min_lr_ratio: float = 0.1
    """Final learning rate as a fraction of the peak."""
    grad_clip: float = 1.0
    """Gradient norm clip (0 disables)."""
    precision: str = "32-true"
    """Lightning precision (``bf16-mixed`` / ``bf16-true`` on GPU)."""
    strategy: str = "auto"
    """``auto``, ``ddp`` or ``deepspeed_zero2`` (CPU runs use the CPU DeepSpeed subclass)."""
    deepspeed_config: str = "configs/zero2.json"
    """DeepSpeed JSON used by ``deepspeed_zero2`` (relative to the repository root or absolute)."""
    accelerator: str = "cpu"
    """Lightning accelerator: cpu or gpu."""
    devices: int = 1
    """Processes/devices per node."""
    num_nodes: int = 1
    """Nodes (the paper: 8 nodes x 8 GPUs = 64 H20s); the global batch is batch_size x devices x
    num_nodes x accumulate_grad_batches."""
    log_every: int = 1
    """Log every N steps."""
    checkpoint_every: int = 10
    """Save a resumable checkpoint every N optimizer steps."""
    val_every: int = 100
    """With ``data.val_shards``: validate every N optimizer steps."""
    val_batches: int = 8
    """With ``data.val_shards``: batches per validation (the same ones every time)."""
    wandb: bool = False
    """Log to Weights & Biases besides CSV (``wandb_mode``; ``nav train --wandb`` sets both)."""
    wandb_mode: str = "offline"
    """offline | online: online only when ``$WANDB_MODE`` allows it too (``tracking.wandb_mode``)."""
    wandb_project: str = "image2nav"
    """W&B project name."""


@dataclass
class AgentConfig:
    """Streaming inference."""

    sparse_frames: int = 24
    """History frames sampled uniformly over the whole episode (global memory)."""
    dense_frames: int = 8
    """Most recent frames kept densely (local context)."""
    constrained: bool = True
    """Decode only token sequences that spell actions (a trie over the action encodings)."""
    max_new_tokens: int = 8
    """Generation budget per step when unconstrained."""
    fallback_action: int = 3
    """Action used when the output cannot be parsed (default TURN_RIGHT: safe and explores)."""
    reuse_cache: bool = True
    """Reuse the KV cache of the unchanged context prefix between steps."""
    stop_gate: float | None = None
    """STOP gated by the policy's goal head (``train.goal_aux_weight``; exported as
    ``goal_head.safetensors``): at each observation the head gives the probability that the
    instruction's goal is in view, and below this value the agent decodes its best actions other
    than STOP. ``None``: off (STOP is the language model's alone)."""


@dataclass
class DaggerConfig:
    """Stage 2: online DAgger in the NeuralSimulator (see :mod:`image2sim.navpolicy.dagger`)."""

    rounds: int = 2
    """Collect-then-train rounds; each round's data joins the aggregated dataset."""
    episodes_per_round: int = 4
    """Episodes rolled out per round."""
    train_steps_per_round: int = 10
    """Optimizer steps on the aggregated dataset after each collection."""
    lr: float | None = None
    """Peak learning rate of each round's updates (``None``: ``train.lr``). Every round restarts
    the warm-up cosine schedule, so at ``train.lr`` each round moves the policy as fast as the
    start of behaviour cloning did (docs/sim2real.md, "DAgger's learning rate")."""
    model_probability: float = 0.5
    """Probability that a control chunk is driven by the model (else by the oracle) in round 0."""
    final_model_probability: float = 0.9
    """Model probability in the last round (``schedule`` interpolates between the two)."""
    schedule: str = "linear"
    """``constant`` (always ``model_probability``), ``linear`` or ``exponential`` (geometric) over rounds."""
    chunk_min: int = 4
    """Shortest control chunk in steps (inclusive)."""
    chunk_max: int = 32
    """Longest control chunk in steps (inclusive); lengths are uniform in [chunk_min, chunk_max]."""
    max_steps: int = 200
    """Step cap per episode (the episode is truncated and logged as ``max_steps``)."""
    stop_on_stuck: bool = True
    """Truncate an episode when the simulator's stuck detector fires (logged as ``stuck``)."""
    override_model_stop: bool = True
    """A model STOP the oracle disagrees with is labelled but not executed (the oracle's action is),
    so an untrained policy's early STOPs do not end episodes after one step."""
    observe_every: int = 1
    """Render the observation of every n-th step only, plus every step where the model asks for
    actions (it asks every other step when it drives): 2 stores what the streaming agent and
    ``data.observation_stride: 2`` samples read, at half the rendering cost. Labels are kept at every
    step."""
    include_bc_data: bool = True
    """Seed the aggregated dataset with the BC shards (``data.shards``) when they exist."""
    seed: int = 0
    """Seed of chunk sampling and episode order."""
    render_device: str = "cpu"
    """Where the rollouts' Gaussian scenes render (``neural`` / ``splat_only`` sources): cpu, or
    cuda[:N] on a GPU machine; the observations match the CPU's up to rounding."""


@dataclass
class TaskConfig:
    """The procedural point-goal tasks of DAgger rollouts and of ``nav compare`` / ``nav act``."""

    goal_marker: bool = False
    """Stand a visible pillar on the goal and name it in the instruction (visual homing). Off: the
    goal is given only as metres relative to the start pose and must be tracked by path integration."""
    marker: GoalMarker = field(default_factory=GoalMarker)
    """The pillar's shape, colour and name (used when ``goal_marker`` is on)."""

    def active_marker(self) -> GoalMarker | None:
        """The marker when ``goal_marker`` is on, else ``None``."""
        return self.marker if self.goal_marker else None


@dataclass
class NavPolicyConfig:
    """Everything an Image2Nav run needs; saved beside every run's outputs."""

    name: str = "tiny"
    """Preset or run name."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Model construction and trainable parts."""
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    """Observation images."""
    data: DataConfig = field(default_factory=DataConfig)
    """Training data."""
    train: TrainConfig = field(default_factory=TrainConfig)
    """Behaviour cloning."""
    agent: AgentConfig = field(default_factory=AgentConfig)
    """Inference."""
    dagger: DaggerConfig = field(default_factory=DaggerConfig)
    """Online DAgger (stage 2)."""
    task: TaskConfig = field(default_factory=TaskConfig)
    """Procedural point-goal tasks (DAgger and the comparison against baselines)."""
    system_prompt: str = (
        "You are a navigation agent in an indoor environment. Follow the instruction. "
        "Actions: STOP, FORWARD (move 0.25 m), LEFT (turn 15 degrees), RIGHT (turn 15 degrees). "
        "After each observation reply with the next two actions, separated by a space."
    )
    """System prompt; the instruction is appended as ``Instruction: ...``."""

    def validate(self) -> NavPolicyConfig:
        """Check cross-field constraints; raise :class:`ConfigError` naming the field."""
        t = self.model.tiny
        if sum(t.mrope_section) * 2 != t.text_head_dim:
            raise ConfigError(f"model.tiny.mrope_section {t.mrope_section} must sum to text_head_dim/2")
        if round(t.num_position_embeddings**0.5) ** 2 != t.num_position_embeddings:
            raise ConfigError("model.tiny.num_position_embeddings must be a perfect square")
        if self.data.max_action_labels < 2 * 1 or self.data.max_observations < 1:
            raise ConfigError("data.max_observations and data.max_action_labels must be positive")
        self._validate_shard_weights()
        require_at_least(self, ("train.goal_aux_weight", "train.stop_weight"), 0)
        require_in_range(self, "train.goal_aux_layer", float("-inf"), -1)  # a negative hidden-state index
        require_at_least(self, ("train.val_every", "train.val_batches", "data.observation_stride"), 1)
        require_one_of(self, "data.sampling", ("uniform", "streaming"))
        require_one_of(self, "model.tiny.tokenizer_corpus", TOKENIZER_CORPORA)
        if self.data.max_trajectories is not None and (
            self.data.max_trajectories < 1 or self.data.shard_weights
        ):
            raise ConfigError("data.max_trajectories must be >= 1 and cannot be used with data.shard_weights")
        require_in_range(self, "data.end_cut_probability", 0.0, 1.0)
        require_one_of(self, "data.goal_label", GOAL_LABELS)
        require_at_least(self, "data.near_end_forward_steps", 0)
        if self.agent.stop_gate is not None:
            require_in_range(self, "agent.stop_gate", 0.0, 1.0)
        require_in_range(self, ("data.late_start_probability", "data.wrong_goal_stop_probability"), 0.0, 1.0)
        if self.data.sampling == "streaming" and (
            self.agent.sparse_frames + self.agent.dense_frames
            > min(self.data.max_observations, self.data.max_action_labels // 2)
        ):
            raise ConfigError(
                "data.sampling streaming: agent.sparse_frames + agent.dense_frames must fit "
                "data.max_observations (and data.max_action_labels / 2)"
            )
        require_one_of(self, "observation.camera", ("pinhole", "equirect"))
        if self.agent.sparse_frames < 0 or self.agent.dense_frames < 1:
            raise ConfigError("agent.dense_frames must be >= 1 and agent.sparse_frames >= 0")
        require_one_of(self, "agent.fallback_action", (0, 1, 2, 3))
        require_one_of(self, "train.strategy", ("auto", "ddp", "deepspeed_zero2"))
        d = self.dagger
        require_at_least(self, "dagger.observe_every", 1)
        if not 1 <= d.chunk_min <= d.chunk_max:
            raise ConfigError(
                f"dagger.chunk_min/chunk_max must satisfy 1 <= min <= max, got {d.chunk_min}, {d.chunk_max}"
            )
        require_in_range(self, ("dagger.model_probability", "dagger.final_model_probability"), 0.0, 1.0)
        require_one_of(self, "dagger.schedule", ("constant", "linear", "exponential"))
        require_render_device(self, "dagger.render_device")
        require_at_least(self, ("dagger.rounds", "dagger.episodes_per_round", "dagger.max_steps"), 1)
        require_at_least(self, "dagger.train_steps_per_round", 0)
        if self.dagger.lr is not None:
            require_at_least(self, "dagger.lr", 1e-12)
        require_at_least(self, "train.max_minutes", 0.0)
        require_one_of(self, "model.dtype", ("float32", "bfloat16", "float16"))
        return self

    def _validate_shard_weights(self) -> None:
        w, n = self.data.shard_weights, len(self.data.shards)
        if not w:
            return
        if len(w) != n:
            raise ConfigError(
                f"data.shard_weights has {len(w)} entries but data.shards has {n}: give one weight per "
                "shard, in the same order (or none: every trajectory equally likely)"
            )
        bad = [x for x in w if not (math.isfinite(x) and x >= 0)]
        if bad:
            raise ConfigError(f"data.shard_weights must be finite and >= 0, got {w}")
        if sum(w) <= 0:
            raise ConfigError(f"data.shard_weights must have a positive sum, got {w}")

    def to_dict(self) -> dict[str, Any]:
        """Plain data (YAML/JSON-safe)."""
        from image2sim.simulator.config import config_to_dict

        return config_to_dict(self)


def tiny_config() -> NavPolicyConfig:
    """CPU preset: tiny from-scratch model, 64x64 pinhole observations."""
    return NavPolicyConfig(name="tiny").validate()


def paper_config(checkpoint: str = "checkpoints/Qwen3-VL-4B-Instruct") -> NavPolicyConfig:
    """The paper's setting: Qwen3-VL-4B-Instruct (local folder), 336x336 pinhole at 90 deg,
    32 observations / 64 labels, DeepSpeed ZeRO-2, bf16, gradient checkpointing, 70K BC steps, then
    10K DAgger steps."""
    return NavPolicyConfig(
        name="paper",
        model=ModelConfig(source=checkpoint, gradient_checkpointing=True, dtype="bfloat16"),
        observation=ObservationConfig(camera="pinhole", height=336, width=336, hfov_deg=90.0, vfov_deg=90.0),
        data=DataConfig(max_observations=32, max_action_labels=64, observation_stride=2, num_workers=8),
        train=TrainConfig(
            batch_size=1,
            max_steps=70_000,
            lr=2e-5,
            weight_decay=0.0,
            warmup_steps=500,
            precision="bf16-mixed",
            strategy="deepspeed_zero2",
            accelerator="gpu",
            devices=8,
            num_nodes=8,
            log_every=10,
            checkpoint_every=1000,
            wandb=True,
        ),
        # Stage 2: 10K online DAgger updates (10 rounds x 1000 steps) with 4-32-step chunks. The
        # paper fixes the update budget and the chunks; rounds, episodes per round and the mixing
        # schedule are our choice.
        dagger=DaggerConfig(
            rounds=10,
            episodes_per_round=2000,
            train_steps_per_round=1000,
            model_probability=0.3,
            final_model_probability=0.9,
            schedule="linear",
            chunk_min=4,
            chunk_max=32,
            max_steps=500,
            observe_every=2,
        ),
    ).validate()


def paper_wide_config(checkpoint: str = "checkpoints/Qwen3-VL-4B-Instruct") -> NavPolicyConfig:
    """The paper's ultra-wide setting: 512x336 equirectangular crop at 180 deg HFOV x 118 deg VFOV."""
    cfg = paper_config(checkpoint)
    cfg.name = "paper-wide"
    cfg.observation = ObservationConfig(
        camera="equirect", height=336, width=512, hfov_deg=180.0, vfov_deg=118.0
    )
    return cfg.validate()


PRESETS = {"tiny": tiny_config, "paper": paper_config, "paper-wide": paper_wide_config}


def load_config(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> NavPolicyConfig:
    """A preset name (``tiny``/``paper``/``paper-wide``) or a YAML file of overrides (which may name
    its ``base`` preset), plus nested ``overrides``; unknown keys or wrong types raise
    :class:`ConfigError` naming the dotted field. Uses the repository's one config mechanism
    (:mod:`image2sim.simulator.config`)."""
    from image2sim.simulator import config as shared

    return shared.load_config(PRESETS, name_or_path, overrides).validate()


def from_dict(data: dict[str, Any]) -> NavPolicyConfig:
    """A config from plain data over the ``tiny`` defaults (e.g. a saved ``config.yaml``)."""
    from image2sim.simulator.config import config_from_dict

    return config_from_dict(NavPolicyConfig, data).validate()
