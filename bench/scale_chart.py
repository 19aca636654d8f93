"""The scale benchmark's picture: each measure against the node count, a
line a mode, in one standalone SVG (no scripts, no external resources)."""

from __future__ import annotations

from html import escape

#: (key in a measurement, panel title, how a value is shown)
MEASURES = (
    ("load_all_ns", "load all (s)", lambda v: v / 1e9),
    ("idle_cpu_pct", "idle CPU (% of a core)", lambda v: v),
    ("pss_kb", "PSS (MiB)", lambda v: v / 1024),
    ("exit_ns", "SIGTERM → exit (s)", lambda v: v / 1e9),
)
COLORS = ("#2f6fb3", "#2e9d4f", "#d13b3b", "#7a6fb0", "#b35b2f")


def _panel(x0: float, y0: float, w: float, h: float, title: str, counts: list[int], lines: dict) -> list[str]:
    """One measure: axes, its lines (mode -> [value or None per count])."""
    values = [v for vs in lines.values() for v in vs if v is not None]
    top = max(values) * 1.1 if values and max(values) > 0 else 1.0
    lo_n, hi_n = counts[0], counts[-1]

    def px(n: int) -> float:
        return x0 + (0.5 if hi_n == lo_n else (n - lo_n) / (hi_n - lo_n)) * w

    def py(v: float) -> float:
        return y0 + h - (v / top) * h

    out = [
        f'<text x="{x0}" y="{y0 - 8}" font-size="13" font-weight="600">{escape(title)}</text>',
        f'<line x1="{x0}" y1="{y0 + h}" x2="{x0 + w}" y2="{y0 + h}" stroke="#888"/>',
        f'<line x1="{x0}" y1="{y0}" x2="{x0}" y2="{y0 + h}" stroke="#888"/>',
    ]
    for frac in (0.0, 0.5, 1.0):
        v = top * frac
        label = f"{v:.0f}" if v >= 100 else f"{v:.3g}"
        out.append(f'<text x="{x0 - 4}" y="{py(v) + 4:.1f}" font-size="10" text-anchor="end">{label}</text>')
    for n in counts:
        out.append(f'<text x="{px(n):.1f}" y="{y0 + h + 14}" font-size="10" text-anchor="middle">{n}</text>')
    for i, (mode, vs) in enumerate(lines.items()):
        color = COLORS[i % len(COLORS)]
        pts = [(px(n), py(v)) for n, v in zip(counts, vs, strict=True) if v is not None]
        if len(pts) > 1:
            path = " ".join(f"{x:.1f},{y:.1f}" for x, y in pts)
            out.append(f'<polyline points="{path}" fill="none" stroke="{color}" stroke-width="2"/>')
        for (x, y), n, v in zip(pts, [n for n, v in zip(counts, vs, strict=True) if v is not None],
                                [v for v in vs if v is not None], strict=True):  # fmt: skip
            out.append(f'<circle cx="{x:.1f}" cy="{y:.1f}" r="3" fill="{color}">'
                       f"<title>{escape(mode)}, {n} nodes: {v:.3g}</title></circle>")  # fmt: skip
    return out


def scale_svg(data: dict, counts: list[int], labels: dict[str, str]) -> str:
    """``data``: mode -> count -> measurement (bench.scale)."""
    pw, ph, gap_x, gap_y, left, top = 300.0, 170.0, 90.0, 70.0, 60.0, 40.0
    width = int(left + 2 * pw + gap_x + 20)
    legend_y = top + 2 * ph + gap_y + 50  # below the lower panels' axis titles
    height = int(legend_y + 18 * len(labels) + 10)
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" viewBox="0 0 {width} {height}" '
        'font-family="sans-serif">',
        f'<rect width="{width}" height="{height}" fill="white"/>',
        f"<title>Cost against the number of nodes ({', '.join(map(str, counts))})</title>",
    ]
    for i, (key, title, show) in enumerate(MEASURES):
        x0 = left + (i % 2) * (pw + gap_x)
        y0 = top + (i // 2) * (ph + gap_y)
        lines = {  # a configuration that failed (or did not exit) has no point
            labels[m]: [None if data[m][n].get(key) is None else show(data[m][n][key]) for n in counts] for m in data
        }
        out += _panel(x0, y0, pw, ph, title, counts, lines)
        out.append(f'<text x="{x0 + pw / 2}" y="{y0 + ph + 30}" font-size="10" text-anchor="middle">nodes</text>')
    for i, mode in enumerate(data):
        y = legend_y + 18 * i
        color = COLORS[i % len(COLORS)]
        out.append(f'<rect x="{left}" y="{y - 9}" width="14" height="10" fill="{color}"/>')
        out.append(f'<text x="{left + 20}" y="{y}" font-size="12">{escape(labels[mode])}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"
