"""Documentation copies of test screenshots, rewritten only when they change visibly.

The screenshot tests refresh small copies in ``docs/images/`` (:data:`DOCS_IMAGES`)
that the documentation site and the README show.  Rendering is not byte-stable
(anti-aliasing, the palette quantiser), so a copy saved on every run changed a few hundred
bytes of committed PNGs each time the suite ran and left every checkout dirty.  A copy is rewritten only when its pixels differ from the
committed one by more than :data:`VISIBLE_MEAN_LEVELS` (mean absolute RGB difference, in
0-255 levels) or its size changed -- a real change of the report still updates it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Where the committed copies live: the documentation's image folder.
DOCS_IMAGES = Path(__file__).resolve().parents[1] / "docs" / "images"

#: Mean absolute RGB difference (0-255 levels) below which a copy is left as it is.
VISIBLE_MEAN_LEVELS = 1.0


def save_if_changed(image, out: Path) -> bool:
    """Save PIL `image` as PNG at `out` unless the file there looks the same; returns
    whether it was written."""
    from PIL import Image

    new = np.asarray(image.convert("RGB"), dtype=float)
    if out.exists():
        with Image.open(out) as old_image:
            old = np.asarray(old_image.convert("RGB"), dtype=float)
        if old.shape == new.shape and float(np.mean(np.abs(old - new))) <= VISIBLE_MEAN_LEVELS:
            return False
    out.parent.mkdir(parents=True, exist_ok=True)
    image.save(out, optimize=True)
    return True
