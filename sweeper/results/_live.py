"""The dashboard's comparison figures kept fresh while a launch runs.

``sweeper aggregate`` saves the per-method figures and the note section into the study;
without this they appear only after it is run. The driver calls ``after_trial`` each time a
trial's result is recorded; a refresh (read the study, compute the tables, save the figures
and the note, as ``sweeper aggregate`` does, without its files) runs when

- it is the launch's last trial (so the dashboard ends showing every result), or
- at least ``MIN_INTERVAL`` s have passed since the previous refresh ended and its cost
  stays within ``MAX_SHARE`` of the launch's time: after a refresh that took ``c`` seconds
  the next one waits at least ``c / MAX_SHARE`` seconds.

So the driver spends at most about ``MAX_SHARE`` of its time on figures however large the
study (measured: docs/dashboard/README.md). A refresh that fails (a database busy beyond its
timeout, a study nothing can be computed from yet) is reported in one line and skipped:
the figures are a view, never a reason to stop a sweep.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import TYPE_CHECKING

from sweeper.results._dashboard_card import save_to_dashboard
from sweeper.results._frame import load_study_frame, stage_frame, study_info
from sweeper.results._tables import study_tables

if TYPE_CHECKING:
    from sweeper.storage import StudyStore

#: seconds between two refreshes at least
MIN_INTERVAL = 60.0
#: the largest share of the driver's time spent refreshing
MAX_SHARE = 0.05


class FigureRefresh:
    """When to refresh one study's dashboard figures, and the refresh itself."""

    def __init__(
        self,
        store: StudyStore,
        *,
        min_interval: float = MIN_INTERVAL,
        max_share: float = MAX_SHARE,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.store = store
        self.min_interval, self.max_share, self.clock = min_interval, max_share, clock
        self.next_at = clock()  # the first result refreshes at once
        self.seconds: list[float] = []  # the cost of each refresh done
        self.failed = False

    def after_trial(self, final: bool = False, say: Callable[[str], None] | None = None) -> bool:
        """Refresh if it is due (or ``final``); return whether it refreshed."""
        now = self.clock()
        if not final and now < self.next_at:
            return False
        try:
            refresh(self.store)
        except Exception as e:  # a view must never stop the sweep
            if say is not None and not self.failed:
                say(f"dashboard figures not refreshed: {type(e).__name__}: {e}")
            self.failed = True
        cost = self.clock() - now
        self.seconds.append(cost)
        self.next_at = self.clock() + max(self.min_interval, cost / self.max_share)
        return True


def refresh(store: StudyStore) -> None:
    """Save the comparison figures and note of the study's search stage into it, computed
    as ``sweeper aggregate`` computes them (no files written)."""
    name = store.storage.get_study_name_from_id(store.study_id)
    frame = load_study_frame(store.storage.url, name)
    seed = int((study_info(frame).attrs.get("spec") or {}).get("seed", 0))
    search = stage_frame(frame, "search")
    tables = study_tables(search, driver_alive=True, seed=seed)
    save_to_dashboard(store.storage, search, tables)


_refreshers: dict[tuple[int, int], FigureRefresh] = {}


def after_trial(
    store: StudyStore, *, final: bool = False, say: Callable[[str], None] | None = None
) -> bool:
    """``FigureRefresh.after_trial`` of the store's study (one ``FigureRefresh`` per store,
    made at its first result): the driver's one call, after it recorded a trial."""
    key = (id(store), store.study_id)
    if key not in _refreshers:
        _refreshers[key] = FigureRefresh(store)
    return _refreshers[key].after_trial(final=final, say=say)
