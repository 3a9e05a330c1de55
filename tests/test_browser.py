"""optuna-dashboard in headless Chromium, as a researcher sees it.

The CI study under ``sweeper dashboard``: the sweep's one card opens on the comparison, its
buttons show the other views (the bands draw no stray markers), the note shows the
comparison without its markers, and a trial's episode video plays. A copy of the published
study (``docs/studies/fetch_reach_cpu/``, its figures saved again by this code) under plain
``optuna-dashboard URL``, its hash seed left random: the study page's cards in order,
optuna-dashboard's three first and the comparison next, every method's name whole in a
1024-px window, the controls named, the best non-control trial named beside
optuna-dashboard's "Best Trial" card, and that trial's page playing its video.

Needs Chromium (``.ci/run`` installs Debian's when it is missing); skipped without it.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from cdp import OPENER, Page, browser, chromium, stop
from conftest import running_dashboard

from sweeper.results._dashboard_card import COMPARISON_ID, CONTROLS

pytestmark = pytest.mark.skipif(chromium() is None, reason="no chromium (apt-get install chromium)")

ROOT = Path(__file__).resolve().parent.parent
PUBLISHED = ROOT / "docs" / "studies" / "fetch_reach_cpu"

#: the study page's cards in order: a saved figure by its element id, any other card by
#: its heading
CARDS_JS = """[...document.querySelectorAll('.MuiCard-root')].map(card => {
  const plot = card.querySelector("[id^='user-defined-plot:']");
  if (plot) return plot.id;
  const heading = card.querySelector('h1, h2, h3, h4, h5, h6');
  return heading ? heading.textContent : card.textContent.slice(0, 40);
})"""
#: optuna-dashboard's cards before any saved figure (a single-objective study)
OPTUNAS_FIRST = ["History", "Hyperparameter Importance", "Timeline"]
CARD = f"document.getElementById('user-defined-plot:{COMPARISON_ID}')"

#: the traces the card draws now (its current view): per scatter trace of that view, in
#: order, whether it is a filled band and the markers it draws; and the comparison table's
#: width as its columns' cells are drawn (its text is clipped to them)
VIEW_JS = f"""(() => {{
  const div = {CARD};
  const view = div.layout.meta.views[div._fullLayout.updatemenus[0].active];
  const traces = div.data.filter(t => t.meta === view && (t.type || "scatter") === "scatter");
  return {{
    view: view,
    title: div.layout.title.text,
    text: div.textContent,
    fills: traces.map(t => t.fill || null),
    points: [...div.querySelectorAll("g.trace.scatter")].map(
      g => g.querySelectorAll("path.point").length),
    tableWidth: [...div.querySelectorAll("g.table g.y-column")].reduce(
      (sum, c) => sum + c.querySelector("rect.cell-rect").getBoundingClientRect().width, 0),
  }};
}})()"""

#: per cell of the comparison table's method column (its header among them): its text
#: (a cell's lines joined without a space) and how far that text runs past the cell's right
#: edge, in pixels (> 0: cut off by the column)
NAMES_JS = f"""(() => {{
  const column = {CARD}.querySelectorAll("g.table g.y-column")[1];
  return [...column.querySelectorAll("g.column-cell")].map(cell => {{
    const text = cell.querySelector("text.cell-text");
    const right = cell.querySelector("rect.cell-rect").getBoundingClientRect().right;
    return [text.textContent, text.getBoundingClientRect().right - right];
  }});
}})()"""

PLAY_JS = """(async () => {
  const video = document.querySelector("video");
  video.muted = true;
  await video.play();
  const start = performance.now();
  while (video.currentTime <= 0.2 && performance.now() - start < 10000) {
    await new Promise(resolve => setTimeout(resolve, 100));
  }
  return {time: video.currentTime, width: video.videoWidth, error: video.error && video.error.code,
          src: video.currentSrc};
})()"""


def show(page: Page, label: str) -> dict:
    """Press the card's button ``label`` and return ``VIEW_JS`` once that view is drawn."""
    page.evaluate(
        "[...document.querySelectorAll('g.updatemenu-button')]"
        f".find(b => b.textContent === {json.dumps(label)})"
        ".dispatchEvent(new MouseEvent('click', {bubbles: true}))"
    )
    labels = f"{CARD}.layout.updatemenus[0].buttons.map(b => b.label)"
    page.wait_for(f"{labels}[{CARD}._fullLayout.updatemenus[0].active] === {json.dumps(label)}")
    time.sleep(0.5)  # the restyle's redraw
    return page.evaluate(VIEW_JS)


