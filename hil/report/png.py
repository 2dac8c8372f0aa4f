"""A matplotlib figure as an inline PNG image: every page the reports write carries its figures (no other file).
A module of its own, so that a page that draws a figure imports no diagnosis (hil.report.html does)."""

from __future__ import annotations

import base64
import io


def png_img(fig) -> str:
    """A matplotlib figure as an <img> that carries its PNG (the page needs no other file); closes it."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return '<img src="data:image/png;base64,' + base64.b64encode(buf.getvalue()).decode() + '">'
