"""Build the Image2Nav policy: a Qwen3-VL model, its tokenizer and a torchvision-free image processor.

``source == "tiny"`` builds a small Qwen3-VL from scratch with the offline tokenizer; anything else
must be a local folder holding a Qwen3-VL checkpoint (config, safetensors, tokenizer,
``preprocessor_config.json``) — hub ids are refused, nothing is downloaded. The vision tower is
frozen; the vision-language merger (projector, incl. DeepStack mergers) and the language model train.
With LoRA enabled, the language model trains only through its adapters, and the merger still trains
unless ``train_merger`` is off.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from image2sim.navpolicy.actions import ActionCodec
from image2sim.navpolicy.config import ModelConfig, NavPolicyConfig, ObservationConfig
from image2sim.navpolicy.tokenizer import build_tiny_tokenizer, check_special_tokens, load_tokenizer
from image2sim.simulator.io.atomic import atomic_dir, atomic_path

MERGE_SIZE = 2
"""Qwen3-VL merges 2x2 patches into one language token."""

TEMPORAL_PATCH_SIZE = 2
"""Qwen3-VL patches are 2 frames deep; a still image is repeated."""

_PROJECTOR_PREFIXES = ("merger.", "deepstack_merger_list.")


@dataclass
class NavPolicy:
    """The pieces of one policy that always travel together."""

    model: torch.nn.Module
    """``Qwen3VLForConditionalGeneration`` (possibly wrapped by peft)."""
    tokenizer: object
    """A ``PreTrainedTokenizerFast`` with the Qwen special tokens."""
    image_processor: object
    """``Qwen2VLImageProcessorPil`` (no torchvision)."""
    codec: ActionCodec
    """Action <-> token sequences for ``tokenizer``."""
    goal_head: GoalHead | None = None
    """The grounding head trained with the language model (``train.goal_aux_weight``), when the
    policy has one: it reads "the named goal is in view" off an image's last token, and
    ``agent.stop_gate`` lets STOP through only where it says so."""

    @property
    def patch_size(self) -> int:
        return int(self.image_processor.patch_size)


GOAL_HEAD_FILE = "goal_head.safetensors"
"""File of an export holding its :class:`GoalHead` (absent when the policy has none)."""


class GoalHead(torch.nn.Module):
    """Linear probe of "the instruction's goal is in this view" on the language model's hidden state
    ``layer`` (an index into ``hidden_states``: -1 the final state) at an image's last token."""

    def __init__(self, hidden_size: int, layer: int = -1) -> None:
        super().__init__()
        if layer > -1:
            raise ValueError(f"GoalHead layer must be a negative hidden-state index, got {layer}")
        self.layer = int(layer)
        self.linear = torch.nn.Linear(hidden_size, 1)

    def forward(self, hidden: torch.Tensor) -> torch.Tensor:
        """(..., hidden) states -> (...) logits."""
        return self.linear(hidden.to(self.linear.weight.dtype)).squeeze(-1)

    def state_at(self, hidden_states: Sequence[torch.Tensor], rows, positions) -> torch.Tensor:
        """The states this head reads, at ``(rows, positions)`` of a model output's ``hidden_states``."""
        if -self.layer > len(hidden_states) - 1:  # index 0 holds the embeddings, not a layer's output
            raise ValueError(
                f"the goal head reads hidden state {self.layer} (train.goal_aux_layer), but the "
                f"language model has {len(hidden_states) - 1} layers"
            )
        return hidden_states[self.layer][rows, positions]

    def probability(self, hidden_states: Sequence[torch.Tensor], rows, positions) -> torch.Tensor:
        """P(the instruction's goal is in view) at ``(rows, positions)`` of ``hidden_states``."""
        return torch.sigmoid(self(self.state_at(hidden_states, rows, positions)))

    def save(self, path: str | Path) -> None:
        """safetensors, its layer in the metadata; written atomically."""
        from safetensors.torch import save_file

        tensors = {k: v.detach().float().contiguous() for k, v in self.linear.state_dict().items()}
        with atomic_path(path) as tmp:
            save_file(tensors, str(tmp), metadata={"format": "image2sim-goal-head", "layer": str(self.layer)})

    @classmethod
    def load(cls, path: str | Path) -> GoalHead:
        """A head written by :meth:`save`; a malformed file is an error naming it."""
        from safetensors import safe_open

        with safe_open(str(path), framework="pt") as f:
            meta = f.metadata() or {}
            tensors = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 (safe_open has no iterator)
        w = tensors.get("weight")
        if meta.get("format") != "image2sim-goal-head" or w is None or w.ndim != 2 or w.shape[0] != 1:
            raise ValueError(f"{path}: not an image2sim goal head (format metadata, a (1, hidden) 'weight')")
        try:
            head = cls(int(w.shape[1]), int(meta.get("layer", "-1")))
            head.linear.load_state_dict(tensors)
        except (ValueError, RuntimeError) as exc:
            raise ValueError(f"{path}: {exc}") from exc
        return head


