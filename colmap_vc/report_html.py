"""The report's HTML pieces: escaping, tables, notes, number formats, the style
sheet (no scripts, no external resources)."""

from __future__ import annotations

import html
import math
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from colmap_vc.evaluation import THRESHOLDS_DEG, Metrics
from colmap_vc.structs import FloatArray

CSS = """
body{font:14px/1.45 system-ui,-apple-system,'Segoe UI',Roboto,'DejaVu Sans',sans-serif;
 margin:0;color:#1d2330;background:#f4f5f7}
main{max-width:1360px;margin:0 auto;padding:12px 20px 40px}
h1{font-size:22px;margin:8px 0 2px}h2{font-size:18px;margin:0 0 8px}
h3{font-size:15px;margin:6px 0 4px}
section{background:#fff;border:1px solid #dde1e7;border-radius:6px;padding:12px 16px;
 margin:12px 0}
nav a{margin-right:14px;color:#2457a6}.sub{color:#5b6473;margin:0 0 6px}
table{border-collapse:collapse;margin:4px 0 8px}
td,th{border-bottom:1px solid #e6e8ec;padding:3px 10px;text-align:left;
 vertical-align:top}
th{background:#f0f2f5}td.num{text-align:right;font-variant-numeric:tabular-nums}
.missing{background:#fff6e0;border-left:4px solid #e0a200;padding:6px 10px;margin:6px 0}
.cols{display:flex;flex-wrap:wrap;gap:16px;align-items:flex-start}
.bar{height:12px;background:#4a7fd0;border-radius:2px;display:inline-block}
img{max-width:100%;height:auto;display:block}
.pairs{display:grid;grid-template-columns:repeat(auto-fill,minmax(620px,1fr));gap:14px}
figure{margin:0}figcaption{font-size:12.5px;color:#3b4350;margin-top:3px}
.legend{display:inline-block;width:180px;height:12px;vertical-align:middle;
 background:linear-gradient(90deg,#00ff00,#ffff00,#ff0000);border:1px solid #999}
.swatch{display:inline-block;width:22px;height:3px;background:#008cff;vertical-align:middle}
.views input{display:none}.views label{display:inline-block;padding:3px 10px;
 border:1px solid #aab;border-radius:4px;margin-right:6px;cursor:pointer}
.views .view{display:none}
#v-oblique:checked~.tabs label[for=v-oblique],#v-front:checked~.tabs label[for=v-front],
#v-top:checked~.tabs label[for=v-top]{background:#2457a6;color:#fff}
#v-oblique:checked~.view-oblique,#v-front:checked~.view-front,
#v-top:checked~.view-top{display:block}
"""


def esc(value: object) -> str:
    return html.escape(str(value))


def table(
    header: Sequence[str], rows: Sequence[Sequence[object]], numeric_from: int = 1
) -> str:
    head = "".join(f"<th>{esc(h)}</th>" for h in header)
    body = "".join(
        "<tr>"
        + "".join(
            f"<td{' class=num' if i >= numeric_from else ''}>{esc(v)}</td>"
            for i, v in enumerate(row)
        )
        + "</tr>"
        for row in rows
    )
    return f"<table><tr>{head}</tr>{body}</table>"


def missing(text: str) -> str:
    return f'<p class="missing">{esc(text)}</p>'


def fmt(value: Any, digits: int = 1) -> str:
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return "-" if math.isnan(value) else f"{value:.{digits}f}"
    return "-" if value is None else str(value)


def metrics_rows(
    metrics: Mapping[str, Any],
) -> tuple[list[list[str]], dict[str, FloatArray]]:
    """Table rows and per-method pair errors (for the curve) from metrics dicts."""
    rows, curves = [], {}
    for name, m in metrics.items():
        m = m.to_dict() if isinstance(m, Metrics) else dict(m)
        auc = m.get("auc", {})
        rows.append(
            [
                name,
                f"{fmt(m.get('num_registered'))}/{fmt(m.get('num_images'))}",
                *(fmt(auc.get(f"{t:g}")) for t in THRESHOLDS_DEG),
                fmt(m.get("median_error_deg")),
            ]
        )
        if m.get("pairs"):
            curves[name] = np.array([p["error_deg"] for p in m["pairs"]], np.float64)
    return rows, curves


def timings_html(timings: Mapping[str, float]) -> str:
    longest = max(max(timings.values(), default=0.0), 1e-9)
    rows = "".join(
        f"<tr><td>{esc(stage)}</td><td class=num>{seconds:.2f} s</td><td>"
        f'<span class="bar" style="width:{max(1, round(300 * seconds / longest))}px">'
        "</span></td></tr>"
        for stage, seconds in timings.items()
    )
    total = sum(timings.values())
    return (
        f"<table><tr><th>stage</th><th>time</th><th></th></tr>{rows}"
        f"<tr><th>total</th><th class=num>{total:.2f} s</th><th></th></tr></table>"
    )
