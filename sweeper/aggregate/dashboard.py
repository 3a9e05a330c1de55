"""What optuna-dashboard shows of the comparison: plotly figures and a section of the study
note, saved into the study."""

from __future__ import annotations

from sweeper.aggregate.figures import PALETTE, env_of, metric_label
from sweeper.aggregate.frame import methods_of, scored, study_info, trial_rows
from sweeper.aggregate.report import DEFINITIONS, table_markdown
from sweeper.aggregate.tables import CONFIDENCE

#: first lines of the study note's section written by ``sweeper aggregate``
NOTE_BEGIN = "<!-- sweeper aggregate: begin (rewritten by every run) -->"
NOTE_END = "<!-- sweeper aggregate: end -->"


def save_to_dashboard(storage, study_id: int, frame, curves, table, improvement) -> None:
    """Plotly figures (curves per metric, AUC) and a note section into the study."""
    import optuna
    import plotly.graph_objects as go
    from optuna_dashboard import get_note, save_note, save_plotly_graph_object

    study = optuna.load_study(study_name=study_info(frame).name, storage=storage)
    colours = [f"rgba{(*rgb, 1)}" for rgb in PALETTE]
    for metric in study_info(frame).metrics:
        figure = go.Figure()
        for index, method in enumerate(methods_of(frame)):
            part = curves[(curves["method"] == method) & (curves["metric"] == metric)]
            if part.empty:
                continue
            steps = part["step"].astype(int).tolist()  # lists: plain JSON, no binary arrays
            mean = part["mean"].tolist()
            std = part["std"].fillna(0).tolist()
            colour = colours[index % len(colours)]
            band = colour.replace(", 1)", ", 0.2)")
            figure.add_trace(
                go.Scatter(
                    x=steps + steps[::-1],
                    y=[m + s for m, s in zip(mean, std, strict=True)]
                    + [m - s for m, s in zip(mean[::-1], std[::-1], strict=True)],
                    fill="toself",
                    fillcolor=band,
                    line={"width": 0},
                    hoverinfo="skip",
                    legendgroup=method,
                    showlegend=False,
                    name=f"{method} ± std",
                )
            )
            figure.add_trace(
                go.Scatter(
                    x=steps,
                    y=mean,
                    name=f"{method} (n = {int(part['n'].max())})",
                    line={"color": colour},
                    legendgroup=method,
                )
            )
        figure.update_layout(
            title=f"{metric.replace('_', ' ')}: mean ± std over done trials per method",
            xaxis_title="environment steps",
            yaxis_title=metric_label(metric, env_of(frame)),
        )
        save_plotly_graph_object(study, figure, graph_object_id=f"sweeper-curves-{metric}")
    done = table[table["n"] > 0]
    aucs = trial_rows(scored(frame))
    auc_figure = go.Figure(
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
    auc_figure.add_trace(
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
    auc_figure.update_layout(
        title=f"AUC per method: IQM with {CONFIDENCE:.0%} stratified bootstrap CI",
        xaxis_title="method",
        yaxis_title="AUC of success rate (normalised, 0..1)",
    )
    save_plotly_graph_object(study, auc_figure, graph_object_id="sweeper-auc")
    section = "\n".join(
        [
            NOTE_BEGIN,
            "## Method comparison (sweeper aggregate)",
            "",
            table_markdown(table, improvement),
            "",
            DEFINITIONS,
            NOTE_END,
        ]
    )
    save_note(study, replace_note_section(get_note(study), section))


#: matplotlib's default colour cycle (tab10) as RGB, so dashboard and PNG colours agree
def replace_note_section(note: str, section: str) -> str:
    """``note`` with its sweeper section (between the markers) replaced by ``section``,
    or ``section`` appended; what the user wrote around it is kept."""
    begin, end = note.find(NOTE_BEGIN), note.find(NOTE_END)
    if begin >= 0 and end > begin:
        return note[:begin] + section + note[end + len(NOTE_END) :]
    return f"{note.rstrip()}\n\n{section}" if note.strip() else section
