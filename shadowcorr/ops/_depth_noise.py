"""The depth noise of one depth image, estimated from the image itself."""

from __future__ import annotations

import numpy as np

#: Rows of a whole depth image a stage reads for the view's noise figure: every this many (and
#: of those every other one, see relative_depth_noise): within a percent or two of the full
#: image's figure, at a sixteenth of the cost.
NOISE_ROW_STEP = 16


def relative_depth_noise(depth: np.ndarray) -> float:
    """The depth noise of an image as ``a`` in ``sigma(z) = a z^2`` (the growth of stereo and ToF
    noise with depth), so ``a z`` is the relative noise at depth ``z``.

    Along each row a smooth surface's second difference is nearly zero, while independent
    noise gives it a standard deviation of ``sqrt(6) sigma``.  The median absolute value of
    ``d2 / z^2`` (robust to the depth edges in between) gives ``a``; every other row is plenty
    for one number.  Invalid pixels (0, negative, not finite) drop out; 0 when fewer than 100
    valid triples remain.
    """
    rows = np.asarray(depth[::2], dtype=np.float64)  # every other row before the conversion, not after
    positive = rows > 0
    d2 = rows[:, :-2] - 2.0 * rows[:, 1:-1] + rows[:, 2:]
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.abs(d2) / rows[:, 1:-1] ** 2
    ratio = ratio[np.isfinite(ratio) & positive[:, :-2] & positive[:, 1:-1] & positive[:, 2:]]
    return float(1.4826 * np.median(ratio) / np.sqrt(6.0)) if ratio.size >= 100 else 0.0
