"""A smoke recording opened in rerun's real web viewer (headless Chromium, SwiftShader WebGL)
renders its 3D view: hair-coloured pixels appear in the view's region of the screenshot.

Slow (the wasm viewer takes 20 s to minutes to load and stream a recording on a loaded 2-core
machine) and needs Debian's Chromium (``apt-get install -y chromium fonts-liberation``); it is
skipped with the reason when Chromium is missing.  Run it with
``.venv/bin/python -m pytest -m slow tests/test_web_viewer.py``.
"""

from __future__ import annotations

import io

import numpy as np
import pytest

from web_viewer import WebViewer, chromium

pytestmark = pytest.mark.slow

#: the smoke run: goaling's wisp, free, a few frames (a small recording loads quickly)
SMOKE = ["experiment=goaling_smoke", "variants=[]", "frames=4", "scene.n_strands=6", "scene.n_vertices=10",
         "logging.rerun=true", "logging.progress=false"]
#: the hair's colour in the recording (rerun_sink: [200, 150, 90]) under the viewer's shading
HAIR_MIN_PIXELS = 40
#: the 3D view's region of a 1600 x 1000 window (the layout puts the 3D view above the plots)
VIEW_REGION = (slice(80, 560), slice(0, 1600))   # rows, columns


def hair_pixels(png: bytes) -> tuple[int, float]:
    """(pixels of the hair's colour, grey-level standard deviation) in the 3D view's region."""
    from PIL import Image

    img = np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.float64)[VIEW_REGION]
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    hair = (r > 120) & (r - b > 60) & (g > 0.55 * r) & (g < 0.95 * r)
    return int(hair.sum()), float(img.mean(-1).std())


@pytest.mark.skipif(chromium() is None, reason="chromium is not installed (Debian: apt-get install -y chromium "
                                               "fonts-liberation); the web viewer test needs it")
def test_smoke_recording_renders_in_the_web_viewer(hydra_conf, tmp_path):
    pytest.importorskip("PIL", reason="Pillow (a matplotlib dependency, dev extra) reads the screenshot")
    from hairexp.app.run import run

    run(hydra_conf(SMOKE), tmp_path / "run")
    rrd = tmp_path / "run" / "recording.rrd"
    assert rrd.is_file()
    with WebViewer(rrd, tmp_path / "viewer", 1600, 1000) as viewer:
        png, ready = viewer.screenshot_when(lambda p: hair_pixels(p)[0] >= HAIR_MIN_PIXELS, timeout=420)
    (tmp_path / "viewer.png").write_bytes(png)
    n, spread = hair_pixels(png)
    assert ready, (f"no hair drawn in the 3D view after 420 s ({n} hair-coloured pixels, grey std {spread:.1f}); "
                   f"screenshot {tmp_path / 'viewer.png'}, logs in {tmp_path / 'viewer'}")
    assert spread > 5.0   # not a blank view
