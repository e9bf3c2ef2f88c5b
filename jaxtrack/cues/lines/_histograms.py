"""Global RGB colour histograms of the object and of its surroundings (M3T's `ColorHistograms`).

The RGB cube is cut into B bins per channel (B³ cells; M3T: 16 by default, 32 in its RBOT setting) and
each histogram is a normalised probability over the cells. They are learned from the pixels of the
correspondence lines, inside the projected contour for the foreground and outside for the background
(`jaxtrack.cues.lines.learn_line_histograms`), and blended into the running histograms frame by frame
with a learning rate (M3T: 1 on the first frame, then 0.2; an empty new histogram keeps the old one).
A pixel's foreground posterior is p_f = h_f(c) / (h_f(c) + h_b(c)); an additive `prior` on both keeps
it finite and differentiable where both histograms are empty (p_f = ½ there).

Images are float (H, W, 3) in [0, 255]; a channel value c falls into bin floor(c · B / 256), clipped.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp


class ColourHistograms(eqx.Module):
    """Normalised foreground and background colour histograms over B³ RGB cells.

    Attributes:
        fg: (B³,) foreground probabilities (sum 1), cell index (r · B + g) · B + b.
        bg: (B³,) background probabilities (sum 1).
        fg_count, bg_count: () number of pixels each was learned from (0: empty, uniform).
    """

    fg: jax.Array
    bg: jax.Array
    fg_count: jax.Array
    bg_count: jax.Array

    @property
    def bins(self) -> int:
        """B, the bins per channel (static: from the shape)."""
        return round(self.fg.shape[-1] ** (1.0 / 3.0))


def colour_index(colours, bins: int):
    """Histogram cell (...,) int32 of colours (..., 3) in [0, 255]; B = `bins` per channel (static).

    Integer colours (8-bit frames) take the bin in integer arithmetic, floor(c · B / 256) = (c · B) >> 8, without a
    cast to float: the same cell as the float path (B / 256 is exact in binary floating point), in fewer operations
    per pixel where the lines read every pixel of every round."""
    colours = jnp.asarray(colours)
    if jnp.issubdtype(colours.dtype, jnp.integer):
        b = jnp.clip((colours.astype(jnp.int32) * bins) >> 8, 0, bins - 1)
    else:
        b = jnp.clip(jnp.floor(colours * (bins / 256.0)), 0, bins - 1).astype(jnp.int32)
    return (b[..., 0] * bins + b[..., 1]) * bins + b[..., 2]


def image_colours(image, pixels):
    """Colours (..., 3) of an (H, W, 3) image at the nearest pixel centres of (..., 2) (x, y) positions
    (clamped to the image; mask them yourself)."""
    h, w = image.shape[:2]
    x = jnp.clip(jnp.floor(pixels[..., 0] + 0.5), 0, w - 1).astype(jnp.int32)
    y = jnp.clip(jnp.floor(pixels[..., 1] + 0.5), 0, h - 1).astype(jnp.int32)
    return image[y, x].astype(pixels.dtype)


def _normalised(counts):
    total = jnp.sum(counts)
    uniform = jnp.full_like(counts, 1.0 / counts.shape[0])
    return jnp.where(total > 0, counts / jnp.where(total > 0, total, 1.0), uniform), total


def histogram_from_colours(colours, weight, bins: int):
    """Normalised histogram (B³,) and total weight of colours (M, 3) with weights (M,) (uniform if empty)."""
    cells = colour_index(colours, bins)
    counts = jnp.zeros((bins**3,), weight.dtype).at[cells].add(weight)
    return _normalised(counts)


def learn_histograms(image, pixels_fg, mask_fg, pixels_bg, mask_bg, bins: int = 32) -> ColourHistograms:
    """Histograms of the image's colours at foreground and background pixels. Jittable.

    Args:
        image: (H, W, 3) float colours in [0, 255].
        pixels_fg: (M, 2) (x, y) foreground positions (nearest pixel); mask_fg: (M,) bool or weights.
        pixels_bg: (K, 2) background positions; mask_bg: (K,).
        bins: B, bins per channel (static; 32 → 32768 cells).

    Returns:
        ColourHistograms; an empty side is uniform with count 0.
    """
    dtype = image.dtype if jnp.issubdtype(image.dtype, jnp.floating) else jnp.float32
    image = image.astype(dtype)
    fg, nf = histogram_from_colours(image_colours(image, pixels_fg), jnp.asarray(mask_fg).astype(dtype), bins)
    bg, nb = histogram_from_colours(image_colours(image, pixels_bg), jnp.asarray(mask_bg).astype(dtype), bins)
    return ColourHistograms(fg=fg, bg=bg, fg_count=nf, bg_count=nb)


def uniform_histograms(bins: int = 32, dtype=jnp.float32) -> ColourHistograms:
    """Uniform, empty histograms (every posterior ½)."""
    u = jnp.full((bins**3,), 1.0 / bins**3, dtype)
    return ColourHistograms(fg=u, bg=u, fg_count=jnp.zeros((), dtype), bg_count=jnp.zeros((), dtype))


def update_histograms(hist: ColourHistograms, new: ColourHistograms, rate) -> ColourHistograms:
    """Blend: (1 − rate) · hist + rate · new per side (M3T; rate 1 on the first frame, then 0.2).

    A side of `new` learned from no pixel leaves that side of `hist` as it was (M3T), unless rate ≥ 1.
    `rate` is a scalar array (differentiable, vmappable).
    """
    rate = jnp.asarray(rate, hist.fg.dtype)

    def blend(old, fresh, count):
        r = jnp.where((count > 0) | (rate >= 1), rate, 0.0)
        return (1 - r) * old + r * fresh

    return ColourHistograms(
        fg=blend(hist.fg, new.fg, new.fg_count),
        bg=blend(hist.bg, new.bg, new.bg_count),
        fg_count=new.fg_count,
        bg_count=new.bg_count,
    )


def pixel_posteriors(hist: ColourHistograms, colours, prior=1e-7):
    """Foreground posterior p_f (...,) of float colours (..., 3): (h_f + ε) / (h_f + h_b + 2ε).

    `prior` ε (scalar array) keeps p_f in (0, 1) (½ where both histograms are empty); 1e-7 is about
    1/300 of one count among the 32768 cells of a histogram of a few thousand pixels.
    """
    cells = colour_index(colours, hist.bins)
    return posterior_of_cells(hist, cells, prior)


def posterior_of_cells(hist: ColourHistograms, cells, prior=1e-7):
    """p_f at histogram cells (...,) int32 (see `pixel_posteriors`)."""
    eps = jnp.asarray(prior, hist.fg.dtype)
    hf = hist.fg[cells] + eps
    hb = hist.bg[cells] + eps
    return hf / (hf + hb)


class LogOddsTable(eqx.Module):
    """log(h_f + ε) − log(h_b + ε) of every cell, computed once where the histograms stay fixed (a frame's
    refinement rounds), so that reading a line's pixels is one gather instead of two gathers and two logs
    per pixel (M3T likewise keeps a posterior table per cell).

    Attributes:
        values: (B³,) log odds per cell; prior: the ε it was computed with (a scalar array).
    """

    values: jax.Array
    prior: jax.Array

    @property
    def bins(self) -> int:
        """B, the bins per channel (static: from the shape)."""
        return round(self.values.shape[-1] ** (1.0 / 3.0))


def log_odds_table(hist: ColourHistograms, prior=1e-7) -> LogOddsTable:
    """The `LogOddsTable` of `hist` with the additive prior ε (scalar array)."""
    eps = jnp.asarray(prior, hist.fg.dtype)
    return LogOddsTable(jnp.log(hist.fg + eps) - jnp.log(hist.bg + eps), eps)


def log_odds_of_cells(hist: ColourHistograms | LogOddsTable, cells, prior=1e-7):
    """log(p_f / p_b) at histogram cells (...,) int32: log(h_f + ε) − log(h_b + ε), finite for ε > 0.

    A `LogOddsTable` is read as it is (its own ε; `prior` is not used).
    """
    if isinstance(hist, LogOddsTable):
        return hist.values[cells]
    eps = jnp.asarray(prior, hist.fg.dtype)
    return jnp.log(hist.fg[cells] + eps) - jnp.log(hist.bg[cells] + eps)


def log_odds_image(hist: ColourHistograms | LogOddsTable, image, prior=1e-7):
    """(H, W) log(h_f + ε) − log(h_b + ε) of every pixel of an (H, W, 3) image (0-255, any dtype), in the
    histograms' dtype: the per-pixel values `segment_log_odds` sums, computed once per image where many poses read
    the same frame (the recovery's hypotheses), so that a line's pixel is one scalar gather. `hist` may be a
    `LogOddsTable` (then `prior` is the table's own)."""
    table = hist if isinstance(hist, LogOddsTable) else log_odds_table(hist, prior)
    return table.values[colour_index(jnp.asarray(image), table.bins)]


def posterior_image(hist: ColourHistograms, image, prior=1e-7):
    """(H, W) foreground posterior of every pixel of an (H, W, 3) image (for display and checks)."""
    return pixel_posteriors(hist, image, prior)