def tiny_qwen3vl_config(tiny, tokenizer):
    """A ``Qwen3VLConfig`` of the given tiny sizes, wired to ``tokenizer``'s special token ids."""
    from transformers import Qwen3VLConfig

    ids = check_special_tokens(tokenizer)
    return Qwen3VLConfig(
        text_config=dict(
            vocab_size=len(tokenizer),
            hidden_size=tiny.text_hidden_size,
            intermediate_size=tiny.text_intermediate_size,
            num_hidden_layers=tiny.text_layers,
            num_attention_heads=tiny.text_heads,
            num_key_value_heads=tiny.text_kv_heads,
            head_dim=tiny.text_head_dim,
            max_position_embeddings=32768,
            rope_parameters={
                "rope_type": "default",
                "rope_theta": 10000.0,
                "mrope_section": list(tiny.mrope_section),
                "mrope_interleaved": True,
            },
            pad_token_id=ids["<|endoftext|>"],
        ),
        vision_config=dict(
            depth=tiny.vision_layers,
            hidden_size=tiny.vision_hidden_size,
            intermediate_size=tiny.vision_intermediate_size,
            num_heads=tiny.vision_heads,
            patch_size=tiny.patch_size,
            spatial_merge_size=MERGE_SIZE,
            temporal_patch_size=TEMPORAL_PATCH_SIZE,
            out_hidden_size=tiny.text_hidden_size,
            num_position_embeddings=tiny.num_position_embeddings,
            deepstack_visual_indexes=list(tiny.deepstack_visual_indexes),
        ),
        image_token_id=ids["<|image_pad|>"],
        video_token_id=ids["<|video_pad|>"],
        vision_start_token_id=ids["<|vision_start|>"],
        vision_end_token_id=ids["<|vision_end|>"],
        tie_word_embeddings=False,
    )


def make_image_processor(obs: ObservationConfig, patch_size: int):
    """PIL-based Qwen image processor that keeps ``obs.height x obs.width`` (rounded to the patch grid).

    Fixing min == max pixels to the observation area makes ``smart_resize`` keep the aspect ratio
    and snap each side to a multiple of ``patch_size * 2`` (a no-op for conforming sizes).
    """
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

    factor = patch_size * MERGE_SIZE
    h = max(factor, round(obs.height / factor) * factor)
    w = max(factor, round(obs.width / factor) * factor)
    return Qwen2VLImageProcessorPil(
        patch_size=patch_size,
        merge_size=MERGE_SIZE,
        temporal_patch_size=TEMPORAL_PATCH_SIZE,
        size={"shortest_edge": h * w, "longest_edge": h * w},
        image_mean=list(obs.image_mean),
        image_std=list(obs.image_std),
    )