def stop_live_updates(page: Page) -> None:
    """Switch optuna-dashboard's Live Update off (the left bar): it draws the saved figures
    again every 10 s, as stored, which returns the card to the comparison."""
    page.evaluate('document.querySelector(\'[title="Live Update"] [role="button"]\').click()')
    page.wait_for("document.querySelector('[title=\"Live Update\"] input').checked === false")


def play_a_trial_video(page: Page, study_page: str, number: int) -> None:
    page.goto(f"{study_page}/trials?numbers={number}")
    page.wait_for("document.querySelector('video') !== null")
    played = page.evaluate(PLAY_JS)
    assert played["error"] is None and played["width"] > 0, played
    assert played["time"] > 0.2, played


def test_the_dashboard_shows_the_comparison_and_plays_a_trial_video(ci_study, ci_aggregate):
    with running_dashboard(ci_study) as study_page, browser() as page:
        page.goto(study_page)
        page.wait_for(f"{CARD} !== null && {CARD}.querySelector('g.table') !== null")
        cards = page.wait_for(f"(cards => cards.includes('Timeline') && cards)({CARDS_JS})")
        assert [c for c in cards if c.startswith("user-defined-plot:")] == [
            f"user-defined-plot:{COMPARISON_ID}"
        ]  # the sweep's one card
        opened = page.evaluate(VIEW_JS)
        assert opened["view"] == "comparison" and opened["tableWidth"] > 300, opened
        assert "IQM AUC" in opened["text"] and "pixel" in opened["text"], opened
        assert "linear" in opened["text"], opened

        # each view behind the buttons, the methods named in it
        stop_live_updates(page)
        problems = []  # what a reader would see wrong, all of it reported at the end
        labels = ["Success rate", "Final distance", "AUC", "Profiles", "Every trial"]
        for label in labels:
            view = show(page, label)
            assert "pixel" in view["text"] and "linear" in view["text"], label
            assert view["tableWidth"] < 2, f"{label}: the comparison table still shows"
            if label in ("Success rate", "Final distance"):
                # a band draws no markers; the lines over it draw one per evaluation step
                assert len(view["points"]) == len(view["fills"]), (label, view)
                pairs = list(zip(view["points"], view["fills"], strict=True))
                bands = [p for p, fill in pairs if fill]
                lines = [p for p, fill in pairs if not fill and p]
                assert len(bands) == 2, label  # one per method
                if bands != [0, 0]:
                    problems.append(f"{label}: stray markers on the bands: {bands}")
                if lines != [4, 4]:  # steps 0, 100, 200, 300 of each method
                    problems.append(f"{label}: markers on the lines: {lines}")
        back = show(page, "Comparison")
        assert back["tableWidth"] > 300 and back["points"] == [], back

        # the note: the comparison, its markers invisible, the improvement table readable
        page.goto(study_page + "/note")
        text = page.wait_for(
            "document.body.innerText.includes('Method comparison') && document.body.innerText"
        )
        for marker in ("<!--", "sweeper aggregate: begin", "sweeper aggregate: end"):
            if marker in text:
                problems.append(f"the note shows its marker {marker!r} as text")
        if "Ranked by IQM AUC" not in text:
            problems.append("the note does not say why the methods rank as they do")
        block = page.evaluate("[...document.querySelectorAll('pre')].map(p => p.innerText)")
        if not any("P(improvement)" in b and "pixel" in b and "linear" in b for b in block):
            problems.append("the note has no fixed-width probability-of-improvement table")
        assert not problems, "\n".join(problems)

        # a trial's page plays its final evaluation episode
        detail = json.loads(page.evaluate(f"fetch('{study_page.replace('/dashboard', '/api')}')"
                                          ".then(r => r.text())"))  # fmt: skip
        play_a_trial_video(page, study_page, detail["trials"][0]["number"])


