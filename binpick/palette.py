"""The one palette of instance colours: instance (or pose) i has the same colour in every
recording, label picture and overlay."""

from __future__ import annotations

import numpy as np

# Fixed colours so that instance i has the same colour in every image and recording.
_PALETTE_SEED = 12345


def instance_colours(n: int) -> np.ndarray:
    """(n, 3) uint8 distinct, stable colours for instances 0..n-1."""
    rng = np.random.default_rng(_PALETTE_SEED)
    hues = (np.arange(n) * 0.618033988749895) % 1.0
    sat = 0.65 + 0.35 * rng.random(n)
    h6 = hues * 6.0
    c = sat
    x = c * (1 - np.abs(h6 % 2 - 1))
    zero = np.zeros(n)
    sector = h6.astype(int) % 6
    table = [(c, x, zero), (x, c, zero), (zero, c, x), (zero, x, c), (x, zero, c), (c, zero, x)]
    rgb = np.stack([np.choose(sector, [t[j] for t in table]) for j in range(3)], axis=1)
    return (255 * (1 - sat[:, None] + rgb) * 0.9).clip(0, 255).astype(np.uint8)


# Points of no instance (noise, ignored, not a part): one grey everywhere.
UNLABELLED_GREY = np.array([110, 110, 110], np.uint8)


def instance_rgb(labels: np.ndarray) -> np.ndarray:
    """(n, 3) uint8 colour of each point by its instance label (n,), UNLABELLED_GREY below 0."""
    labels = np.asarray(labels)
    palette = instance_colours(max(int(labels.max()) + 1 if len(labels) else 1, 1))
    return np.where((labels >= 0)[:, None], palette[np.maximum(labels, 0) % len(palette)], UNLABELLED_GREY)
