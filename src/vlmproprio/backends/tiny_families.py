"""The tiny random builds of the families beyond Qwen2-VL, Qwen2.5-VL and LLaVA (see vlmproprio.backends.tiny).

Each build has its family's real architecture class, processor class and processor settings (the
published ``preprocessor_config.json`` / ``processor_config.json`` of the checkpoint named in its
builder), its chat template (``chat_templates/<family>.jinja``, the logic of the published template for the
system, user and assistant turns vlmproprio sends) and its special tokens, on the shared tiny byte-level BPE
(``tiny.train_bpe``): the real tokenizers' vocabularies are not reproduced, their special tokens are. Sizes are
tiny (hidden 64, 2 layers), the text context holds Process 3 of the longest fixture episode at the image cap,
and the image geometry keeps the real number of tokens a 256x256 frame costs wherever the vision tower allows
it cheaply (each builder says where it does not).

What the builds share (tokenizer, text config, file layout) is vlmproprio.backends.tiny_common; LLaVA-NeXT and
Idefics2, both on a Mistral language model, are built in vlmproprio.backends.tiny_mistral_families.
"""

from __future__ import annotations

from collections.abc import Callable
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
from vlmproprio.backends.tiny_mistral_families import save_idefics2, save_llava_next

# ------------------------------------------------------------------------------------------------ Qwen3-VL


def save_qwen3_vl(out: Path, seed: int) -> None:
    """Qwen3-VL (Qwen/Qwen3-VL-2B-Instruct's processor): 16 px patches merged 2x2, so a 256x256 frame is 64
    tokens; interleaved multimodal RoPE; DeepStack features from the vision tower's first layer."""
    from transformers import Qwen2VLImageProcessorPil, Qwen3VLConfig, Qwen3VLForConditionalGeneration

    qwen = ("<|im_start|>", "<|im_end|>", "<|vision_start|>", "<|vision_end|>", "<|image_pad|>", "<|video_pad|>")
    tok = family_tokenizer(bos=None, eos="<|im_end|>", pad="<|endoftext|>", specials=qwen)
    image, video, start, end = token_ids(tok, "<|image_pad|>", "<|video_pad|>", "<|vision_start|>", "<|vision_end|>")
    rope = {"rope_type": "default", "rope_theta": 5_000_000.0, "mrope_section": [2, 3, 3], "mrope_interleaved": True}
    config = Qwen3VLConfig(
        text_config=tiny_text_config(tok, eos="<|im_end|>", head_dim=16, rope_parameters=rope),
        vision_config=dict(
            depth=2,
            hidden_size=32,
            intermediate_size=64,
            num_heads=4,
            out_hidden_size=64,
            patch_size=16,
            spatial_merge_size=2,
            temporal_patch_size=2,
            num_position_embeddings=2304,  # the real 48x48 grid of learned positions, interpolated per image
            deepstack_visual_indexes=[0],
        ),
        image_token_id=image,
        video_token_id=video,
        vision_start_token_id=start,
        vision_end_token_id=end,
        tie_word_embeddings=False,
    )
    save_model(out, Qwen3VLForConditionalGeneration, config, tok, ("<|im_end|>", "<|endoftext|>"), seed)
    image_processor = Qwen2VLImageProcessorPil(
        patch_size=16,
        merge_size=2,
        temporal_patch_size=2,
        image_mean=[0.5, 0.5, 0.5],
        image_std=[0.5, 0.5, 0.5],
        size={"shortest_edge": 65536, "longest_edge": 16777216},
    )
    save_pieces(out, tok, image_processor, "Qwen3VLProcessor", chat_template("qwen3-vl"))


# ------------------------------------------------------------------------------------------------ Gemma 3


