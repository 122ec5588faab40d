"""The demo report in a real browser (`make test-all`; `make browser` installs Debian's Chromium): every image
decodes, nothing is left to load, and the page draws something. A report can be valid HTML with a broken
data: URI or an image whose bytes are not a PNG; only a browser says so."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest
from test_demo_report import demo_report  # the same report as the fast test (synthetic stages)

PROBE = ("<script>window.addEventListener('load', () => { const imgs = [...document.images]; "
         "document.body.dataset.images = imgs.length; document.body.dataset.broken = imgs.filter(i => "
         "!i.complete || i.naturalWidth === 0).length; });</script>")


def _chromium() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        pytest.fail("no chromium on PATH: `make browser` installs Debian's package (sudo apt-get install chromium)")
    return found


@pytest.mark.slow
def test_the_demo_report_renders_every_image_in_chromium(tmp_path: Path) -> None:
    _, report = demo_report(tmp_path)
    args = [_chromium(), "--headless", "--no-sandbox", "--disable-gpu", f"--user-data-dir={tmp_path / 'profile'}",
            "--virtual-time-budget=10000"]

    def count(extra: str = "") -> tuple[int, int]:
        """(images, broken images) of the report as Chromium loads it, `extra` HTML added."""
        probe = tmp_path / "probe.html"
        probe.write_text(report.read_text(encoding="utf-8").replace("</body>", extra + PROBE + "</body>"))
        dom = subprocess.run([*args, "--dump-dom", probe.as_uri()], capture_output=True, text=True, timeout=120,
                             check=True).stdout
        images, broken = re.search(r'data-images="(\d+)"', dom), re.search(r'data-broken="(\d+)"', dom)
        assert images and broken, "the load probe did not run"
        return int(images.group(1)), int(broken.group(1))

    images, broken = count()
    assert images >= 4 and broken == 0, (images, broken)
    assert count("<img alt='bad' src='data:image/png;base64,AAAA'>") == (images + 1, 1)  # the probe sees a bad one
    shot = tmp_path / "report.png"
    subprocess.run([*args, "--window-size=1280,4000", f"--screenshot={shot}", report.as_uri()], capture_output=True,
                   timeout=120, check=True)
    import numpy as np
    from PIL import Image

    pixels = np.asarray(Image.open(shot).convert("L"))
    assert pixels.std() > 10.0  # tables, figures and text, not a blank page
