"""Prompt lengths for the hf backend's scheduler, counted piece by piece with a cache.

The scheduler needs the token count of every chat text of a wave (a Process 1
wave of the benchmark is ~1200 prompts of ~3.6 kB each). Most of a prompt is
the same for every request (the system prompt, the task and its worked
example, "Image k:" lines); only the state text differs. So a text is cut at
the tokenizer's added tokens (``<|im_start|>``, ``<|image_pad|>``, ...), each
piece between them is tokenized once per backend and remembered, and a text's
count is the number of added tokens plus the counts of its pieces.

Exactly the count of tokenizing the whole text: a fast tokenizer itself first
splits its input at the added tokens (leftmost, longest first) and then
normalizes, pre-tokenizes and encodes each piece on its own, so no token ever
spans a cut. That holds for added tokens matched on the raw text as they are:
not ``normalized``, no ``lstrip``/``rstrip`` (which would eat the whitespace
next to them), not ``single_word``; and when special tokens are not split
(``split_special_tokens``); and for pre-tokenizers that treat every piece
alike: a ``Metaspace`` pre-tokenizer with ``prepend_scheme="first"`` (Llama-2
and Mistral style tokenizers, as in LLaVA-1.5) marks only the piece at the start
of the whole text as a word start, so a piece tokenized alone can come out one
token longer. Such tokenizers count whole texts (slower, never wrong); and the first texts a
counter sees are also counted whole, and any difference turns cutting off for
good. Tests compare both counts on the pipeline's real prompts and on a
``Metaspace`` tokenizer.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence

# Distinct pieces remembered per backend: the shared template parts and one state text per request of a wave
# or two; the cache is emptied when it grows past this (a long run has more distinct states than that).
MAX_PIECES = 8192
CHECKED_TEXTS = 4  # of the first texts a counter sees, counted both ways


def _prepends_to_first_piece_only(node: object) -> bool:
    """Whether a tokenizer's JSON description holds a Metaspace pre-tokenizer that prepends to the first piece
    of a text only (its pieces then tokenize differently alone)."""
    if isinstance(node, dict):
        if node.get("type") == "Metaspace" and node.get("prepend_scheme") == "first":
            return True
        return any(_prepends_to_first_piece_only(v) for v in node.values())
    if isinstance(node, list):
        return any(_prepends_to_first_piece_only(v) for v in node)
    return False


def added_token_pattern(tokenizer) -> re.Pattern[str] | None:
    """A regex that cuts text where ``tokenizer`` does (its added tokens), or None where cutting is not exact."""
    backend = getattr(tokenizer, "backend_tokenizer", None)
    if backend is None or getattr(tokenizer, "split_special_tokens", False):
        return None
    added = list(backend.get_added_tokens_decoder().values())
    if not added or any(a.normalized or a.lstrip or a.rstrip or a.single_word for a in added):
        return None
    if _prepends_to_first_piece_only(json.loads(backend.to_str()).get("pre_tokenizer")):
        return None
    # longest first: among added tokens starting at one position the longest wins, as in the tokenizer
    contents = sorted({a.content for a in added}, key=lambda c: (-len(c), c))
    return re.compile("(" + "|".join(map(re.escape, contents)) + ")")


class PromptTokenCounter:
    """Token counts of texts (no special tokens added), with the pieces between added tokens cached."""

    def __init__(self, tokenizer) -> None:
        self.tokenizer = tokenizer
        self.pattern = added_token_pattern(tokenizer)
        self._pieces: dict[str, int] = {}
        self._unchecked = CHECKED_TEXTS

    def counts(self, texts: Sequence[str]) -> list[int]:
        if self.pattern is not None and self._unchecked > 0:
            sample = list(texts[: self._unchecked])
            self._unchecked -= len(sample)
            if self._by_pieces(sample) != self._tokenize(sample):  # a tokenizer this module does not foresee
                self.pattern, self._pieces = None, {}
        if self.pattern is None:
            return self._tokenize(texts)
        return self._by_pieces(texts)

    def _by_pieces(self, texts: Sequence[str]) -> list[int]:
        split = [self.pattern.split(t) for t in texts]  # text, added token, text, ..., text
        new = list(dict.fromkeys(p for parts in split for p in parts[::2] if p and p not in self._pieces))
        if len(self._pieces) + len(new) > MAX_PIECES:
            self._pieces.clear()
            new = list(dict.fromkeys(p for parts in split for p in parts[::2] if p))
        self._pieces.update(zip(new, self._tokenize(new), strict=True))
        return [len(parts) // 2 + sum(self._pieces[p] for p in parts[::2] if p) for parts in split]

    def _tokenize(self, texts: Sequence[str]) -> list[int]:
        if not texts:
            return []
        return [len(ids) for ids in self.tokenizer(list(texts), add_special_tokens=False)["input_ids"]]
