"""optuna-dashboard on the CI study in headless Chromium, as a researcher sees it: the
comparison figures render (their bands draw no stray markers), the note shows the
comparison without its markers, and a trial's episode video plays.

Needs Chromium (``.ci/run`` installs Debian's when it is missing); skipped without it.
"""

from __future__ import annotations

import json

import pytest
from cdp import browser, chromium
from conftest import running_dashboard

pytestmark = pytest.mark.skipif(chromium() is None, reason="no chromium (apt-get install chromium)")

#: per sweeper figure on the study page: the number of scatter traces drawn, the markers
#: each draws and whether it is a filled band (``fill: toself``)
FIGURES_JS = """(() => {
  const out = {};
  for (const div of document.querySelectorAll("[id^='user-defined-plot:']")) {
    const traces = [...div.querySelectorAll("g.trace.scatter")];
    out[div.id.slice("user-defined-plot:".length)] = {
      svg: div.querySelector(".main-svg") !== null,
      text: div.textContent,
      fills: (div.data || []).filter(t => (t.type || "scatter") === "scatter")
        .map(t => t.fill || null),
      points: traces.map(g => g.querySelectorAll("path.point").length),
    };
  }
  return out;
})()"""

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


def test_the_dashboard_shows_the_comparison_and_plays_a_trial_video(ci_study, ci_aggregate):
    with running_dashboard(ci_study) as study_page, browser() as page:
        page.goto(study_page)
        ready = "document.querySelectorAll(\"[id^='user-defined-plot:'] .main-svg\").length >= 5"
        page.wait_for(ready)
        figures = page.evaluate(FIGURES_JS)

        # the comparison figures render, the methods named in them, the table first (the
        # order is a Python set's: sweeper dashboard fixes its hash seed)
        expected = {"sweeper-comparison", "sweeper-auc", "sweeper-trials", "sweeper-profiles"}
        expected |= {"sweeper-curves-success_rate", "sweeper-curves-final_distance"}
        assert expected <= set(figures)
        assert next(iter(figures)) == "sweeper-comparison", list(figures)
        for name, figure in figures.items():
            assert figure["svg"] and "pixel" in figure["text"], name
            assert "linear" in figure["text"], name
        assert "IQM AUC" in figures["sweeper-comparison"]["text"]
        # a band draws no markers; the lines over them draw one per evaluation step
        problems = []  # what a reader would see wrong, all of it reported at the end
        for name in ("sweeper-curves-success_rate", "sweeper-curves-final_distance"):
            figure = figures[name]
            assert len(figure["points"]) == len(figure["fills"]), name
            bands = [p for p, fill in zip(figure["points"], figure["fills"], strict=True) if fill]
            lines = [p for p, fill in zip(figure["points"], figure["fills"], strict=True)
                     if not fill and p]  # fmt: skip
            assert len(bands) == 2, name  # one per method
            if bands != [0, 0]:
                problems.append(f"{name}: stray markers on the bands: {bands}")
            if lines != [4, 4]:  # steps 0, 100, 200, 300 of each method
                problems.append(f"{name}: markers on the lines: {lines}")

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
        number = detail["trials"][0]["number"]
        page.goto(f"{study_page}/trials?numbers={number}")
        page.wait_for("document.querySelector('video') !== null")
        played = page.evaluate(PLAY_JS)
        assert played["error"] is None and played["width"] > 0, played
        assert played["time"] > 0.2, played
