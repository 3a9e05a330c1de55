"""What optuna-dashboard shows of the comparison: plotly figures and a section of the study
note, saved into the study."""

from __future__ import annotations

import numpy as np
import pandas as pd

from sweeper.aggregate.figures import (
    PALETTE,
    PLOTLY_DASHES,
    PROFILE_SCORES,
    clip_band,
    env_of,
    line_width,
    metric_label,
    random_label,
)
from sweeper.aggregate.frame import (
    by_auc,
    methods_of,
    random_success,
    scored,
    study_info,
    trial_rows,
)
from sweeper.aggregate.report import (
    DEFINITIONS,
    MIN_RELIABLE,
    _fmt,
    ranking_sentence,
    table_markdown,
)
from sweeper.aggregate.tables import CONFIDENCE, Tables
from sweeper.storage import OBJECTIVE_NAME, name_objective
from sweeper.text import plural

#: first and last lines of the study note's section written by ``sweeper aggregate``: link
#: reference definitions, the Markdown comment that renders as nothing (optuna-dashboard
#: shows an HTML comment as text)
NOTE_BEGIN = "[//]: # (sweeper aggregate: begin, rewritten by every run)"
NOTE_END = "[//]: # (sweeper aggregate: end)"
#: the markers written before, recognised so that their section is replaced, not repeated
OLD_MARKERS = (
    (
        "<!-- sweeper aggregate: begin (rewritten by every run) -->",
        "<!-- sweeper aggregate: end -->",
    ),
)
#: the graph object id of the comparison table, the dashboard's headline figure
COMPARISON_ID = "sweeper-comparison"


