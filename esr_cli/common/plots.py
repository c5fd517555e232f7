"""Pictures read from artifacts: learning curves and rollout animations."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

CURVE_PANELS = (
    ("return", "return (steps on goal)"),
    ("success", "success rate"),
    ("mi_estimate", "MI estimate (nats)"),
    ("contrastive_accuracy", "contrastive accuracy"),
)


# A logged value beyond this is drawn as a gap: a plot's axis arithmetic (squares, spans)
# overflows on values near the float limit, and no metric esr logs is anywhere near it.
DRAWABLE = 1e100


def _series(rows: list[dict], name: str) -> tuple[np.ndarray, np.ndarray]:
    epochs = np.array([r["epoch"] for r in rows])
    vals = np.array([[np.nan if v is None else v for v in r[name]] for r in rows], dtype=float)
    with np.errstate(invalid="ignore"):
        vals[~(np.abs(vals) <= DRAWABLE)] = np.nan
    return epochs, vals


def smooth(y: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average along axis 0 (NaN-aware), so early epochs stay visible."""
    if window <= 1:
        return y
    out = np.empty_like(y)
    for i in range(len(y)):
        block = y[max(0, i - window + 1) : i + 1]
        with np.errstate(all="ignore"):
            out[i] = np.nanmean(block, axis=0) if np.isfinite(block).any() else np.nan
    return out


def learning_curve(rows: list[dict], out_png: Path, title: str, provenance: dict, warmup_epochs: int = 0) -> Path:
    """Return, success, MI estimate and contrastive accuracy vs epoch; mean +- 1 SE over seeds.
    Warm-up epochs (the robot acting uniformly, learner.warmup_epochs) are shaded."""
    panels = [(k, label) for k, label in CURVE_PANELS if rows and k in rows[0]]
    fig, axes = plt.subplots(1, len(panels), figsize=(4 * len(panels), 3.2), squeeze=False)
    window = max(1, len(rows) // 50)
    for ax, (name, label) in zip(axes[0], panels):
        epochs, vals = _series(rows, name)
        vals = smooth(vals, window)
        if not np.isfinite(vals).any():
            ax.text(0.5, 0.5, "not logged for this method", ha="center", va="center", transform=ax.transAxes)
        else:
            n = np.isfinite(vals).sum(axis=1)
            with np.errstate(all="ignore"), warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)  # an epoch with no finite seed: a gap, said by NaN
                mean = np.nanmean(vals, axis=1)
                se = np.where(n > 1, np.nanstd(vals, axis=1, ddof=min(1, vals.shape[1] - 1)) / np.sqrt(np.maximum(n, 1)), 0.0)
            ax.plot(epochs, mean, color="C0")
            ax.fill_between(epochs, mean - se, mean + se, color="C0", alpha=0.25, linewidth=0)
            if name == "contrastive_accuracy" and "contrastive_chance" in rows[0]:
                _, chance = _series(rows, "contrastive_chance")
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore", RuntimeWarning)
                    ax.plot(epochs, np.nanmean(smooth(chance, window), axis=1), "k--", lw=1, label="chance")
                ax.legend(fontsize=8, loc="lower right")
        if warmup_epochs:
            ax.axvspan(0.5, warmup_epochs + 0.5, color="0.5", alpha=0.15, lw=0, label="uniform robot (warm-up)")
            if ax is axes[0][0]:
                ax.legend(fontsize=8, loc="lower right")
        ax.set_xlabel("epoch")
        ax.set_title(label, fontsize=10)
        ax.grid(alpha=0.3)
    seeds = len(rows[0]["return"]) if rows else 0
    fig.suptitle(f"{title}  ({'1 seed' if seeds == 1 else f'{seeds} seeds, mean ± 1 SE'})", fontsize=11)
    fig.tight_layout()
    return save_figure(fig, out_png, provenance)


# Where each format keeps a figure's provenance: a PNG's and an SVG's description, a PDF's
# subject; JPEG keeps none (its sidecar JSON does).
PROVENANCE_FIELD = {".png": "Description", ".svg": "Description", ".pdf": "Subject"}


def _metadata(path: Path, provenance: dict) -> dict:
    """savefig's keyword for the provenance of a figure written to `path` (none for JPEG, whose
    writer refuses any metadata)."""
    field = PROVENANCE_FIELD.get(path.suffix.lower())
    return {"metadata": {field: json.dumps(provenance, sort_keys=True)}} if field else {}


def save_figure(fig, out_png: Path, provenance: dict, pdf: bool = False) -> Path:
    """The figure (PNG, or the format `out_png`'s suffix names; provenance in its metadata where
    the format has a field for it) plus a sidecar JSON with the same provenance; with `pdf`, a
    PDF twin."""
    out_png = Path(out_png)
    out_png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out_png, dpi=110, **_metadata(out_png, provenance))
    if pdf:
        fig.savefig(out_png.with_suffix(".pdf"), **_metadata(out_png.with_suffix(".pdf"), provenance))
    plt.close(fig)
    out_png.with_suffix(".json").write_text(json.dumps(provenance, indent=2, sort_keys=True))
    return out_png


GIF_MIN_SIDE = 360  # px: a frame is scaled up (nearest neighbour, whole multiples) to at least this
GIF_LAST_FRAME_MS = 1500  # the end of the episode stays on screen


