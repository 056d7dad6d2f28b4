"""Local Qwen3-VL backend through transformers (checkpoint from a local folder only, never downloaded).

The folder must hold a ``Qwen3VLForConditionalGeneration`` checkpoint with its tokenizer and image
processor. The PIL image processor is used (the default one needs torchvision, which this stack
cannot import).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

from image2sim.dataengine.annotate.prompts import Annotation, AnnotationRequest
from image2sim.dataengine.annotate.vlm import annotate_one

__all__ = ["TransformersAnnotator"]


class TransformersAnnotator:
    """Greedy generation with a local Qwen3-VL checkpoint."""

    name = "transformers"

    def __init__(
        self,
        path: str | Path,
        vocabulary: Iterable[str] = (),
        max_new_tokens: int = 384,
        max_attempts: int = 2,
    ) -> None:
        path = Path(path)
        if not (path / "config.json").is_file():
            raise FileNotFoundError(f"{path}: not a local transformers checkpoint (config.json missing)")
        import os

        os.environ.setdefault("HF_HUB_OFFLINE", "1")
        from transformers import AutoTokenizer, Qwen3VLForConditionalGeneration
        from transformers.models.qwen2_vl.image_processing_pil_qwen2_vl import Qwen2VLImageProcessorPil

        self.tokenizer = AutoTokenizer.from_pretrained(path, local_files_only=True)
        self.image_processor = Qwen2VLImageProcessorPil.from_pretrained(path, local_files_only=True)
        self.model = Qwen3VLForConditionalGeneration.from_pretrained(path, local_files_only=True).eval()
        self.vocabulary = list(vocabulary)
        self.max_new_tokens = int(max_new_tokens)
        self.max_attempts = int(max_attempts)

    def complete(self, messages: list[dict]) -> str:
        import torch

        images, text = [], ""
        for m in messages:
            text += f"<|im_start|>{m['role']}\n"
            parts = (
                m["content"] if isinstance(m["content"], list) else [{"type": "text", "text": m["content"]}]
            )
            for p in parts:
                if p["type"] == "image":
                    images.append(p["image"])
                    text += "<|vision_start|><|image_pad|><|vision_end|>"
                else:
                    text += p["text"] + "\n"
            text += "<|im_end|>\n"
        text += "<|im_start|>assistant\n"
        kwargs = {}
        if images:
            proc = self.image_processor(images=images, return_tensors="pt")
            merge = int(getattr(self.image_processor, "merge_size", 2))
            counts = (proc["image_grid_thw"].prod(-1) // merge**2).tolist()
            pieces = text.split("<|image_pad|>")
            pads = ["<|image_pad|>" * int(n) for n in counts]
            text = pieces[0] + "".join(a + b for a, b in zip(pads, pieces[1:], strict=True))
            kwargs = {"pixel_values": proc["pixel_values"], "image_grid_thw": proc["image_grid_thw"]}
        enc = self.tokenizer(text, return_tensors="pt")
        pad_id = self.tokenizer.convert_tokens_to_ids("<|image_pad|>")
        kwargs["mm_token_type_ids"] = (enc["input_ids"] == pad_id).long()
        with torch.no_grad():
            out = self.model.generate(**enc, **kwargs, max_new_tokens=self.max_new_tokens, do_sample=False)
        return self.tokenizer.decode(out[0, enc["input_ids"].shape[1] :], skip_special_tokens=True)

    def annotate(self, requests: list[AnnotationRequest]) -> list[Annotation]:
        return [annotate_one(r, self.complete, self.vocabulary, self.max_attempts) for r in requests]
