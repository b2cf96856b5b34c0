"""The report page in a real browser: headless Chromium renders it from a copied folder, with its images
loaded, its tables present and no caption text executed; a screenshot shows something.

Needs Debian's `chromium` (apt-get install -y chromium); without it the test is skipped, saying so.
"""

from __future__ import annotations

import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest
from PIL import Image

from report_helpers import shared_report

for _module in ("matplotlib", "jinja2"):
    pytest.importorskip(_module, reason="reports need the [report] extra: pip install 'vlmproprio[report]'")

FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--hide-scrollbars",
    "--virtual-time-budget=10000",  # let every load event fire before the DOM is dumped
)


def chromium() -> str:
    for name in ("chromium", "chromium-browser"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip(
        "chromium not found: install Debian's package (`apt-get install -y chromium`) to render the report page"
    )


def run_chromium(browser: str, profile: Path, *args: str) -> str:
    res = subprocess.run(
        [browser, *FLAGS, f"--user-data-dir={profile}", *args], capture_output=True, text=True, timeout=120
    )
    assert res.returncode == 0, res.stderr[-2000:]
    return res.stdout


class DomSummary(HTMLParser):
    """The images (with their attributes), table count, title and text of a dumped DOM."""

    def __init__(self):
        super().__init__()
        self.images: list[dict] = []
        self.tables = 0
        self.rows = 0
        self.title = ""
        self.text: list[str] = []
        self._in_title = False

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        if tag == "img":
            self.images.append(a)
        elif tag == "table":
            self.tables += 1
        elif tag == "tr":
            self.rows += 1
        self._in_title = tag == "title"

    def handle_endtag(self, tag):
        self._in_title = False

    def handle_data(self, data):
        if self._in_title:
            self.title += data
        self.text.append(data)


def dom(browser: str, profile: Path, page: Path) -> DomSummary:
    d = DomSummary()
    d.feed(run_chromium(browser, profile, "--dump-dom", page.as_uri()))
    return d


@pytest.fixture(scope="module")
def copied_report(tmp_path_factory):
    _, index = shared_report(tmp_path_factory)  # test_report.py's run and report, built once per session
    copy = tmp_path_factory.mktemp("browser") / "elsewhere" / "report"
    shutil.copytree(index.parent, copy)  # only the report folder: it must work on its own
    return copy / "index.html"


def test_page_renders_its_images_and_tables_in_chromium(copied_report, tmp_path):
    browser = chromium()
    d = dom(browser, tmp_path / "profile", copied_report)
    assert d.title == "vlmproprio report — run"  # the captions' <script> and onerror never ran
    assert '<script>document.title="pwned"</script>' in "".join(d.text)  # shown as text instead
    plots = [i for i in d.images if i["src"].endswith(".png")]
    thumbs = [i for i in d.images if i["src"].startswith("frames/")]
    assert len(plots) == 6 and all(i.get("data-state") == "ok" for i in plots), (
        plots
    )  # Figs. 5, 6, F1, two traces, power
    eager = [i for i in thumbs if i.get("loading") != "lazy"]
    assert len(eager) == 14 and all(i.get("data-state") == "ok" for i in eager), eager[:3]
    assert d.tables >= 6 and d.rows > 100

    shot = tmp_path / "page.png"
    run_chromium(
        browser, tmp_path / "profile2", "--window-size=1280,2400", f"--screenshot={shot}", copied_report.as_uri()
    )
    with Image.open(shot) as im:
        assert im.size == (1280, 2400)
        colours = im.convert("RGB").resize((64, 120)).getcolors(64 * 120)
        assert colours is not None and len(colours) > 50, "the screenshot is (nearly) blank"


def test_a_missing_image_is_flagged_broken(copied_report, tmp_path):
    browser = chromium()
    broken = tmp_path / "report"
    shutil.copytree(copied_report.parent, broken)
    (broken / "fig6_points__synthetic.png").unlink()
    d = dom(browser, tmp_path / "profile", broken / "index.html")
    states = {i["src"]: i.get("data-state") for i in d.images if i["src"].endswith(".png")}
    assert states["fig6_points__synthetic.png"] == "broken"
    assert states["fig5_success__synthetic.png"] == "ok"


def test_without_chromium_the_test_skips_saying_how_to_install_it(monkeypatch):
    monkeypatch.setattr(shutil, "which", lambda name: None)
    with pytest.raises(pytest.skip.Exception, match=r"apt-get install -y chromium"):
        chromium()
