"""Report figures are saved as palette PNGs: smaller, and flat colours kept exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("matplotlib")
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Rectangle  # noqa: E402
from PIL import Image  # noqa: E402

from sitl_bridge.rl.analysis.figure_file import save_figure  # noqa: E402


def _figure() -> Figure:
    fig = Figure(figsize=(4, 3))
    ax = fig.add_subplot()
    ax.add_patch(Rectangle((0.1, 0.1), 0.3, 0.3, color="#f7f7f7"))  # a light fill a coarse palette drops
    ax.add_patch(Rectangle((0.6, 0.6), 0.3, 0.3, color="#cc4d33"))
    x = np.linspace(0, 1, 200)
    ax.plot(x, 0.5 + 0.4 * np.sin(8 * x), lw=1.5)
    ax.fill_between(x, 0.3, 0.5, alpha=0.2)
    return fig


def test_a_png_is_a_palette_image_smaller_than_true_colour_with_flat_fills_exact(tmp_path: Path) -> None:
    fig = _figure()
    small = save_figure(fig, tmp_path / "small.png", dpi=100)
    fig.savefig(tmp_path / "true_colour.png", dpi=100)
    assert Image.open(small).mode == "P"
    assert small.stat().st_size < (tmp_path / "true_colour.png").stat().st_size
    palette = np.asarray(Image.open(small).convert("RGB"), dtype=int)
    true_colour = np.asarray(Image.open(tmp_path / "true_colour.png").convert("RGB"), dtype=int)
    assert palette.shape == true_colour.shape
    for colour in ((0xF7, 0xF7, 0xF7), (0xCC, 0x4D, 0x33), (255, 255, 255)):
        where = np.all(true_colour == colour, axis=-1)
        assert where.sum() > 100, colour
        assert np.array_equal(palette[where], true_colour[where]), colour


def test_other_formats_are_written_as_matplotlib_writes_them(tmp_path: Path) -> None:
    out = save_figure(_figure(), tmp_path / "figure.svg", dpi=100)
    assert out.read_text().lstrip().startswith("<?xml")
