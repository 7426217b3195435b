"""The batch's pages in headless Chromium (tests/browser.py): a drive's report.html and the batch's index.html
load without a console error, every video plays, every picture and link resolves, and the 3D view draws
the puppet and plays its drive. Nothing is fetched from a network: the pages are files on disk."""

from pathlib import Path
from urllib.parse import unquote, urlparse

import numpy as np
import pytest

from browser import Browser, chromium
from persona.stores import media

pytestmark = pytest.mark.skipif(chromium() is None, reason="no Chromium here (bash setup.sh test installs it)")

#: every picture, every link's target and every video of the page, as the browser sees them
_INVENTORY = """(() => ({
  images: [...document.images].map(i => ({src: i.src.slice(0, 60), ok: i.complete && i.naturalWidth > 0})),
  links: [...document.querySelectorAll('a[href]')].map(a => a.href),
  media: [...document.querySelectorAll('video, audio, source, iframe, link[href], script[src]')]
    .map(e => e.src || e.href).filter(u => u && !u.startsWith('data:')),
}))()"""

#: each video muted, played for 1.5 s: the furthest time it reached, and its error if any
_PLAY = """Promise.all([...document.querySelectorAll('video')].map(v => {
  let furthest = 0;
  v.addEventListener('timeupdate', () => { furthest = Math.max(furthest, v.currentTime); });
  v.muted = true;
  return v.play().then(() => new Promise(r => setTimeout(r, 1500)))
    .then(() => ({furthest: Math.max(furthest, v.currentTime), error: v.error && v.error.message, width: v.videoWidth}))
    .catch(e => ({furthest: 0, error: String(e)}));
}))"""


def _check_resources(browser: Browser, page: Path) -> dict:
    """Every picture decoded, every link a file that exists (or a place in the page), nothing off the machine."""
    found = browser.js(_INVENTORY)
    assert all(i["ok"] for i in found["images"]), [i for i in found["images"] if not i["ok"]]
    for url in found["links"] + found["media"]:
        parsed = urlparse(url)
        assert parsed.scheme == "file", f"{page.name} links off the machine: {url}"
        if parsed.path != page.as_posix() or not parsed.fragment:
            assert Path(unquote(parsed.path)).exists(), f"{page.name}: {url} does not resolve"
    return found


def _inked(png: bytes, background=(238, 238, 238)) -> float:
    """The share of a screenshot's pixels that differ from the background."""
    path = Path("/dev/shm" if Path("/dev/shm").is_dir() else "/tmp") / "persona-browser-shot.png"
    path.write_bytes(png)
    try:
        image = media.decode_image(path)
    finally:
        path.unlink()
    return float(np.mean(np.abs(image.astype(int) - background).sum(axis=2) > 30)), image


def test_a_drive_report_plays_its_videos_and_draws_the_puppet_in_3d(batch, tmp_path):
    folder, _, _, _ = batch
    page = (folder / "reference" / "bea_al_al" / "report.html").resolve()
    with Browser(width=1200, height=1000) as browser:
        browser.open(page.as_uri())
        _check_resources(browser, page)
        videos = browser.js(_PLAY)
        assert len(videos) == 3 and all(v["error"] is None and v["width"] > 0 and v["furthest"] > 0 for v in videos), videos
        browser.js("document.querySelector('.persona-3d').scrollIntoView()")
        frames = set()
        for i in range(10):  # the drive plays: the frame shown changes while the page draws on
            browser.pump(0.03 * (i + 1))  # uneven steps: a fixed one can alias with the loop (frames 2, 6, 2, 6)
            frames.add(browser.js("document.querySelector('.persona-3d canvas').dataset.frame"))
        draws = int(browser.js("document.querySelector('.persona-3d canvas').dataset.draws"))
        box = browser.js("(() => { const r = document.querySelector('.persona-3d canvas').getBoundingClientRect();"
                         " return {x: r.x + scrollX, y: r.y + scrollY, width: r.width, height: r.height}; })()")
        shot = browser.screenshot(box)
        assert browser.errors() == []
    (tmp_path / "view.png").write_bytes(shot)
    inked, image = _inked(shot)
    assert box["width"] == 480 and draws > 5 and len(frames) > 2, (draws, frames)
    assert 0.05 < inked < 0.9, inked  # the face drawn on the view's grey, not a blank canvas
    face = image[np.abs(image.astype(int) - 238).sum(axis=2) > 30]
    assert face.std() > 5  # a textured face, not a flat shape


def test_the_batch_index_page_shows_every_drive(batch):
    folder, _, _, _ = batch
    page = (folder / "reference" / "index.html").resolve()
    with Browser(width=1200, height=1000) as browser:
        browser.open(page.as_uri())
        found = _check_resources(browser, page)
        shot = browser.screenshot()
        assert browser.errors() == []
    reports = [u for u in found["links"] if u.endswith("/report.html")]
    assert len(reports) == 2 and len(found["images"]) >= 2  # a poster per drive, the people's pictures
    assert _inked(shot, (255, 255, 255))[0] > 0.05
