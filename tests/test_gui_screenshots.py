"""The docs' screenshots come from the current build: the script that makes them runs,
makes every picture docs/gui.md and the README show, and each is a picture of the window."""
import os
import subprocess
import sys
from pathlib import Path

from PIL import Image

from labbench.gui.screenshot import SHOTS

ROOT = Path(__file__).resolve().parents[1]


def test_the_docs_show_exactly_the_pictures_the_script_makes():
    made = set(SHOTS)
    on_disk = {p.name for p in (ROOT / "docs" / "screenshots").glob("*.png")}
    assert on_disk == made  # a picture nobody remakes would go stale silently
    gui_md = (ROOT / "docs" / "gui.md").read_text()
    assert all(f"screenshots/{name}" in gui_md for name in made)
    assert "docs/screenshots/demo-etfe.png" in (ROOT / "README.md").read_text()


def test_the_screenshot_script_makes_each_picture(tmp_path):
    env = {**os.environ, "QT_QPA_PLATFORM": "offscreen"}
    done = subprocess.run([sys.executable, "-m", "labbench.gui.screenshot", str(tmp_path)],
                          capture_output=True, text=True, timeout=1200, env=env,
                          stdin=subprocess.DEVNULL)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split() == [str(tmp_path / name) for name in SHOTS]
    for name in SHOTS:
        with Image.open(tmp_path / name) as image:
            assert image.size == (1600, 1000)
            colours = image.convert("RGB").getcolors(maxcolors=1_000_000)
            assert len(colours) > 100, name  # a window drawn, not a blank
