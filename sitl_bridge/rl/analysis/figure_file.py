"""Figure files that stay small: PNGs saved as 256-colour palette images.

Report figures are line plots and flat-coloured boxes on white, which a palette holds without a
visible change; stored as true-colour PNGs they were ~3.5x larger, and they are committed with
every experiment's report. Median-cut without dithering keeps flat fills exact (dithering would
speckle them and compress worse).
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

PALETTE_COLOURS = 256


def save_figure(fig: Any, out: str | Path, dpi: float) -> Path:
    """Save the matplotlib figure `fig` to `out` at `dpi`: a `.png` as a palette PNG, any other
    format as matplotlib writes it. Returns the path."""
    from PIL import Image  # with matplotlib (the plots extra), as the figure is

    out = Path(out)
    if out.suffix.lower() != ".png":
        fig.savefig(out, dpi=dpi)
        return out
    rendered = io.BytesIO()
    fig.savefig(rendered, format="png", dpi=dpi)
    rendered.seek(0)
    with Image.open(rendered) as image:
        palette_image(image).save(out, format="PNG", optimize=True)
    return out


def palette_image(image: Any) -> Any:
    """A PIL image as its 256-colour palette version (how `save_figure` stores a PNG)."""
    from PIL import Image

    return image.convert("RGB").quantize(colors=PALETTE_COLOURS, method=Image.Quantize.MEDIANCUT,
                                         dither=Image.Dither.NONE)
