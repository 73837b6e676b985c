"""The pictures' titles: a long one (a mixture's name) is broken in two and stays inside."""

from __future__ import annotations

import pytest

from twoscale.plots import SPHERES, _save, _subplots, _wrap_title

LONG = "mix-gold-metallic-paint2-specular-white-phenolic: two-scale (plastic), log RMSE 0.152"


def test_wrap_title_breaks_long_titles_only():
    assert _wrap_title("pvc: two-scale (plastic), log RMSE 0.0123", 7.0).count("\n") == 0
    wrapped = _wrap_title(LONG, 7.0)
    assert wrapped == LONG.replace(": ", ":\n", 1)
    # No ": " early enough: the last space that fits.
    words = "a " * 60
    assert _wrap_title(words.strip(), 7.0).count("\n") == 1
    assert _wrap_title(LONG, 20.0) == LONG  # a wide figure keeps it on one line


@pytest.mark.parametrize("title", [LONG, "short title"])
def test_saved_title_lies_inside_the_figure(tmp_path, title):
    fig, axes = _subplots(1, 2, figsize=(7, 3.8))
    for ax in axes:
        ax.set_title("measured (MERL lookup)")
        ax.axis("off")
    path = _save(fig, tmp_path / "t.png", title, SPHERES)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    renderer = fig._get_renderer()  # the Agg renderer savefig drew with
    box = fig._suptitle.get_window_extent(renderer)
    width, height = fig.get_size_inches() * fig.dpi
    assert 0.0 <= box.x0 and box.x1 <= width, (box, width)
    # Above the panels' own titles, below the top edge.
    panel_top = max(ax.title.get_window_extent(renderer).y1 for ax in axes)
    assert panel_top <= box.y0 and box.y1 <= height, (box, panel_top, height)