def _dash(index: int) -> str:
    return PLOTLY_DASHES[(index // 10 + index) % len(PLOTLY_DASHES)]


def _band_traces(
    go, method: str, colour: str, steps, line, low, high, n: int, what: str, index: int = 0
):
    """A filled band from ``low`` to ``high`` and the ``line`` over it, as plotly traces.

    Every trace sets its ``mode``: plotly's default for a trace of at most 20 points is
    lines and markers, which draws a band's outline as dots in the next palette colour."""
    band = colour.replace(", 1)", ", 0.2)")
    return [
        go.Scatter(
            x=steps + steps[::-1],
            y=list(high) + list(low)[::-1],
            mode="lines",
            fill="toself",
            fillcolor=band,
            line={"width": 0, "color": band},
            hoverinfo="skip",
            legendgroup=method,
            showlegend=False,
            name=f"{method} {what}",
        ),
        go.Scatter(
            x=steps,
            y=list(line),
            mode="lines+markers",
            name=f"{method} (n = {n})",
            legendgroup=method,
            line={"color": colour, "dash": _dash(index)},
            marker={"color": colour, "size": 5},
        ),
    ]


def _random_trace(go, frame: pd.DataFrame, steps: list[int]):
    """The random agent's measured success rate as a dotted grey line, or None."""
    success = random_success(frame)
    if success is None or not steps:
        return None
    return go.Scatter(
        x=[min(steps), max(steps)],
        y=[success, success],
        mode="lines",
        name=random_label(success),
        line={"color": "rgba(90, 90, 90, 1)", "dash": "dot", "width": 1.5},
        hoverinfo="name",
    )


def _curve_figure(go, frame, tables: Tables, metric: str):
    """Per method: success rate as IQM with its bootstrap band (the default curve), every
    other metric as mean ± std (clipped to the metric's range); the random agent's success
    rate as a line on the success rate."""
    colours = [f"rgba{(*rgb, 1)}" for rgb in PALETTE]
    figure = go.Figure()
    iqm = metric == "success_rate"
    drawn: list[int] = []
    for index, method in enumerate(methods_of(frame)):
        colour = colours[index % len(colours)]
        if iqm:
            part = tables.efficiency[tables.efficiency["method"] == method]
            if part.empty:
                continue
            line, low, high = part["iqm"], part["low"], part["high"]
        else:
            curves = tables.curves
            part = curves[(curves["method"] == method) & (curves["metric"] == metric)]
            if part.empty:
                continue
            std = part["std"].fillna(0)
            line = part["mean"]
            low, high = clip_band(metric, part["mean"] - std, part["mean"] + std)
        steps = part["step"].astype(int).tolist()  # lists: plain JSON, no binary arrays
        drawn += steps
        what = "band" if iqm else "± std"
        n = int(part["n"].max())
        for trace in _band_traces(go, method, colour, steps, line, low, high, n, what, index):
            figure.add_trace(trace)
    if metric == "success_rate" and (trace := _random_trace(go, frame, drawn)) is not None:
        figure.add_trace(trace)
    title = (
        f"success rate: IQM with {CONFIDENCE:.0%} bootstrap bands over done trials per method"
        if iqm
        else f"{metric.replace('_', ' ')}: mean ± std over done trials per method"
    )
    figure.update_layout(
        title=title,
        xaxis_title="environment steps",
        yaxis_title=metric_label(metric, env_of(frame)),
    )
    if metric.endswith("_rate"):  # a rate: its whole range, however low the curves
        figure.update_yaxes(range=[-0.02, 1.02])
    return figure


def _profile_figure(go, frame, tables: Tables):
    """Performance profiles, a panel per score, with bootstrap bands."""
    from plotly.subplots import make_subplots

    colours = [f"rgba{(*rgb, 1)}" for rgb in PALETTE]
    titles = PROFILE_SCORES.values()
    figure = make_subplots(
        rows=1, cols=len(PROFILE_SCORES), shared_yaxes=True, subplot_titles=[*titles]
    )
    profiles = tables.profiles
    for column, score in enumerate(PROFILE_SCORES, start=1):
        for index, method in enumerate(methods_of(frame)):
            part = profiles[(profiles["method"] == method) & (profiles["score"] == score)]
            if part.empty:
                continue
            colour = colours[index % len(colours)]
            n = int(part["n"].max())
            taus = part["tau"].tolist()
            fraction, low, high = part["fraction"], part["low"], part["high"]
            traces = _band_traces(go, method, colour, taus, fraction, low, high, n, "band", index)
            traces[1].update(
                mode="lines", line={"width": line_width(index, len(methods_of(frame)))}
            )  # 101 thresholds: a line without markers; earlier methods wider
            for trace in traces:
                shown = trace.showlegend is not False and column == 1
                trace.update(legendgroup=method, showlegend=shown)
                figure.add_trace(trace, row=1, col=column)
        figure.update_xaxes(title_text="threshold tau", range=[0, 1], row=1, col=column)
    figure.update_yaxes(title_text="fraction of trials above tau", range=[0, 1.02], row=1, col=1)
    figure.update_layout(title=f"Performance profiles with {CONFIDENCE:.0%} bootstrap bands")
    return figure


#: most trials drawn per method in the dashboard's trial panels (a study attr holds the
#: figure, and hundreds of overlapping lines read no better than a spread of them)
TRIALS_PER_PANEL = 30


def _panel_trials(trials: pd.DataFrame) -> pd.DataFrame:
    """One method's trials to draw: all of them, or ``TRIALS_PER_PANEL`` spread evenly over
    their AUC ranks (best and worst included; trials without an AUC rank last)."""
    if len(trials) <= TRIALS_PER_PANEL:
        return trials
    ranked = by_auc(trials)
    picks = np.unique(np.linspace(0, len(ranked) - 1, TRIALS_PER_PANEL).round().astype(int))
    return ranked.iloc[picks]


def _trials_figure(go, frame: pd.DataFrame):
    """Each method's trials' success rate in a panel of its own; hovering a point names its
    trial (key and number). One trace per method, its trials apart by gaps. The
    dashboard's own intermediate-value plot draws every trial alike."""
    from plotly.subplots import make_subplots

    methods = methods_of(frame)
    columns = min(3, len(methods))
    rows = -(-len(methods) // columns)
    trials = trial_rows(frame[frame["counted"]])
    titles = []
    for method in methods:
        mine = trials[trials["method"] == method]
        shown = len(_panel_trials(mine))
        titles.append(method if shown == len(mine) else f"{method} ({shown} of {len(mine)})")
    figure = make_subplots(
        rows=rows, cols=columns, shared_xaxes=True, shared_yaxes=True, subplot_titles=titles
    )
    evaluated = frame[frame["counted"] & frame["step"].notna()]
    for index, method in enumerate(methods):
        drawn = set(_panel_trials(trials[trials["method"] == method])["trial"])
        mine = evaluated[(evaluated["method"] == method) & evaluated["trial"].isin(drawn)]
        steps, success, names = [], [], []
        for (number, key), part in mine.groupby(["trial", "key"]):
            steps += [*part["step"].astype(int), None]  # None: a gap between two trials
            success += [*part["success_rate"], None]
            names += [f"{key} (trial {number})"] * (len(part) + 1)
        row, column = divmod(index, columns)
        figure.add_trace(
            go.Scatter(
                x=steps,
                y=success,
                text=names,
                mode="lines+markers",
                name=method,
                line={"color": f"rgba{(*PALETTE[index % len(PALETTE)], 1)}", "width": 1},
                hovertemplate="%{text}<br>step %{x}: %{y:.2f}<extra></extra>",
            ),
            row=row + 1,
            col=column + 1,
        )
    figure.update_yaxes(range=[-0.02, 1.02])
    figure.update_layout(
        title="success rate of every trial, a panel per method<br><sup>at most "
        f"{TRIALS_PER_PANEL} per method, spread over AUC ranks; hover: key and trial</sup>",
        showlegend=False,
    )
    return figure


def trials_by_method(frame, study_id: int) -> str:
    """A markdown line per method listing its counted trials' numbers, linked to
    optuna-dashboard's trial list with them selected (its ``numbers`` query: the list keeps
    every trial and shows the selected ones side by side; it has no filter by attribute)."""
    trials = trial_rows(frame[frame["counted"]])
    lines = []
    for method in methods_of(frame):
        numbers = sorted(trials.loc[trials["method"] == method, "trial"].tolist())
        if numbers:
            joined = ",".join(map(str, numbers))
            link = f"/dashboard/studies/{study_id}/trials?numbers={joined}"
            lines.append(
                f"- **{method}**: trials {', '.join(map(str, numbers))} "
                f"([show them side by side]({link}))"
            )
    return "\n".join(lines)


def _comparison_figure(go, frame: pd.DataFrame, tables: Tables):
    """The comparison as a table on the study page (optuna-dashboard shows the note on a
    page of its own): per method, best first by IQM AUC, its ledger, IQM AUC with its
    interval, and its paired probability of improvement over the next method."""
    table = tables.table
    done = table[table["n"] > 0].sort_values("iqm", ascending=False, kind="stable")
    rest = table[table["n"] == 0]
    lookup = {(r.method, r.versus): r for r in tables.improvement.itertuples()}
    rows: dict[str, list[str]] = {k: [] for k in ("rank", "method", "done", "iqm", "next", "best")}
    ordered = [*done.itertuples(), *rest.itertuples()]
    for rank, row in enumerate(ordered, start=1):
        following = ordered[rank] if rank < len(done) else None
        versus = "–"
        r = None if following is None else lookup.get((row.method, following.method))
        if r is not None and r.pairs:
            mark = "*" if r.pairs < MIN_RELIABLE else ""
            versus = (
                f"{_fmt(r.probability, 2)} [{_fmt(r.low, 2)}, {_fmt(r.high, 2)}] over "
                f"{following.method} ({plural(r.pairs, 'pair')}{mark})"
            )
        rows["rank"].append(str(rank) if row.n else "–")
        rows["method"].append(f"<b>{row.method}</b>")
        rows["done"].append(f"{row.done} of {row.planned}")
        rows["iqm"].append(
            f"{_fmt(row.iqm, 3)} [{_fmt(row.iqm_low, 3)}, {_fmt(row.iqm_high, 3)}]"
            if row.n
            else "–"
        )
        rows["next"].append(versus)
        rows["best"].append(f"#{row.best_trial} {_fmt(row.best_auc, 3)}" if row.n else "–")
    headers = [
        "rank",
        "method",
        "done",
        f"IQM AUC [{CONFIDENCE:.0%} CI]",
        "P(improvement) over the next",
        "best trial",
    ]
    figure = go.Figure(
        go.Table(
            columnwidth=[0.5, 1.3, 0.8, 1.6, 2.6, 1.0],
            header={"values": [f"<b>{h}</b>" for h in headers], "align": "left"},
            cells={"values": list(rows.values()), "align": "left", "height": 26},
        )
    )
    random = random_success(frame)
    subtitle = f"random agent: success {random:.2f}; " if random is not None else ""
    figure.update_layout(
        title={
            "text": "Method comparison, ranked by IQM AUC<br><sup>"
            f"{subtitle}* fewer than {MIN_RELIABLE} pairs; the note holds the whole table "
            "and the ranking's reason</sup>"
        },
        margin={"l": 10, "r": 10, "t": 70, "b": 10},
    )
    return figure


def _auc_figure(go, frame: pd.DataFrame, tables: Tables):
    """Every trial's AUC per method, with the method's IQM and its bootstrap CI."""
    done = tables.table[tables.table["n"] > 0]
    aucs = trial_rows(scored(frame))
    figure = go.Figure(
        go.Box(
            x=aucs["method"].tolist(),
            y=aucs["auc"].tolist(),
            text=aucs["key"].tolist(),
            boxpoints="all",
            jitter=0.4,
            pointpos=0,
            name="trial AUCs",
            marker={"color": "rgba(127, 127, 127, 0.7)"},
            line={"color": "rgba(127, 127, 127, 0.7)"},
        )
    )
    figure.add_trace(
        go.Scatter(
            x=done["method"].tolist(),
            y=done["iqm"].tolist(),
            mode="markers",
            marker={"size": 12, "symbol": "diamond", "color": "rgba(214, 39, 40, 1)"},
            error_y={
                "type": "data",
                "symmetric": False,
                "array": (done["iqm_high"] - done["iqm"]).tolist(),
                "arrayminus": (done["iqm"] - done["iqm_low"]).tolist(),
            },
            name=f"IQM with {CONFIDENCE:.0%} bootstrap CI",
        )
    )
    figure.update_layout(
        title=f"AUC per method: IQM with {CONFIDENCE:.0%} stratified bootstrap CI",
        xaxis_title="method",
        yaxis_title="AUC of success rate (normalised, 0..1)",
        yaxis_range=[-0.02, 1.02],
    )
    return figure


def save_to_dashboard(storage, frame: pd.DataFrame, tables: Tables) -> None:
    """Plotly figures (curves per metric, sample efficiency, profiles, trials per method,
    AUC), the objective's name and a note section into the study."""
    import optuna
    import plotly.graph_objects as go
    from optuna_dashboard import get_note, save_note, save_plotly_graph_object

    study = optuna.load_study(study_name=study_info(frame).name, storage=storage)
    if study.metric_names != [OBJECTIVE_NAME]:  # studies launched before it was named
        name_objective(study)
    figures = {COMPARISON_ID: _comparison_figure(go, frame, tables)}
    figures |= {
        f"sweeper-curves-{metric}": _curve_figure(go, frame, tables, metric)
        for metric in study_info(frame).metrics
    }
    figures["sweeper-profiles"] = _profile_figure(go, frame, tables)
    figures["sweeper-trials"] = _trials_figure(go, frame)
    figures["sweeper-auc"] = _auc_figure(go, frame, tables)
    for graph_object_id, figure in figures.items():
        save_plotly_graph_object(study, figure, graph_object_id=graph_object_id)
    section = "\n".join(
        [
            NOTE_BEGIN,
            "",
            "## Method comparison",
            "",
            "*Written by `sweeper launch` as trials finish and by `sweeper aggregate`; this "
            "section is rewritten each time, text outside it is kept.*",
            "",
            ranking_sentence(tables.table, tables.improvement, random_success(frame)),
            "",
            table_markdown(tables.table, tables.improvement, pairs=True),
            "",
            DEFINITIONS,
            "",
            "### Trials by method",
            "",
            trials_by_method(frame, study._study_id),
            "",
            NOTE_END,
        ]
    )
    save_note(study, replace_note_section(get_note(study), section))


def replace_note_section(note: str, section: str) -> str:
    """``note`` with its sweeper section (between the markers, or the markers written
    before, ``OLD_MARKERS``) replaced by ``section``, or ``section`` appended; what the user
    wrote around it is kept."""
    for first, last in ((NOTE_BEGIN, NOTE_END), *OLD_MARKERS):
        begin, end = note.find(first), note.find(last)
        if begin >= 0 and end > begin:
            return note[:begin] + section + note[end + len(last) :]
    return f"{note.rstrip()}\n\n{section}" if note.strip() else section