def load_image_processor(path: str | Path):
    """The PIL image processor from a local checkpoint's ``preprocessor_config.json``."""
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

    p = Path(path) / "preprocessor_config.json"
    if not p.is_file():
        raise FileNotFoundError(f"{p} not found: a local Qwen3-VL checkpoint needs its preprocessor config")
    raw = json.loads(p.read_text())
    keep = {
        "patch_size",
        "merge_size",
        "temporal_patch_size",
        "size",
        "image_mean",
        "image_std",
        "min_pixels",
        "max_pixels",
        "do_rescale",
        "rescale_factor",
        "do_normalize",
        "do_convert_rgb",
    }
    return Qwen2VLImageProcessorPil(**{k: v for k, v in raw.items() if k in keep})


def _torch_dtype(name: str) -> torch.dtype:
    return {"float32": torch.float32, "bfloat16": torch.bfloat16, "float16": torch.float16}[name]


def freeze_for_training(model: torch.nn.Module, cfg: ModelConfig) -> None:
    """Freeze the vision tower (keeping the merger/projector trainable when ``cfg.train_merger``)."""
    visual = base_qwen(model).model.visual
    for name, p in visual.named_parameters():
        is_projector = name.startswith(_PROJECTOR_PREFIXES)
        p.requires_grad_(not cfg.freeze_vision or (cfg.train_merger and is_projector))


def base_qwen(model: torch.nn.Module):
    """The ``Qwen3VLForConditionalGeneration`` inside a possible peft wrapper."""
    from transformers import Qwen3VLForConditionalGeneration

    m = model.get_base_model() if hasattr(model, "get_base_model") else model  # peft wrapper
    if isinstance(m, Qwen3VLForConditionalGeneration):
        return m
    raise TypeError(f"{type(model).__name__} does not wrap a Qwen3VLForConditionalGeneration")


def projector_modules(model: torch.nn.Module) -> list[str]:
    """Names of the vision-language projectors (merger and DeepStack mergers), as peft's
    ``modules_to_save`` matches them (a suffix of the module's full name)."""
    visual = base_qwen(model).model.visual
    names = ["visual.merger"]
    names += [f"visual.deepstack_merger_list.{i}" for i in range(len(visual.deepstack_merger_list))]
    return names


def apply_lora(model: torch.nn.Module, cfg: ModelConfig) -> torch.nn.Module:
    """Wrap the language model's projections with LoRA; keep the projector trainable if asked.

    peft freezes every non-adapter weight. The projectors train as peft ``modules_to_save`` (a
    trainable copy beside the frozen original), so the saved adapter carries them and
    ``PeftModel.from_pretrained(base, adapter)`` reproduces the trained policy.
    """
    from peft import LoraConfig, get_peft_model

    lcfg = LoraConfig(
        r=cfg.lora.r,
        lora_alpha=cfg.lora.alpha,
        lora_dropout=cfg.lora.dropout,
        target_modules=cfg.lora.target_modules,
        bias="none",
        modules_to_save=projector_modules(model) if cfg.train_merger else None,
    )
    return get_peft_model(model, lcfg)


def tokenizer_corpus(cfg: NavPolicyConfig, dataset=None) -> list[str]:
    """The training instructions a tiny policy's tokenizer learns from (``model.tiny.tokenizer_corpus
    == "instructions"``): those of ``dataset`` when given, else of ``cfg.data.shards``; empty for
    the built-in corpus or a pretrained source, whose tokenizer is fixed."""
    if cfg.model.source != "tiny" or cfg.model.tiny.tokenizer_corpus != "instructions":
        return []
    if dataset is not None:
        return [dataset.instruction_of(i) for i in range(len(dataset))]
    from image2sim.navpolicy.data import shard_instructions

    return shard_instructions(cfg.data.shards)


