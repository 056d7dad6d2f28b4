"""Collating Image2Nav samples into Qwen3-VL batches: image patches, interleaved prompts with
action-only labels, and the training-only entries the losses read (grounding labels, the STOP
decision's token masks).

Split from :mod:`image2sim.navpolicy.data`, which keeps what a sample is and where samples come
from (trajectories, shards, datasets); this module turns samples into model inputs.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from image2sim.navpolicy.data import NavSample
from image2sim.navpolicy.model import MERGE_SIZE
from image2sim.navpolicy.prompting import IGNORE_INDEX, PromptBuilder, Turn
from image2sim.simulator.conventions import Action


def image_token_counts(image_grid_thw: torch.Tensor, merge_size: int = MERGE_SIZE) -> list[int]:
    """``<|image_pad|>`` tokens per image: t*h*w patches merged ``merge_size``^2 to one token."""
    return [int(v) for v in (image_grid_thw.prod(-1) // (merge_size**2)).tolist()]


def image_end_positions(mm_token_type_ids: torch.Tensor) -> torch.Tensor:
    """(num_images, 2) [row, position] of each image's last token, images in prompt order (row by
    row): where a causal model has read the instruction and the whole image."""
    mm = mm_token_type_ids != 0
    nxt = torch.zeros_like(mm)
    nxt[:, :-1] = mm[:, 1:]
    return torch.nonzero(mm & ~nxt)


def patchify_batch(images: Sequence[np.ndarray], processor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """The Qwen image processor's output for a batch of equal-sized frames, in one vectorised pass.

    The processor handles one image at a time in Python (rescale, normalise, patchify): about 0.4 ms
    per 64x64 frame, a fifth of a training step at batch 16. When every frame is an (H, W, 3) uint8
    array of the same size that the processor would not resize (``smart_resize`` keeps it), this
    computes the same ``pixel_values`` and ``image_grid_thw`` (the same arithmetic, so bit-equal:
    tested against the processor). Returns None otherwise, and the caller uses the processor.
    """
    from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import smart_resize

    if not images:
        return None
    first = np.asarray(images[0])
    if first.dtype != np.uint8 or first.ndim != 3 or first.shape[2] != 3:
        return None
    if any(np.asarray(im).shape != first.shape or np.asarray(im).dtype != np.uint8 for im in images):
        return None
    p = processor
    patch, merge, temporal = int(p.patch_size), int(p.merge_size), int(p.temporal_patch_size)
    h, w = first.shape[:2]
    size = p.size if isinstance(p.size, dict) else dict(p.size)
    if not (p.do_rescale and p.do_normalize) or getattr(p, "do_convert_rgb", True) is False:
        return None
    if p.do_resize and smart_resize(
        h, w, factor=patch * merge, min_pixels=size["shortest_edge"], max_pixels=size["longest_edge"]
    ) != (h, w):
        return None
    if h % (patch * merge) or w % (patch * merge):
        return None
    # The processor's arithmetic: rescale in float64, cast to float32, normalise in float32.
    x = (
        torch.from_numpy(np.stack([np.asarray(im) for im in images])).double() * float(p.rescale_factor)
    ).float()
    mean = torch.tensor(np.asarray(p.image_mean, dtype=np.float32))
    std = torch.tensor(np.asarray(p.image_std, dtype=np.float32))
    x = ((x - mean) / std).permute(0, 3, 1, 2)
    n, c = x.shape[:2]
    gh, gw = h // patch, w // patch
    x = x.reshape(n, c, gh // merge, merge, patch, gw // merge, merge, patch)
    x = x.permute(0, 2, 5, 3, 6, 1, 4, 7)  # (N, gh/m, gw/m, m, m, C, p, p)
    x = x[:, :, :, :, :, :, None].expand(*x.shape[:6], temporal, patch, patch)
    pixel_values = x.reshape(n * gh * gw, c * temporal * patch * patch)
    grid = torch.tensor([[1, gh, gw]], dtype=torch.int64).expand(n, 3).contiguous()
    return pixel_values, grid


TRAINING_ONLY_KEYS = ("episode_ids", "goal_in_view", "image_end", "stop_negative_mask", "stop_positive_mask")
"""Entries of a :class:`NavCollator` batch for the training module (losses, logging), not the model."""


def model_inputs(batch: dict) -> dict:
    """The entries of a collated batch that the model's forward takes."""
    return {k: v for k, v in batch.items() if k not in TRAINING_ONLY_KEYS}


