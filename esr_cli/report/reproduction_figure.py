"""The reproduction report's figure: the curves of every run behind it, a row per figure of the
paper and a panel per environment, each method in one colour and line style everywhere, the
legend of a row beside it, and across seeds the interquartile mean with its bootstrap band."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from esr_cli.common import specs
from esr_cli.common.plots import smooth
from esr_cli.report import figures as figs
from esr_cli.storage.finals import series

POINTS = 300  # points drawn per curve: smoothed over len/50 epochs, then thinned
BAND_RESAMPLES = 500
BAND_CONFIDENCE = 0.95
# ESR's own variants are lines of their own in the ablation rows: a colour each.
ESR_VARIANT_COLORS = {"without aR": "C5", "critic gamma 0": "C6", "human future": "C8"}


def line_style(spec) -> tuple[str, str]:
    """(colour, line style) of a run: the colour names the method (figures.METHOD_COLORS, as in
    fig1-fig5) or ESR's variant, the style solid for the paper's setting and dashed for esr's
    variants of it; a run whose human is not the paper's (esr's MLP clone on Overcooked) is
    dotted in its own colour, so that it is never read as the paper's-human line beside it."""
    colour, style = _method_style(spec)
    return colour, style if specs.plays_with_paper_human(spec) else ":"


def _method_style(spec) -> tuple[str, str]:
    method = spec.method
    if method.kind == "esr":
        if not method.condition_on_robot_action:
            return ESR_VARIANT_COLORS["without aR"], "-"
        if spec.learner.gamma == 0.0:
            return ESR_VARIANT_COLORS["critic gamma 0"], "-"
        if method.future == "human":
            return ESR_VARIANT_COLORS["human future"], "--"
    esrs_variant = getattr(method, "variant", None) in ("fixed", "exact") or (
        method.kind == "esr" and spec.learner.warmup_epochs > 0)
    return figs.METHOD_COLORS.get(method.kind, "C7"), "--" if esrs_variant else "-"


def iqm_band(vals: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(IQM, low, high) over the seeds (columns) of each row: a percentile bootstrap that
    resamples whole seeds, so every point of a band comes from the same resampled seed sets.
    One seed: its values, with no band."""
    from esr_cli.common.stats import iqm

    finite = np.isfinite(vals).any(axis=0)
    vals = vals[:, finite]
    if vals.shape[1] < 2:
        line = vals[:, 0] if vals.shape[1] else np.full(len(vals), np.nan)
        return line, line, line
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, vals.shape[1], size=(BAND_RESAMPLES, vals.shape[1]))
    with np.errstate(all="ignore"):
        boots = iqm(vals[:, picks], axis=-1)  # [rows, resamples]
        tail = (1 - BAND_CONFIDENCE) / 2 * 100
        low, high = np.nanpercentile(boots, [tail, 100 - tail], axis=-1)
        return iqm(vals, axis=-1), low, high


def _curve(ax, rows: list[dict], metric: str, colour: str, style: str, label: str) -> None:
    epochs, vals = series(rows, metric)
    vals = smooth(vals, max(1, len(rows) // 50))
    keep = np.unique(np.linspace(0, len(epochs) - 1, min(POINTS, len(epochs))).astype(int))
    centre, low, high = iqm_band(vals[keep])
    ax.plot(epochs[keep], centre, style, color=colour, label=label, lw=1.4)
    ax.fill_between(epochs[keep], low, high, color=colour, alpha=0.18, linewidth=0)


def draw(rows_of_panels: list[tuple[str, str, list[tuple[str, list[tuple[str, object, list[dict]]]]]]],
         out_png: Path, title: str) -> Path:
    """rows_of_panels: [(row title, metric, [(panel title, [(label, spec, metric rows)])])]."""
    import matplotlib.pyplot as plt

    figs._style()
    ncols = max(len(panels) for _, _, panels in rows_of_panels)
    fig, axes = plt.subplots(len(rows_of_panels), ncols, figsize=(3.0 * ncols + 2.9, 2.5 * len(rows_of_panels) + 0.6),
                             squeeze=False)
    for r, (row_title, metric, panels) in enumerate(rows_of_panels):
        handles = {}
        for c in range(ncols):
            ax = axes[r][c]
            if c >= len(panels):
                ax.set_visible(False)
                continue
            panel, lines = panels[c]
            for label, spec, rows in lines:
                colour, style = line_style(spec)
                _curve(ax, rows, metric, colour, style, label)
            ax.set_title(f"{row_title}: {panel}", fontsize=8)
            ax.grid(alpha=0.3)
            ax.set_xlabel("epoch", fontsize=8)
            if c == 0:
                ax.set_ylabel("MI estimate (nats)" if metric == "mi_estimate" else "return")
            for handle, label in zip(*ax.get_legend_handles_labels()):
                handles.setdefault(label, handle)
        last = axes[r][len(panels) - 1]
        last.legend(handles.values(), handles.keys(), fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0),
                    frameon=False)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110)
    plt.close(fig)
    return out_png
