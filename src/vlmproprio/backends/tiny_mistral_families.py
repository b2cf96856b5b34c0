"""The tiny random builds of LLaVA-NeXT and Idefics2: two families on a Mistral language model, built as the
others in vlmproprio.backends.tiny_families are (published processor settings and chat template, the shared tiny
BPE with the family's special tokens, hidden 64, 2 layers); each builder says what it keeps of the published
image geometry.
"""

from __future__ import annotations

from pathlib import Path

from vlmproprio.backends.tiny_common import (
    chat_template,
    family_tokenizer,
    save_model,
    save_pieces,
    tiny_text_config,
    tiny_vision_config,
    token_ids,
)

# ------------------------------------------------------------------------------------------------ LLaVA-NeXT

NEXT_PINPOINTS = [[336, 672], [672, 336], [672, 672], [1008, 336], [336, 1008]]  # as published


def save_llava_next(out: Path, seed: int) -> None:
    """LLaVA-NeXT, LLaVA-1.6 (llava-hf/llava-v1.6-mistral-7b-hf's processor: 336 px views, the anyres grid of the
    five published resolutions, the template that puts a turn's images before its text, ``[INST]`` as plain text
    on a Mistral language model). Every image, alone or not, gets a base view plus its anyres tiles: a square
    frame is fitted to 336x672 (two tiles), unpadded back to a square, with a newline token after each row. The
    real CLIP tower has 14 px patches: 576 tokens the base view, 24x24 + 24 the tiles, 1,176 a frame, so Process 3
    at 31 frames (~36k image tokens) does not fit the 32k context. The tiny tower has 42 px patches: 8x8 = 64 the
    base view, 8x8 + 8 the tiles, 136 a frame, the same layout 8.6 times cheaper."""
    from transformers import LlavaNextConfig, LlavaNextForConditionalGeneration, LlavaNextImageProcessorPil

    named = {"image_token": "<image>"}
    tok = family_tokenizer(bos="<s>", eos="</s>", pad="<pad>", named=named)
    [image] = token_ids(tok, "<image>")
    config = LlavaNextConfig(
        text_config=dict(model_type="mistral", **tiny_text_config(tok, eos="</s>", head_dim=16, sliding_window=None)),
        vision_config=tiny_vision_config(
            model_type="clip_vision_model",
            projection_dim=64,
            image_size=336,
            patch_size=42,  # the real 14 px: 1,176 tokens a frame
        ),
        image_token_index=image,
        vision_feature_select_strategy="default",
        vision_feature_layer=-2,
        image_grid_pinpoints=NEXT_PINPOINTS,
        image_seq_length=64,
        tie_word_embeddings=False,
    )
    save_model(out, LlavaNextForConditionalGeneration, config, tok, ("</s>",), seed)
    image_processor = LlavaNextImageProcessorPil(
        size={"shortest_edge": 336},
        crop_size={"height": 336, "width": 336},
        image_grid_pinpoints=NEXT_PINPOINTS,
        image_mean=[0.48145466, 0.4578275, 0.40821073],
        image_std=[0.26862954, 0.26130258, 0.27577711],
        resample=3,  # bicubic, as published
        do_center_crop=True,
        do_pad=True,
    )
    save_pieces(
        out,
        tok,
        image_processor,
        "LlavaNextProcessor",
        chat_template("llava-next"),
        patch_size=42,
        vision_feature_select_strategy="default",
        num_additional_image_tokens=1,
    )


# ------------------------------------------------------------------------------------------------ Idefics2


def save_idefics2(out: Path, seed: int) -> None:
    """Idefics2 (HuggingFaceM4/idefics2-8b's processor: images scaled to 378-980 px, 14 px patches, a perceiver
    resampler to 64 latents, so every image is 64 tokens between ``<fake_token_around_image>`` markers; Mistral
    language model), with image splitting off. Published, splitting is on: four crops plus the whole image, five
    views of 64 tokens, 325 a frame with their markers (Process 3 at 31 frames ~10k image tokens, which fits), but the tiny tower then
    sees 155 views of 27x27 patches in Process 3; without splitting a 256x256 frame is one 378x378 view."""
    from transformers import Idefics2Config, Idefics2ForConditionalGeneration, Idefics2ImageProcessorPil

    specials = ("<fake_token_around_image>", "<image>", "<end_of_utterance>")
    tok = family_tokenizer(bos="<s>", eos="</s>", pad="<unk>", specials=specials)
    [image] = token_ids(tok, "<image>")
    text = tiny_text_config(tok, eos="</s>", head_dim=16, sliding_window=None)
    config = Idefics2Config(
        text_config=dict(model_type="mistral", rms_norm_eps=1e-5, **text),
        vision_config=tiny_vision_config(
            image_size=980,
            patch_size=14,
        ),
        perceiver_config=dict(
            hidden_size=text["hidden_size"],
            rms_norm_eps=1e-5,  # as published
            resampler_n_latents=64,
            resampler_depth=2,
            resampler_n_heads=4,
            resampler_head_dim=16,
            num_key_value_heads=2,
        ),
        image_token_id=image,
        tie_word_embeddings=False,
    )
    save_model(out, Idefics2ForConditionalGeneration, config, tok, ("<end_of_utterance>", "</s>"), seed)
    image_processor = Idefics2ImageProcessorPil(
        do_image_splitting=False,
        size={"shortest_edge": 378, "longest_edge": 980},
        image_mean=[0.5, 0.5, 0.5],
        image_std=[0.5, 0.5, 0.5],
        resample=2,  # bilinear, as published
        do_pad=True,
    )
    save_pieces(out, tok, image_processor, "Idefics2Processor", chat_template("idefics2"), image_seq_len=64)
