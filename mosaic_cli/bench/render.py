"""The tables of ``mosaic bench`` (rich): one row an estimator, for a flight or video
(:func:`render_table`) and for a folder of flights (:func:`render_flights_table`)."""

from __future__ import annotations


def render_flights_table(report: dict):
    """A rich table of a :func:`run_flights` report: totals, then MACE per profile."""
    from rich.table import Table

    src = report["source"]
    profiles = src["profiles"]
    table = Table(title=f"bench: {len(src['flights'])} flights in {src['path']} ({src['frames']} frames)", title_justify="left")
    table.add_column("estimator", no_wrap=True)
    with_bursts = any(e.get("burst_pairs") for e in report["estimators"].values())
    burst_cols = ("burst pairs\nfailed", "carried\npairs") if with_bursts else ()
    for col in ("MACE\nall", *[f"MACE / failed\n{p}" for p in profiles], "corner px\nmedian", "failure\nrate",
                *burst_cols, "fallback\npairs", "ms/frame\np50", "CPU ms/fr\np50"):
        table.add_column(col, justify="right", no_wrap=True)

    def num(v, fmt):
        return "-" if v is None else fmt.format(v)

    for label, e in report["estimators"].items():
        paths = e.get("paths")
        fallback = paths.get("fallback", 0) / max(1, sum(paths.values())) if paths else None
        carried = paths.get("carried", 0) / max(1, sum(paths.values())) if paths else None
        burst_cells = (num(e.get("burst_failure_rate"), "{:.1%}"), num(carried, "{:.1%}")) if with_bursts else ()
        table.add_row(
            label,
            num(e["mace"], "{:.2f}"),
            *[f"{num(e['profiles'][p]['mace'], '{:.2f}')} / {e['profiles'][p]['failure_rate']:.1%}" for p in profiles],
            num(e["corner_error"], "{:.2f}"),
            num(e["failure_rate"], "{:.1%}"),
            *burst_cells,
            num(fallback, "{:.1%}"),
            num(e["ms_per_frame"]["p50"], "{:.2f}"),
            num(e["cpu_ms_per_frame"]["p50"], "{:.2f}"),
        )
    return table


def render_table(report: dict):
    """A rich table of a bench report."""
    from rich.table import Table

    src = report.get("source", {})
    title = (
        f"bench: simulated {src.get('profile')} flight, {src.get('frames')} frames {src.get('size', ['?', '?'])[0]}x{src.get('size', ['?', '?'])[1]}"
        if src.get("kind") == "simulated"
        else f"bench: {src.get('path')}"
    )
    table = Table(title=title, title_justify="left")
    table.add_column("estimator", no_wrap=True)
    for col in ("decode ms\np50/p95", "prep ms\np50/p95", "estimate ms\np50/p95", "ms per\nframe", "fps", "MACE\npx", "corner px\nmedian", "failure\nrate"):
        table.add_column(col, justify="right", no_wrap=True)

    def pair(s):
        return "-" if s["p50"] is None else f"{s['p50']:.2f}/{s['p95']:.2f}"

    def num(v, fmt):
        return "-" if v is None else fmt.format(v)

    for name, e in report["estimators"].items():
        st = e["stages"]
        table.add_row(
            name,
            pair(st["decode"]),
            pair(st["preprocess"]),
            pair(st["estimate"]),
            num(e["ms_per_frame"], "{:.2f}"),
            num(e["fps"], "{:.1f}"),
            num(e.get("mace"), "{:.2f}"),
            num(e.get("corner_error"), "{:.2f}"),
            num(e.get("failure_rate"), "{:.1%}"),
        )
    return table
