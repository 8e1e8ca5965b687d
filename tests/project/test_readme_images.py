"""Documentation screenshot copies are rewritten only on a visible change (tests/readme_images.py)."""

from __future__ import annotations

import numpy as np
from PIL import Image

from tests.readme_images import VISIBLE_MEAN_LEVELS, save_if_changed


def test_a_copy_is_written_new_kept_on_render_noise_and_replaced_on_a_real_change(tmp_path):
    rng = np.random.default_rng(0)
    base = rng.integers(0, 256, size=(40, 60, 3)).astype(np.uint8)
    out = tmp_path / "readme" / "shot.png"
    assert save_if_changed(Image.fromarray(base), out)  # absent: written
    first = out.read_bytes()
    # render noise: a few pixels off by a few levels (mean difference well below the bar)
    noisy = base.copy()
    noisy[::7, ::9] = np.clip(noisy[::7, ::9].astype(int) + 3, 0, 255).astype(np.uint8)
    assert np.mean(np.abs(noisy.astype(float) - base)) < VISIBLE_MEAN_LEVELS
    assert not save_if_changed(Image.fromarray(noisy), out)
    assert out.read_bytes() == first
    # a real change (a panel repainted) and a new size are written
    changed = base.copy()
    changed[:, :30] = 255
    assert save_if_changed(Image.fromarray(changed), out)
    assert np.array_equal(np.asarray(Image.open(out).convert("RGB")), changed)
    assert save_if_changed(Image.fromarray(changed[:20]), out)
    assert Image.open(out).size == (60, 20)