def save_gemma3(out: Path, seed: int) -> None:
    """Gemma 3 (google/gemma-3-4b-it's processor): every image becomes 256 soft tokens between
    ``<start_of_image>`` and ``<end_of_image>``. The real SigLIP tower sees 896 px (64x64 patches pooled 4x4 to
    16x16); the tiny one sees 224 px (16x16 patches, pooled 1x1): the same 256 tokens a frame, 16 times cheaper."""
    from transformers import Gemma3Config, Gemma3ForConditionalGeneration, Gemma3ImageProcessorPil

    named = {"image_token": "<image_soft_token>", "boi_token": "<start_of_image>", "eoi_token": "<end_of_image>"}
    tok = family_tokenizer(
        bos="<bos>", eos="<eos>", pad="<pad>", specials=("<start_of_turn>", "<end_of_turn>"), named=named
    )
    image, boi, eoi = token_ids(tok, *named.values())
    text = tiny_text_config(
        tok,
        eos="<eos>",
        head_dim=16,
        query_pre_attn_scalar=16,
        sliding_window=512,
        layer_types=["sliding_attention", "full_attention"],
        rope_parameters={
            "full_attention": {"rope_type": "default", "rope_theta": 1_000_000.0},
            "sliding_attention": {"rope_type": "default", "rope_theta": 10_000.0},
        },
    )
    config = Gemma3Config(
        text_config=text,
        vision_config=tiny_vision_config(
            image_size=224,
            patch_size=14,
        ),
        mm_tokens_per_image=256,
        image_token_index=image,
        boi_token_index=boi,
        eoi_token_index=eoi,
        tie_word_embeddings=True,
    )
    save_model(out, Gemma3ForConditionalGeneration, config, tok, ("<end_of_turn>", "<eos>"), seed)
    image_processor = Gemma3ImageProcessorPil(
        size={"height": 224, "width": 224},
        image_mean=[0.5, 0.5, 0.5],
        image_std=[0.5, 0.5, 0.5],
        resample=2,  # bilinear, as published
        do_pan_and_scan=False,
    )
    save_pieces(out, tok, image_processor, "Gemma3Processor", chat_template("gemma3"), image_seq_length=256)


# ------------------------------------------------------------------------------------------------ Idefics3 (SmolVLM)


_ROWS_COLS = tuple(f"<row_{i + 1}_col_{j + 1}>" for i in range(6) for j in range(6))  # the tiles' tags


def _save_idefics3_geometry(
    out: Path, seed: int, classes: tuple, processor_class: str, family: str, specials: tuple[str, ...]
) -> None:
    """An Idefics3-style build: 512 px views of 64 tokens (16 px patches, pixel shuffle by 4), image splitting
    off, on a Llama text model; ``classes`` are the family's config, model and image processor classes and
    ``specials`` its special tokens in the order that fixes their ids."""
    config_cls, model_cls, image_processor_cls = classes
    tok = family_tokenizer(bos="<|im_start|>", eos="<end_of_utterance>", pad="<|im_end|>", specials=specials)
    [image] = token_ids(tok, "<image>")
    config = config_cls(
        text_config=dict(model_type="llama", **tiny_text_config(tok, eos="<end_of_utterance>")),
        vision_config=tiny_vision_config(image_size=512, patch_size=16),
        scale_factor=4,
        image_token_id=image,
        tie_word_embeddings=False,
    )
    save_model(out, model_cls, config, tok, ("<end_of_utterance>",), seed)
    image_processor = image_processor_cls(
        do_image_splitting=False,
        size={"longest_edge": 2048},
        max_image_size={"longest_edge": 512},
        image_mean=[0.5, 0.5, 0.5],
        image_std=[0.5, 0.5, 0.5],
        resample=1,  # LANCZOS, as published
    )
    save_pieces(out, tok, image_processor, processor_class, chat_template(family), image_seq_len=64)


def save_idefics3(out: Path, seed: int) -> None:
    """Idefics3 as SmolVLM (HuggingFaceTB/SmolVLM-256M-Instruct's processor, 512 px views of 64 tokens: 16 px
    patches, pixel shuffle by 4), with image splitting off. Published, splitting is on: an image is scaled so its
    long side is 2048 px and cut into 4x4 tiles of 512 px plus a global view, so a 256x256 frame costs ~1,100
    tokens, Process 3 at 31 frames ~41k tokens (5 times the real model's 8,192-token context), and the tiny
    build took 6 minutes for one episode. Without splitting a frame is one 512 px view: 64 image tokens
    between ``<fake_token_around_image><global-img>`` and ``<fake_token_around_image>``. With the real
    checkpoints, set ``"do_image_splitting": false`` in the preprocessor config too, or cap Process 3
    (``--max-images-p3 7`` fits 8,192 tokens with splitting on)."""
    from transformers import Idefics3Config, Idefics3ForConditionalGeneration, Idefics3ImageProcessorPil

    classes = (Idefics3Config, Idefics3ForConditionalGeneration, Idefics3ImageProcessorPil)
    specials = ("<fake_token_around_image>", "<image>", "<end_of_utterance>", "<global-img>", *_ROWS_COLS)
    _save_idefics3_geometry(out, seed, classes, "Idefics3Processor", "idefics3", specials)


