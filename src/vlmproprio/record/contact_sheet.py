"""Contact sheets: every sampled frame of an episode on one image, labelled, for checking recordings by eye."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

COLUMNS = 8
THUMB = 128


def contact_sheet(images: Sequence[np.ndarray], labels: Sequence[str], title: str):
    from PIL import Image, ImageDraw

    rows = (len(images) + COLUMNS - 1) // COLUMNS
    label_h, title_h = 14, 18
    sheet = Image.new("RGB", (COLUMNS * THUMB, title_h + rows * (THUMB + label_h)), "white")
    draw = ImageDraw.Draw(sheet)
    draw.text((4, 3), title, fill="black")
    for i, (img, label) in enumerate(zip(images, labels, strict=True)):
        r, c = divmod(i, COLUMNS)
        x, y = c * THUMB, title_h + r * (THUMB + label_h)
        sheet.paste(Image.fromarray(img).resize((THUMB, THUMB), Image.Resampling.BILINEAR), (x, y))
        draw.text((x + 2, y + THUMB), label[:24], fill="black")
    return sheet


def write_contact_sheet(path: Path, images: Sequence[np.ndarray], meta: dict) -> Path:
    labels = [f"{r['index']} s{r['step']} {r['phase']}" for r in meta["frames"]]
    title = f"{meta['episode_id']}  {meta['instruction']}  ({meta['steps']} steps, camera {meta['camera']})"
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    contact_sheet(images, labels, title).save(path)
    return path
