"""Figures of the validation experiments: one PNG per experiment, no screen needed."""

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402  (backend must be chosen first)


def new_figure(rows: int = 1, cols: int = 1, title: str = ""):
    """A figure with a grid of axes; returns (fig, axes)."""
    fig, axes = plt.subplots(rows, cols, figsize=(6.4 * cols, 3.6 * rows), squeeze=False)
    if title:
        fig.suptitle(title)
    return fig, axes


def save(fig, out_dir: Path | None, name: str) -> Path | None:
    """Write ``fig`` as ``out_dir/name.png`` (nothing when out_dir is None); close it."""
    path = None
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        path = out_dir / f"{name}.png"
        fig.tight_layout()
        fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
