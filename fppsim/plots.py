"""The one place that sets matplotlib up (both packages' figures come through here).

Figures are written off-screen (no display on a cluster node or a bare GPU machine): :func:`pyplot`
selects the ``Agg`` backend before ``matplotlib.pyplot`` is first imported; :func:`save_figure` writes
a figure through the atomic write helper. matplotlib is imported only when a figure is made.
"""

from __future__ import annotations

import os
from pathlib import Path
from fppsim.files import atomic_path

__all__ = ["pyplot", "save_figure"]


def pyplot():
    """``matplotlib.pyplot`` on the off-screen ``Agg`` backend."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | os.PathLike, dpi: float = 100, **savefig) -> Path:
    """Write ``fig`` to ``path`` (format from its suffix) atomically; returns the path. ``savefig``:
    more ``Figure.savefig`` options (e.g. ``bbox_inches="tight"``). The figure stays open."""

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, **savefig)
    return path
