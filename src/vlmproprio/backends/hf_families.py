"""What the hf backend does differently for some model families: how a batch's images reach its prompts, and
the one line a model gets when its family needs a library that is not installed (docs/models.md)."""

from __future__ import annotations

import json
from pathlib import Path

# Processors that tell which images belong to which prompt of a batch only by a list of images per prompt (they
# refuse a flat list for a batch of several prompts); the others take one flat list in prompt order.
# LLaVA-OneVision takes a flat list too, but then treats every image as a prompt's only one (anyres tiles for each,
# where a prompt of several images gets one view per image).
NESTED_IMAGE_PROCESSORS = frozenset(
    {"Gemma3Processor", "Idefics3Processor", "SmolVLMProcessor", "MllamaProcessor", "LlavaOnevisionProcessor"}
)


def processor_images(processor, per_request: list[list]) -> list | None:
    """The images of a batch as ``processor`` takes them: None without any, else flat or one list per prompt."""
    if not any(per_request):
        return None
    if any(cls.__name__ in NESTED_IMAGE_PROCESSORS for cls in type(processor).__mro__):
        return per_request
    return [img for row in per_request for img in row]


def _model_type(path: Path) -> str:
    try:
        return str(json.loads((path / "config.json").read_text()).get("model_type") or "unknown")
    except (OSError, ValueError, AttributeError):
        return "unknown"


def missing_library_message(model_id: str, path: Path, exc: ImportError) -> str:
    """One line for a model whose processor or model class needs a library that is not installed: the model, its
    family, what is missing and the fix (transformers' own message is a paragraph)."""
    family = _model_type(path)
    first = " ".join(str(exc).split()).split(". ")[0].rstrip(".") or type(exc).__name__  # its first sentence
    if "torchvision" in str(exc).lower() or getattr(exc, "name", "") == "torchvision":
        return (
            f"cannot load {model_id} (family {family}): {first}; transformers has no PIL-only "
            "processor for this family: install the torchvision that matches your torch "
            "(pip install torchvision==<the torch version's pair>) to run it"
        )
    return f"cannot load {model_id} (family {family}): {first}; install the missing package to run it"
