"""Whether an image file can be used, checked without decoding it in full: shared by the dataparser (frames it
drops) and the preference commands (labelled images checked before training). PIL only, so commands that call it
need not load torch."""

from __future__ import annotations

from pathlib import Path
from typing import Optional


def image_problem(path: Path) -> Optional[str]:
    """Why the image file at `path` cannot be used ("empty file", "truncated", PIL's error), or None.

    Cheap but real: JPEGs are decoded at 1/8 scale (`draft`), which still reads the whole entropy-coded stream;
    other formats are checked by PIL's `verify()` (for PNG: every chunk and its CRC, up to IEND)."""
    from PIL import Image

    try:
        if path.stat().st_size == 0:
            return "empty file"
        with Image.open(path) as image:
            if image.format == "JPEG":
                image.draft("RGB", (max(image.width // 8, 1), max(image.height // 8, 1)))
                image.load()
            else:
                image.verify()
    except Exception as err:  # PIL raises OSError, SyntaxError, struct.error, ... for damaged files
        return "truncated" if "truncated" in str(err).lower() else (str(err) or type(err).__name__)
    return None