class NavCollator:
    """Turns :class:`NavSample` lists into padded Qwen3-VL batches with action-only labels.

    Output keys: ``input_ids``, ``attention_mask``, ``labels``, ``mm_token_type_ids`` (B, L), right
    padded with the pad token; ``pixel_values`` (all patches of all images, sample-major) and
    ``image_grid_thw`` (num_images, 3).
    """

    def __init__(self, prompt_builder: PromptBuilder, image_processor) -> None:
        self.prompts = prompt_builder
        self.image_processor = image_processor
        self.pad_id = int(prompt_builder.tokenizer.pad_token_id)

    def process_images(self, images: Sequence[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
        """Pixel patches and grids of ``images``: :func:`patchify_batch` when it applies (equal-sized
        uint8 frames the processor would not resize), else the (PIL) Qwen image processor."""
        fast = patchify_batch(images, self.image_processor)
        if fast is not None:
            return fast
        out = self.image_processor(images=[np.asarray(im) for im in images], return_tensors="pt")
        return out["pixel_values"], out["image_grid_thw"]

    def __call__(self, samples: Sequence[NavSample]) -> dict[str, torch.Tensor]:
        if not samples:
            raise ValueError("cannot collate an empty list of samples")
        images = [im for s in samples for im in s.observations]
        pixel_values, grid = self.process_images(images)
        counts = image_token_counts(grid, self.image_processor.merge_size)
        encs, k = [], 0
        for s in samples:
            turns = []
            for j in range(len(s.observations)):
                turns.append(
                    Turn(
                        frame_key=s.steps[j],
                        num_image_tokens=counts[k],
                        executed=tuple(s.executed[j]),
                        target=tuple(s.targets[j]),
                    )
                )
                k += 1
            encs.append(self.prompts.encode(s.instruction, turns))
        length = max(len(e) for e in encs)
        b = len(encs)
        input_ids = torch.full((b, length), self.pad_id, dtype=torch.long)
        labels = torch.full((b, length), IGNORE_INDEX, dtype=torch.long)
        mm = torch.zeros((b, length), dtype=torch.long)
        attn = torch.zeros((b, length), dtype=torch.long)
        stop_negative = (
            torch.zeros((b, length), dtype=torch.bool) if any(s.stop_negative for s in samples) else None
        )
        stop_positive = torch.zeros((b, length), dtype=torch.bool)
        for i, e in enumerate(encs):
            n = len(e)
            input_ids[i, :n] = torch.tensor(e.input_ids)
            labels[i, :n] = torch.tensor(e.labels)
            mm[i, :n] = torch.tensor(e.mm_token_type_ids)
            attn[i, :n] = 1
            stop = self.final_stop_positions(e.labels, samples[i].targets[-1])
            if samples[i].stop_negative:
                stop_negative[i, stop] = True
                labels[i] = IGNORE_INDEX  # the actions followed another goal: no labels
            else:
                stop_positive[i, stop] = True
        # Belt and braces: no label may ever sit on an image token.
        labels[mm != 0] = IGNORE_INDEX
        batch = {
            "input_ids": input_ids,
            "attention_mask": attn,
            "labels": labels,
            "mm_token_type_ids": mm,
            "pixel_values": pixel_values,
            "image_grid_thw": grid,
        }
        if any(s.goal_in_view is not None for s in samples):
            batch["goal_in_view"] = torch.tensor(
                [v for s in samples for v in (s.goal_in_view or [-1] * len(s.observations))],
                dtype=torch.float32,
            )
            batch["image_end"] = image_end_positions(mm)
        if stop_negative is not None:
            batch["stop_negative_mask"] = stop_negative
        if bool(stop_positive.any()):
            batch["stop_positive_mask"] = stop_positive
        return batch

    def final_stop_positions(self, labels: Sequence[int], target: Sequence[int]) -> list[int]:
        """Token positions of the STOP action in the last reply (``target``), read off the labelled
        positions (every reply's action pieces are labelled, in order); [] when it has no STOP."""
        actions = [int(a) for a in target]
        if int(Action.STOP) not in actions:
            return []
        pieces = self.prompts.codec.encode(actions)
        labelled = [p for p, v in enumerate(labels) if v != IGNORE_INDEX]
        last = labelled[len(labelled) - sum(len(pc) for pc in pieces) :]
        k = actions.index(int(Action.STOP))
        start = sum(len(pc) for pc in pieces[:k])
        return last[start : start + len(pieces[k])]