@pytest.fixture(scope="module")
def published(tmp_path_factory) -> tuple[str, int]:
    """A copy of the published study with the comparison saved into it by this code (as
    ``sweeper aggregate`` saves it), and the number of its best non-control trial."""
    from sweeper.results._dashboard_card import best_non_control, save_to_dashboard
    from sweeper.results._frame import load_study_frame, stage_frame
    from sweeper.results._tables import study_tables
    from sweeper.spec._models import load_spec
    from sweeper.storage._open import open_study

    spec = load_spec(ROOT / "studies" / "fetch_reach_cpu.yaml")
    database = tmp_path_factory.mktemp("published") / "study.db"
    shutil.copy(PUBLISHED / "study.db", database)  # the committed file stays untouched
    url = f"sqlite:///{database}"
    search = stage_frame(load_study_frame(url, spec.study), "search")
    with open_study(url, spec.study, write=True, create=False) as store:
        tables = study_tables(search, driver_alive=store.driver_alive(), seed=spec.seed)
        save_to_dashboard(store.storage, search, tables)
    return url, int(best_non_control(search)["trial"])


@contextlib.contextmanager
def plain_optuna_dashboard(url: str, artifacts: Path, timeout: float = 60) -> Iterator[str]:
    """``optuna-dashboard URL --artifact-dir DIR`` (its console script's entry point), its
    hash seed random as anyone's; yields its address, stops it on exit."""
    with socket.socket() as probe:  # a free port (its console script has no port 0)
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    command = [sys.executable, "-c", "from optuna_dashboard._cli import main; main()", url]
    command += ["--port", str(port), "--artifact-dir", str(artifacts), "--quiet"]
    environment = {k: v for k, v in os.environ.items() if k != "PYTHONHASHSEED"}
    process = subprocess.Popen(
        command, env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
    )
    base = f"http://127.0.0.1:{port}"
    try:
        deadline = time.monotonic() + timeout
        while True:
            try:
                with OPENER.open(urllib.request.Request(f"{base}/api/studies"), timeout=5):
                    break
            except OSError:
                if process.poll() is not None or time.monotonic() > deadline:
                    pytest.fail(f"optuna-dashboard did not start: {process.stderr.read()[-2000:]}")
                time.sleep(0.5)
        yield base
    finally:
        stop(process)


def test_plain_optuna_dashboard_on_the_published_study_puts_the_comparison_first(published):
    url, best = published
    with (
        plain_optuna_dashboard(url, PUBLISHED / "artifacts") as base,
        browser(width=1024, height=1400) as page,
    ):
        study_page = f"{base}/dashboard/studies/1"
        page.goto(study_page)
        page.wait_for(f"{CARD} !== null && {CARD}.querySelector('g.table') !== null")
        cards = page.wait_for(
            f"(cards => cards.some(c => c.startsWith('Best Trial')) && cards)({CARDS_JS})"
        )
        # optuna-dashboard's own three cards come first, whatever a study stores; then
        # the saved figures, the sweep's one card alone among them, whatever the hash seed
        assert cards[:4] == [*OPTUNAS_FIRST, f"user-defined-plot:{COMPARISON_ID}"], cards
        assert sum(c.startswith("user-defined-plot:") for c in cards) == 1, cards

        # every method's name whole, the controls named as such
        names = page.evaluate(NAMES_JS)
        cut = [(text, round(over)) for text, over in names if over > 0]
        assert not cut, f"method names cut off at 1024 px: {cut}"
        shown = {text.replace(" ", "") for text, _ in names} - {"method"}
        methods = {"pixel", "linear", "conv", "conv_pytorch_init", "vae", "cvae"}
        assert shown == methods | {f"{c}(control)" for c in CONTROLS}, shown

        # the best non-control trial named beside optuna-dashboard's Best Trial card (the
        # best value of all, which is a control's here)
        title = page.evaluate(VIEW_JS)["title"]
        assert f"best non-control trial: #{best} " in title, title
        optunas_best = next(c for c in cards if c.startswith("Best Trial"))
        assert optunas_best != f"Best Trial (number={best})", optunas_best

        # that trial's page plays its video
        play_a_trial_video(page, study_page, best)