def policy_tokenizer(cfg: NavPolicyConfig, corpus: Sequence[str] = ()):
    """The tokenizer of ``cfg``'s policy: the offline tiny BPE (its merges also learned on
    ``corpus`` when ``model.tiny.tokenizer_corpus == "instructions"``), or a local checkpoint's."""
    mc = cfg.model
    if mc.source != "tiny":
        return load_tokenizer(mc.source)
    extra = corpus if mc.tiny.tokenizer_corpus == "instructions" else ()
    return build_tiny_tokenizer(mc.tiny.tokenizer_vocab_size, extra_corpus=extra)


def build_policy(cfg: NavPolicyConfig, seed: int | None = None, corpus: Sequence[str] = ()) -> NavPolicy:
    """Model + tokenizer + image processor + action codec for ``cfg`` (frozen parts applied).

    ``corpus``: the training instructions, which the tiny tokenizer's merges learn from when
    ``model.tiny.tokenizer_corpus == "instructions"`` (:func:`tokenizer_corpus` gathers them).
    """
    from transformers import Qwen3VLForConditionalGeneration

    mc = cfg.model
    if mc.source == "tiny":
        if mc.tiny.tokenizer_corpus == "instructions" and not corpus:
            raise ValueError(
                "model.tiny.tokenizer_corpus='instructions' needs the training instructions to learn "
                "the tokenizer from; none were given (no data.shards?)"
            )
        tokenizer = policy_tokenizer(cfg, corpus)
        if seed is not None:
            torch.manual_seed(seed)
        qcfg = tiny_qwen3vl_config(mc.tiny, tokenizer)
        qcfg._attn_implementation = mc.attn_implementation
        model = Qwen3VLForConditionalGeneration(qcfg).to(_torch_dtype(mc.dtype))
        image_processor = make_image_processor(cfg.observation, mc.tiny.patch_size)
    else:
        path = Path(mc.source)
        if not path.is_dir():
            raise FileNotFoundError(
                f"model.source {mc.source!r} is neither 'tiny' nor a local folder (hub ids are refused)"
            )
        tokenizer = policy_tokenizer(cfg)
        model = Qwen3VLForConditionalGeneration.from_pretrained(
            str(path),
            local_files_only=True,
            dtype=_torch_dtype(mc.dtype),
            attn_implementation=mc.attn_implementation,
        )
        image_processor = make_image_processor(cfg.observation, int(model.config.vision_config.patch_size))
        pre = load_image_processor(path)
        image_processor.image_mean, image_processor.image_std = pre.image_mean, pre.image_std
    if mc.vision_weights:
        from image2sim.navpolicy.vision_pretrain import load_vision_weights

        load_vision_weights(model, mc.vision_weights)
    freeze_for_training(model, mc)
    if mc.gradient_checkpointing:
        enable_checkpointing(model)
        model.config.use_cache = False
    if mc.lora.enabled:
        model = apply_lora(model, mc)
    codec = ActionCodec.from_tokenizer(tokenizer)
    goal_head = None
    head_file = Path(mc.source) / GOAL_HEAD_FILE
    if mc.source != "tiny" and head_file.is_file():
        goal_head = GoalHead.load(head_file)
        hidden = int(base_qwen(model).config.text_config.hidden_size)
        if goal_head.linear.in_features != hidden:
            raise ValueError(
                f"{head_file}: {goal_head.linear.in_features} inputs, but the language model's "
                f"hidden size is {hidden}"
            )
    return NavPolicy(
        model=model, tokenizer=tokenizer, image_processor=image_processor, codec=codec, goal_head=goal_head
    )


def enable_checkpointing(model: torch.nn.Module) -> None:
    """Non-reentrant activation checkpointing (the newer transformers name when it exists)."""
    kwargs = {"use_reentrant": False}
    if hasattr(model, "activation_checkpointing_enable"):
        model.activation_checkpointing_enable(activation_checkpointing_kwargs=kwargs)
    else:
        model.gradient_checkpointing_enable(gradient_checkpointing_kwargs=kwargs)