def save_smolvlm(out: Path, seed: int) -> None:
    """SmolVLM2 (HuggingFaceTB/SmolVLM2-500M-Video-Instruct's processor: SmolVLMProcessor, which needs
    ``num2words``, and its image processor): the Idefics3 geometry and tokens (the special tokens in SmolVLM2's
    order), with SmolVLM2's own classes and its template, which also takes video parts. Published, image
    splitting is on (a 256x256 frame ~1,100 tokens; the model's context is 8,192): off here, as for Idefics3."""
    from transformers import SmolVLMConfig, SmolVLMForConditionalGeneration, SmolVLMImageProcessorPil

    classes = (SmolVLMConfig, SmolVLMForConditionalGeneration, SmolVLMImageProcessorPil)
    specials = ("<global-img>", *_ROWS_COLS, "<fake_token_around_image>", "<image>", "<end_of_utterance>")
    _save_idefics3_geometry(out, seed, classes, "SmolVLMProcessor", "smolvlm", specials)


# ------------------------------------------------------------------------------------------------ InternVL


def save_internvl(out: Path, seed: int) -> None:
    """InternVL (OpenGVLab/InternVL3-1B-hf's processor, as transformers' converter writes it): 448 px tiles,
    up to 12 by aspect ratio plus a thumbnail when there are several; a square 256x256 frame is one tile of 256
    tokens (14 px patches, pixel shuffle 0.5) between ``<img>`` and ``</img>``. Qwen2 language model."""
    from transformers import GotOcr2ImageProcessorPil, InternVLConfig, InternVLForConditionalGeneration

    qwen = ("<|im_start|>", "<|im_end|>")
    named = {
        "start_image_token": "<img>",
        "end_image_token": "</img>",
        "context_image_token": "<IMG_CONTEXT>",
        "video_token": "<video>",
    }
    tok = family_tokenizer(bos=None, eos="<|im_end|>", pad="<|endoftext|>", specials=qwen, named=named)
    [image] = token_ids(tok, "<IMG_CONTEXT>")
    config = InternVLConfig(
        text_config=dict(model_type="qwen2", **tiny_text_config(tok, eos="<|im_end|>")),
        vision_config=tiny_vision_config(
            image_size=[448, 448],
            patch_size=[14, 14],
            use_absolute_position_embeddings=True,
        ),
        image_token_id=image,
        image_seq_length=256,
        downsample_ratio=0.5,
        tie_word_embeddings=False,
    )
    save_model(out, InternVLForConditionalGeneration, config, tok, ("<|im_end|>", "<|endoftext|>"), seed)
    image_processor = GotOcr2ImageProcessorPil(
        size={"height": 448, "width": 448},
        image_mean=[0.485, 0.456, 0.406],
        image_std=[0.229, 0.224, 0.225],
        crop_to_patches=False,  # the processor turns it on for every call (InternVLProcessor.images_kwargs)
        min_patches=1,
        max_patches=12,
    )
    save_pieces(out, tok, image_processor, "InternVLProcessor", chat_template("internvl"), image_seq_length=256)


# ------------------------------------------------------------------------------------------------ LLaVA-OneVision

ONEVISION_PINPOINTS = [[384 * r, 384 * c] for r in range(1, 7) for c in range(1, 7)]  # anyres_max_9, as published


def save_llava_onevision(out: Path, seed: int) -> None:
    """LLaVA-OneVision (llava-hf/llava-onevision-qwen2-0.5b-ov-hf's processor: 384 px views, the anyres grid
    of 1x1 to 6x6 tiles, the template that puts a turn's images before its text). A prompt with several images
    gets one base view per image; a prompt with one image gets the base view plus its anyres tiles. The real
    SigLIP has 14 px patches: 729 tokens a view, so a frame costs 730 tokens in a several-image prompt (Process 3
    at 31 frames is ~23k image tokens of the 32k context) and 1,485 alone. The tiny tower has 48 px patches: 64
    tokens a view (65 a frame in a several-image prompt), the same layout 11 times cheaper."""
    from transformers import (
        LlavaOnevisionConfig,
        LlavaOnevisionForConditionalGeneration,
        LlavaOnevisionImageProcessorPil,
    )

    qwen = ("<|im_start|>", "<|im_end|>")
    named = {"image_token": "<image>", "video_token": "<video>"}
    tok = family_tokenizer(bos=None, eos="<|im_end|>", pad="<|endoftext|>", specials=qwen, named=named)
    image, video = token_ids(tok, "<image>", "<video>")
    config = LlavaOnevisionConfig(
        text_config=dict(model_type="qwen2", **tiny_text_config(tok, eos="<|im_end|>")),
        vision_config=tiny_vision_config(
            model_type="siglip_vision_model",
            image_size=384,
            patch_size=48,
            vision_use_head=False,
        ),
        image_token_index=image,
        video_token_index=video,
        vision_feature_select_strategy="full",
        vision_feature_layer=-1,
        vision_aspect_ratio="anyres_max_9",
        image_grid_pinpoints=ONEVISION_PINPOINTS,
        tie_word_embeddings=False,
    )
    save_model(out, LlavaOnevisionForConditionalGeneration, config, tok, ("<|im_end|>", "<|endoftext|>"), seed)
    image_processor = LlavaOnevisionImageProcessorPil(
        size={"height": 384, "width": 384},
        image_grid_pinpoints=ONEVISION_PINPOINTS,
        image_mean=[0.5, 0.5, 0.5],
        image_std=[0.5, 0.5, 0.5],
        resample=3,  # bicubic, as published
        do_pad=True,
    )
    save_pieces(
        out,
        tok,
        image_processor,
        "LlavaOnevisionProcessor",
        chat_template("llava-onevision"),
        num_image_tokens=64,
        vision_feature_select_strategy="full",
        vision_aspect_ratio="anyres_max_9",
    )


