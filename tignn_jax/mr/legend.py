"""A colour legend for rendered frames: the colour map's bar, its range and the quantity it shows.

Drawn on the host onto finished uint8 frames (with Pillow's built-in bitmap font), outside the real-time loop.
"""
from __future__ import annotations

import numpy as np

from tignn_jax.mr.render import colour_map


def rgb255(colour) -> tuple:
    """An RGB colour in [0, 1] as a tuple of three 0–255 ints (Pillow's and viser's colour format)."""
    return tuple(int(round(255 * float(c))) for c in colour)


def with_legend(rgb, vmin: float, vmax: float, label: str, width: int = 14, height: int | None = None,
                swatches: tuple = ()):
    """The frame with a vertical colour bar in its top-right corner, labelled with ``label`` and the values at
    its ends.

    Args:
      rgb: [H, W, 3] uint8 frame.
      vmin, vmax: the values `colour_map` shows at the bottom (dark purple) and the top (yellow).
      label: the quantity and its units, e.g. "von Mises stress (data units)".
      width: the bar's width in pixels.
      height: the bar's height in pixels (default: 40 % of the frame's).
      swatches: (name, (r, g, b) in [0, 1]) entries drawn as small labelled squares below the bar, for colours
        that are not values of the map (e.g. the clamped nodes', `tignn_jax.mr.scene.CLAMP_COLOUR`).

    Returns:
      [H, W, 3] uint8: a copy of the frame with the legend.

    Raises:
      ValueError: a frame that is not [H, W, 3], or vmax ≤ vmin.
    """
    from PIL import Image, ImageDraw, ImageFont

    rgb = np.asarray(rgb)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"rgb must be [H, W, 3], got shape {rgb.shape}")
    if not vmax > vmin:
        raise ValueError(f"vmax must exceed vmin, got {vmin} and {vmax}")
    h, w, _ = rgb.shape
    height = max(8, int(0.4 * h)) if height is None else int(height)
    top, right = 22, w - 58
    values = np.linspace(vmax, vmin, height)
    bar = (np.asarray(colour_map(values, vmin, vmax)) * 255).astype(np.uint8)
    out = rgb.copy()
    out[top:top + height, right:right + width] = bar[:, None, :]
    image = Image.fromarray(out)
    draw = ImageDraw.Draw(image)
    try:
        font = ImageFont.load_default(size=12)     # Pillow's built-in scalable font
    except TypeError:                              # an older Pillow: its bitmap font
        font = ImageFont.load_default()
    draw.rectangle([right - 1, top - 1, right + width, top + height], outline=(0, 0, 0))
    draw.text((right + width + 3, top - 4), f"{vmax:.3g}", fill=(0, 0, 0), font=font)
    draw.text((right + width + 3, top + height - 10), f"{vmin:.3g}", fill=(0, 0, 0), font=font)
    text_w = draw.textlength(label, font=font)
    draw.text((max(2, w - 4 - text_w), 4), label, fill=(0, 0, 0), font=font)
    for k, (name, colour) in enumerate(swatches):
        y = top + height + 10 + 18 * k
        x = min(right, w - 4 - width - 3 - int(draw.textlength(str(name), font=font)))   # its name inside the frame
        draw.rectangle([x - 1, y - 1, x + width, y + width],
                       fill=rgb255(colour), outline=(0, 0, 0))
        draw.text((x + width + 3, y), str(name), fill=(0, 0, 0), font=font)
    return np.asarray(image)