def trainable_summary(model: torch.nn.Module) -> dict[str, int]:
    """Parameter counts: total, trainable, and trainable inside the vision tower proper."""
    total = sum(p.numel() for p in model.parameters())
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    vis = base_qwen(model).model.visual
    vis_trainable = sum(
        p.numel()
        for n, p in vis.named_parameters()
        if p.requires_grad and not n.startswith(_PROJECTOR_PREFIXES)
    )
    return {"total": total, "trainable": trainable, "vision_tower_trainable": vis_trainable}


def merged_model(model: torch.nn.Module) -> torch.nn.Module:
    """Fold LoRA adapters into the base weights; returns the plain Qwen3-VL model."""
    if hasattr(model, "merge_and_unload"):
        return model.merge_and_unload()
    return model


ADAPTER_DIR = "adapter"
"""Sub-folder of an export holding the unmerged LoRA adapter (peft ``save_pretrained``)."""


def export_policy(
    policy: NavPolicy,
    out_dir: str | Path,
    cfg: NavPolicyConfig | None = None,
    metrics: str | Path | None = None,
    data: list[str | Path] | None = None,
) -> Path:
    """Write the policy as a Hugging Face folder: merged weights (safetensors) and config, tokenizer
    with the policy's chat template, image processor and a model card (``README.md``).

    The folder reloads with ``build_policy`` (``model.source = out_dir``) or with
    ``AutoModelForImageTextToText.from_pretrained``. With LoRA the unmerged adapter is saved first to
    ``<out_dir>/adapter`` (``PeftModel.from_pretrained(base, <out_dir>/adapter)``); then the adapters
    are merged in place (peft's ``merge_and_unload``) and ``policy.model`` becomes the merged plain
    model: export at the end of training. The policy's goal head, if any, goes to
    ``goal_head.safetensors``. ``cfg`` (the run's config), ``data`` (the training shards
    and files; default ``cfg.data.shards``) and ``metrics`` (a metrics JSON) go into the card. The
    folder is written whole (temp folder + rename), so a crash never leaves a half-written export.
    """
    from image2sim.navpolicy.card import write_model_card
    from image2sim.navpolicy.prompting import chat_template

    with atomic_dir(out_dir) as tmp:
        adapter = None
        if hasattr(policy.model, "peft_config"):
            adapter = tmp / ADAPTER_DIR
            policy.model.save_pretrained(str(adapter), safe_serialization=True)
        policy.model = merged_model(policy.model)
        policy.model.save_pretrained(str(tmp), safe_serialization=True)
        policy.tokenizer.chat_template = chat_template()
        policy.tokenizer.save_pretrained(str(tmp))
        # The processor object cannot save itself without a video processor; write its config alone.
        policy.image_processor.save_pretrained(str(tmp))
        if policy.goal_head is not None:
            policy.goal_head.save(tmp / GOAL_HEAD_FILE)
        write_model_card(
            tmp,
            policy.model,
            cfg,
            metrics=metrics,
            adapter=adapter is not None,
            data=data,
            goal_head=policy.goal_head is not None,
        )
    return Path(out_dir)


def make_processor(policy: NavPolicy):
    """A ``Qwen3VLProcessor`` over the policy's tokenizer and PIL image processor, without video.

    The stock class insists on a (torchvision) video processor; this subclass accepts ``None``.
    ``save_pretrained`` is not supported on it: save the tokenizer and image processor separately
    (as :func:`export_policy` does). The collator builds ids itself; this processor is the reference
    it is tested against and the entry point for callers that prefer chat text.
    """
    from transformers import Qwen3VLProcessor

    class _ImageOnlyQwen3VLProcessor(Qwen3VLProcessor):
        def check_argument_for_proper_class(self, argument_name, argument):
            if argument_name == "video_processor" and argument is None:
                return None
            return super().check_argument_for_proper_class(argument_name, argument)

    return _ImageOnlyQwen3VLProcessor(
        image_processor=policy.image_processor, tokenizer=policy.tokenizer, video_processor=None
    )