# ------------------------------------------------------------------------------------------------ Mistral 3


def save_mistral3(out: Path, seed: int) -> None:
    """Mistral 3 (mistralai/Mistral-Small-3.1-24B-Instruct-2503's processor: Pixtral tower, 14 px patches merged
    2x2, sizes rounded up to 28 px, up to 1,540 px): a 256x256 frame becomes 280x280, 10x10 = 100 tokens plus
    an ``[IMG_BREAK]`` after each row but the last and an ``[IMG_END]``. Its template writes today's date into the default system prompt, so a prompt
    without a system message changes from one day to the next (the cache key does not: it hashes the messages)."""
    from transformers import Mistral3Config, Mistral3ForConditionalGeneration, PixtralImageProcessorPil

    specials = ("[INST]", "[/INST]", "[SYSTEM_PROMPT]", "[/SYSTEM_PROMPT]", "[IMG]", "[IMG_BREAK]", "[IMG_END]")
    tok = family_tokenizer(bos="<s>", eos="</s>", pad="<pad>", specials=specials)
    [image] = token_ids(tok, "[IMG]")
    config = Mistral3Config(
        text_config=dict(model_type="mistral", **tiny_text_config(tok, eos="</s>", head_dim=16, sliding_window=None)),
        vision_config=tiny_vision_config(
            model_type="pixtral",
            image_size=1540,
            patch_size=14,
        ),
        image_token_index=image,
        spatial_merge_size=2,
        vision_feature_layer=-1,
        multimodal_projector_bias=False,
        tie_word_embeddings=False,
    )
    save_model(out, Mistral3ForConditionalGeneration, config, tok, ("</s>",), seed)
    image_processor = PixtralImageProcessorPil(
        size={"longest_edge": 1540},
        patch_size={"height": 14, "width": 14},
        image_mean=[0.48145466, 0.4578275, 0.40821073],
        image_std=[0.26862954, 0.26130258, 0.27577711],
    )
    save_pieces(
        out, tok, image_processor, "PixtralProcessor", chat_template("mistral3"), patch_size=14, spatial_merge_size=2
    )


# ------------------------------------------------------------------------------------------------ GLM-4V