def frame_caption(step: int, steps: int, actions: tuple[str, str] | None, reward: float | None, total: float) -> str:
    """The text under frame `step` (0: the start; t: after the t-th step, whose actions and
    reward it names)."""
    if actions is None:
        return f"step 0/{steps}: the start   return 0\n"
    return f"step {step}/{steps}   reward {reward:g}   return {total:g}\nrobot: {actions[0]}   human: {actions[1]}"


def annotated_frames(frames: list[np.ndarray], captions: list[str]) -> list[np.ndarray]:
    """Each frame scaled up to at least GIF_MIN_SIDE px and its caption (two lines) in a strip below."""
    from PIL import Image, ImageDraw, ImageFont

    h, w = frames[0].shape[:2]
    scale = max(1, -(-GIF_MIN_SIDE // min(h, w)))
    try:
        font = ImageFont.load_default(size=14)
    except TypeError:  # a Pillow without FreeType's default font
        font = ImageFont.load_default()
    strip = 44
    out = []
    for frame, caption in zip(frames, captions):
        img = Image.fromarray(np.asarray(frame, np.uint8)).resize((w * scale, h * scale), Image.NEAREST)
        canvas = Image.new("RGB", (w * scale, h * scale + strip), (255, 255, 255))
        canvas.paste(img, (0, 0))
        ImageDraw.Draw(canvas).multiline_text((6, h * scale + 4), caption, fill=(0, 0, 0), font=font, spacing=4)
        out.append(np.asarray(canvas))
    return out


def rollout_gif(frames: list[np.ndarray], out_gif: Path, fps: int = 6, captions: list[str] | None = None) -> Path:
    """One GIF frame per state (steps + 1), each shown 1000 / fps ms (the last longer), with
    its caption under it when given."""
    from PIL import Image

    out_gif = Path(out_gif)
    out_gif.parent.mkdir(parents=True, exist_ok=True)
    if captions is not None:
        frames = annotated_frames(frames, captions)
    images = [Image.fromarray(np.asarray(f, np.uint8)) for f in frames]
    durations = [round(1000 / fps)] * (len(images) - 1) + [GIF_LAST_FRAME_MS]
    # optimize=False and every frame kept: Pillow would otherwise merge identical frames.
    images[0].save(out_gif, save_all=True, append_images=images[1:], duration=durations, loop=0, optimize=False,
                   disposal=1)
    return out_gif


SCATTER_POINTS = 20_000  # the estimator scatter draws this many pairs at random when there are more


def estimator_scatter(exact_mi, estimate, spearman: float, out_png: Path, provenance: dict) -> Path:
    """ESR's reward estimate against the exact conditional MI, one point per (state, robot action)."""
    fig, ax = plt.subplots(figsize=(4.8, 4.2))
    rng = np.random.default_rng(0)
    idx = rng.choice(len(exact_mi), size=min(len(exact_mi), SCATTER_POINTS), replace=False)
    ax.scatter(np.asarray(exact_mi)[idx], np.asarray(estimate)[idx], s=3, alpha=0.3, color="C0", linewidths=0)
    ax.set_xlabel("exact I(aH; s+ | s, aR)  (nats)")
    ax.set_ylabel("ESR reward, averaged over g ~ rho")
    ax.set_title(f"ESR estimator vs exact MI (Spearman {spearman:.3f})", fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save_figure(fig, out_png, provenance)


def _barycentric(p: np.ndarray) -> np.ndarray:
    """Points of the 2-simplex (rows summing to 1) in the plane of an equilateral triangle."""
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.5, np.sqrt(3) / 2]])
    return np.asarray(p) @ corners


def information_geometry(geo, gamma: float, out_png: Path, provenance: dict, pdf: bool = False) -> Path:
    """The simplex of future-state distributions of a 3-state MDP: the polytope of achievable
    distributions, its capacity centre, and the KL distances to the vertices."""
    fig, ax = plt.subplots(figsize=(5.2, 4.8))
    tri = _barycentric(np.eye(3))
    ax.fill(tri[:, 0], tri[:, 1], color="0.95", edgecolor="0.3")
    for i, name in enumerate(("s1", "s2", "s3")):
        ax.annotate(name, tri[i], textcoords="offset points", xytext=(0, -14 if i < 2 else 6), ha="center")
    v = _barycentric(geo.vertices)
    ax.fill(v[:, 0], v[:, 1], color="C0", alpha=0.25, label="state-marginal polytope")
    c = _barycentric(geo.centre[None])[0]
    u = _barycentric(geo.uniform_centre[None])[0]
    top = np.isclose(geo.kl, geo.kl.max(), rtol=1e-6)
    for k in range(len(v)):
        ax.plot([c[0], v[k, 0]], [c[1], v[k, 1]], color="C3" if top[k] else "0.5", lw=1.5 if top[k] else 0.8)
        ax.annotate(f"a{k + 1}: KL {geo.kl[k]:.3f}", v[k], textcoords="offset points", xytext=(5, 5), fontsize=8)
    ax.scatter(v[:, 0], v[:, 1], color="C0", zorder=3, label="rho(s+ | s, a)")
    ax.scatter([c[0]], [c[1]], color="C3", marker="*", s=120, zorder=4, label=f"capacity centre (I = {geo.mutual_information:.3f} nats)")
    ax.scatter([u[0]], [u[1]], color="k", marker="x", zorder=4, label=f"uniform-policy centre (I = {geo.uniform_mi:.3f})")
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_title(f"Empowerment as a distance in the simplex (gamma {gamma})", fontsize=10)
    ax.legend(fontsize=7, loc="upper right", bbox_to_anchor=(1.05, 1.0))
    fig.tight_layout()
    return save_figure(fig, out_png, provenance, pdf)