def save_glm4v(out: Path, seed: int) -> None:
    """GLM-4.1V (zai-org/GLM-4.1V-9B-Thinking's processor: 14 px patches merged 2x2, sizes rounded to 28 px):
    a 256x256 frame becomes 252x252, 81 tokens between ``<|begin_of_image|>`` and ``<|end_of_image|>``;
    multimodal RoPE on half of each head. The real model answers with a ``<think>`` trace before its caption."""
    from transformers import Glm4vConfig, Glm4vForConditionalGeneration, Glm4vImageProcessorPil

    glm = ("[gMASK]", "<sop>", "<|system|>", "<|user|>", "<|assistant|>", "<|observation|>", "<think>", "</think>")
    vision = ("<|begin_of_image|>", "<|end_of_image|>", "<|begin_of_video|>", "<|end_of_video|>")
    named = {"image_token": "<|image|>", "video_token": "<|video|>"}
    ends = ("<|endoftext|>", "<|user|>", "<|observation|>")
    tok = family_tokenizer(bos=None, eos="<|endoftext|>", pad="<|endoftext|>", specials=glm + vision, named=named)
    image, video, start, end, vstart, vend = token_ids(tok, "<|image|>", "<|video|>", *vision)
    rope = {"rope_type": "default", "rope_theta": 10_000.0, "mrope_section": [2, 1, 1], "partial_rotary_factor": 0.5}
    config = Glm4vConfig(
        text_config=tiny_text_config(tok, eos="<|endoftext|>", rope_parameters=rope),
        vision_config=dict(
            depth=2,
            hidden_size=32,
            intermediate_size=64,
            num_heads=4,
            out_hidden_size=64,
            image_size=336,
            patch_size=14,
            spatial_merge_size=2,
            temporal_patch_size=2,
        ),
        image_token_id=image,
        video_token_id=video,
        image_start_token_id=start,
        image_end_token_id=end,
        video_start_token_id=vstart,
        video_end_token_id=vend,
        tie_word_embeddings=False,
    )
    save_model(out, Glm4vForConditionalGeneration, config, tok, ends, seed)
    image_processor = Glm4vImageProcessorPil(
        size={"shortest_edge": 12544, "longest_edge": 9633792},
        patch_size=14,
        temporal_patch_size=2,
        merge_size=2,
        image_mean=[0.48145466, 0.4578275, 0.40821073],
        image_std=[0.26862954, 0.26130258, 0.27577711],
    )
    save_pieces(out, tok, image_processor, "Glm4vProcessor", chat_template("glm4v"))


# ------------------------------------------------------------------------------------------------ Mllama


def save_mllama(out: Path, seed: int) -> None:
    """Mllama, Llama 3.2 Vision (meta-llama/Llama-3.2-11B-Vision-Instruct's processor: 560 px tiles, up to 4 by
    aspect ratio). Images enter through cross-attention layers, not the prompt: a frame is one ``<|image|>``
    token in the text however large it is, and its tiles (one for a 256x256 frame, padded to 4) are attended
    from the text tokens after it. The published model card supports one image per prompt; transformers runs
    several, each text token attending to the images before it. The template is the logic of the published one
    without its tool-calling and date lines (transformers' tests use the same). The tiny tower has 56 px patches
    (101 positions a tile, where the real one has 1,601): the prompt is the same, the cross-attention 16 times
    smaller."""
    from transformers import MllamaConfig, MllamaForConditionalGeneration, MllamaImageProcessorPil

    specials = ("<|start_header_id|>", "<|end_header_id|>", "<|eot_id|>", "<|end_of_text|>", "<|python_tag|>")
    named = {"image_token": "<|image|>"}
    bos, pad = "<|begin_of_text|>", "<|finetune_right_pad_id|>"
    tok = family_tokenizer(bos=bos, eos="<|eot_id|>", pad=pad, specials=specials, named=named)
    [image] = token_ids(tok, "<|image|>")
    config = MllamaConfig(
        text_config=dict(**tiny_text_config(tok, eos="<|eot_id|>"), cross_attention_layers=[1]),
        vision_config=dict(
            hidden_size=32,
            intermediate_size=64,
            num_hidden_layers=2,
            num_global_layers=1,
            attention_heads=4,
            image_size=560,
            patch_size=56,  # the real 14 px: 1,601 positions a tile, and one episode took 6.5 minutes here
            max_num_tiles=4,
            intermediate_layers_indices=[0],
            vision_output_dim=64,  # hidden size x (intermediate layers + 1)
            supported_aspect_ratios=[[1, 1], [1, 2], [1, 3], [1, 4], [2, 1], [2, 2], [3, 1], [4, 1]],
        ),
        image_token_index=image,
    )
    save_model(out, MllamaForConditionalGeneration, config, tok, ("<|eot_id|>", "<|end_of_text|>"), seed)
    image_processor = MllamaImageProcessorPil(
        size={"height": 560, "width": 560},
        max_image_tiles=4,
        image_mean=[0.48145466, 0.4578275, 0.40821073],
        image_std=[0.26862954, 0.26130258, 0.27577711],
    )
    save_pieces(out, tok, image_processor, "MllamaProcessor", chat_template("mllama"))


BUILDERS: dict[str, Callable[[Path, int], None]] = {
    "qwen3-vl": save_qwen3_vl,
    "gemma3": save_gemma3,
    "idefics3": save_idefics3,
    "smolvlm": save_smolvlm,
    "internvl": save_internvl,
    "llava-onevision": save_llava_onevision,
    "mistral3": save_mistral3,
    "glm4v": save_glm4v,
    "mllama": save_mllama,
    "llava-next": save_llava_next,
    "idefics2": save_idefics2,
}
