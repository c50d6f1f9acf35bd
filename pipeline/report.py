"""A static HTML page of the current DAG's artifacts: metrics, figures, provenance.

Everything comes from the store (nothing is recomputed) and the page works offline: no
script, no external URL. It is organised by conventions visible in the data only:
- a metric name is slash-separated; its first segment is its namespace (a study), and
  a node belongs to the namespaces of its metrics;
- four-segment names `<study>/<row>/<method>/<metric>` become pivot tables (rows x
  method column groups x metric columns; the row `mean` goes last, the best method per
  metric is shaded); other names are listed as they are;
- datasets under "figures/" hold PNG bytes; they are written to `<out>/figures/` and shown
  with the namespaces of their node, or under "Data" for nodes without metrics;
- an artifact attribute `report_tables` (a list of {"title", "header", "rows"}) is a node's
  answer in brief: those tables open the page, under "Summary".
"""
from __future__ import annotations

import html
import json
import math
import re
import struct
import time
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import quote

from pipeline.errors import PipelineError
from pipeline.metrics import higher_is_better

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
MEAN_ROW = "mean"
FIGURE_FILE = re.compile(r"^[0-9a-f]{12}-[A-Za-z0-9._-]+\.png$")  # files this module writes
PROVENANCE_FIELDS = ("params", "key", "code", "inputs", "created", "seconds", "timing", "host")

CSS = """:root{--line:#d0d7de;--head:#f0f3f6;--best:#c9efcf;--muted:#57606a}
body{font:14px/1.45 system-ui,-apple-system,"Segoe UI",sans-serif;margin:0;color:#1f2328}
header{padding:12px 28px;background:var(--head);border-bottom:1px solid var(--line)}
header h1{margin:0 0 6px;font-size:22px}main{padding:0 28px 40px}
h2{margin-top:36px;padding-top:8px;border-top:2px solid var(--line)}h3{margin:20px 0 6px;font-size:16px}
a{color:#0550ae}code,pre{font:12px/1.4 ui-monospace,Menlo,Consolas,monospace}
pre{background:#f6f8fa;border:1px solid var(--line);padding:6px 8px;overflow:auto;max-height:360px;margin:4px 0}
.meta{color:var(--muted);margin:4px 0}.warn{color:#9a3412}
dl.info{display:grid;grid-template-columns:max-content auto;gap:1px 14px;margin:6px 0}dl.info dt{color:var(--muted)}dl.info dd{margin:0}
nav.toc ol{columns:3 220px;margin:6px 0;padding-left:22px}
.scroll{max-height:75vh;max-width:100%;overflow:auto;border:1px solid var(--line);display:inline-block}
table{border-collapse:separate;border-spacing:0;font-size:13px}
th,td{padding:2px 8px;border-right:1px solid var(--line);border-bottom:1px solid var(--line);white-space:nowrap;text-align:left}
thead th{position:sticky;top:0;z-index:2;background:var(--head);line-height:20px;height:25px;box-sizing:border-box}
thead tr+tr th{top:25px}thead th.group{text-align:center;border-bottom:2px solid #8c959f}
tbody th{position:sticky;left:0;z-index:1;background:#fff;font-weight:500}thead th.corner{left:0;z-index:3}
td.num{text-align:right;font-variant-numeric:tabular-nums}
tbody tr:nth-child(even) td,tbody tr:nth-child(even) th{background:#f8f9fa}tbody tr:hover td,tbody tr:hover th{background:#eaf1fb}
table.pivot tbody td.best{background:var(--best);font-weight:600}
table.pivot tbody tr.mean td,table.pivot tbody tr.mean th{font-weight:700;border-top:2px solid #8c959f;position:sticky;bottom:0;z-index:1;background:#fff}
table.pivot tbody tr.mean th{z-index:2}table.pivot tbody tr.mean td.best{background:var(--best)}
tr.stale td,tr.stale th{color:#b42318}td.status-stale{font-weight:700}
.gallery{display:flex;flex-wrap:wrap;gap:14px;align-items:flex-start}
figure{margin:0;max-width:420px}figure img{display:block;max-width:100%;height:auto;border:1px solid var(--line);background:#fff}
figcaption{font-size:12px;color:var(--muted);overflow-wrap:anywhere}
details{margin:3px 0}summary{cursor:pointer}details dl.info{margin-left:18px}"""


@dataclass
class Figure:
    node: str           # the instance that made it
    name: str           # its dataset name after "figures/"
    file: str           # file name under <out>/figures/
    width: int
    height: int


@dataclass
class NodeView:
    """One planned instance as the page shows it."""
    name: str
    node: str
    status: str
    reason: str
    key: str | None
    record: dict | None
    provenance: dict = field(default_factory=dict)
    figures: list[Figure] = field(default_factory=list)
    tables: list[dict] = field(default_factory=list)   # attrs report_tables

    @property
    def metrics(self) -> dict[str, float]:
        return (self.record or {}).get("metrics") or {}


@dataclass
class Pivot:
    """Four-segment metrics of one study with one set of metrics per method."""
    study: str
    methods: list[str]
    metrics: list[str]
    rows: list[str]                                   # natural order, `mean` last
    values: dict[tuple[str, str, str], float]         # (row, method, metric) -> value
    best: set[tuple[str, str, str]]                   # cells holding a row's best per metric

    @property
    def columns(self) -> list[tuple[str, str]]:
        return [(m, k) for m in self.methods for k in self.metrics]


# -- organising metrics ----------------------------------------------------------------

def natural_key(text: str) -> list:
    """'Array10' sorts after 'Array2'."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", text) if t]


def namespace(metric: str) -> str:
    return metric.split("/", 1)[0]


def pivots(metrics: dict[str, float]) -> tuple[list[Pivot], dict[str, float]]:
    """Split one namespace's metrics into pivot tables and the remaining flat metrics.

    Methods reporting the same set of metric names share a table, so image metrics (few
    methods x fid, kid) and force metrics (other methods x mae_*, r2_*) of a study get
    one table each instead of one wide, mostly empty table.
    """
    cells: dict[str, dict[tuple[str, str, str], float]] = {}
    rest: dict[str, float] = {}
    for name, value in metrics.items():
        parts = name.split("/")
        if len(parts) == 4 and all(parts) and _is_number(value):
            cells.setdefault(parts[0], {})[(parts[1], parts[2], parts[3])] = float(value)
        else:
            rest[name] = value
    out = []
    for study in sorted(cells, key=natural_key):
        values = cells[study]
        per_method: dict[str, set[str]] = {}
        for _, method, metric in values:
            per_method.setdefault(method, set()).add(metric)
        groups: dict[tuple[str, ...], list[str]] = {}
        for method in sorted(per_method, key=natural_key):
            groups.setdefault(tuple(sorted(per_method[method], key=natural_key)), []).append(method)
        for names, methods in groups.items():
            mine = {c: v for c, v in values.items() if c[1] in methods}
            rows = sorted({r for r, _, _ in mine}, key=lambda r: (r == MEAN_ROW, natural_key(r)))
            out.append(Pivot(study, methods, list(names), rows, mine, _best(study, mine, rows, methods, names)))
    return out, rest


def _best(study, values, rows, methods, metrics) -> set[tuple[str, str, str]]:
    best = set()
    for row in rows:
        for metric in metrics:
            scored = [(values[(row, m, metric)], m) for m in methods
                      if math.isfinite(values.get((row, m, metric), math.nan))]
            if len(scored) < 2:
                continue
            pick = max if higher_is_better(f"{study}/{row}/{scored[0][1]}/{metric}") else min
            top = pick(v for v, _ in scored)
            best.update((row, m, metric) for v, m in scored if v == top)
    return best


def _plural(n: int, word: str) -> str:
    return f"{n} {word}{'' if n == 1 else 's'}"


def _same(a, b) -> bool:
    return a == b or (_is_number(a) and _is_number(b) and math.isnan(a) and math.isnan(b))


def _is_number(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def fmt(v) -> str:
    """3-4 significant digits; plain integers up to ten million."""
    if not _is_number(v):
        return str(v)
    v = float(v)
    if not math.isfinite(v) or v == 0:
        return "0" if v == 0 else str(v)
    if 1e4 <= abs(v) < 1e7:
        return f"{v:.0f}"
    return f"{v:.4g}"


# -- reading the store ------------------------------------------------------------------

def _png_size(data: bytes) -> tuple[int, int] | None:
    if len(data) < 24 or not data.startswith(PNG_SIGNATURE) or data[12:16] != b"IHDR":
        return None
    return struct.unpack(">II", data[16:24])


def _file_name(key: str, name: str, used: set[str]) -> str:
    stem = f"{key[:12]}-{re.sub(r'[^A-Za-z0-9._-]+', '_', name).strip('._') or 'figure'}"[:100]
    fname, n = f"{stem}.png", 1
    while fname in used:
        n += 1
        fname = f"{stem}-{n}.png"
    used.add(fname)
    return fname


def _read(planned, store, fig_dir: Path, warnings: list[str]) -> list[NodeView]:
    views, used = [], set()
    for p in planned:
        view = NodeView(p.name, p.name.split("[", 1)[0], p.status, p.reason, p.key, p.record)
        views.append(view)
        if p.record is None:
            continue
        view.node = p.record.get("node") or view.node
        try:
            with store.open(p.key, p.name) as a:
                view.provenance = a.provenance
                tables = a.attrs.get("report_tables")
                if isinstance(tables, list):
                    view.tables = [t for t in tables if isinstance(t, dict) and "rows" in t]
                for name in a:
                    if not name.startswith("figures/"):
                        continue
                    raw = a[name][()]
                    data = raw.tobytes() if hasattr(raw, "tobytes") else b""
                    size = _png_size(data)
                    if size is None:
                        warnings.append(f"{p.name}: {name} is not a PNG image; left out")
                        continue
                    fname = _file_name(p.key, name[len("figures/"):], used)
                    (fig_dir / fname).write_bytes(data)
                    view.figures.append(Figure(p.name, name[len("figures/"):], fname, *size))
        except (PipelineError, OSError, KeyError, RuntimeError) as exc:  # h5py's ways to fail
            view.status, view.reason, view.figures = "unreadable", (str(exc) or type(exc).__name__).splitlines()[0], []
            warnings.append(f"{p.name}: artifact unreadable; its figures and provenance are missing")
    for old in fig_dir.iterdir():  # an earlier report's figures must not linger
        if FIGURE_FILE.match(old.name) and old.name not in used:
            old.unlink(missing_ok=True)
    return views


def _last_run(store) -> dict | None:
    runs = sorted(Path(store.runs).glob("*.json")) if Path(store.runs).is_dir() else []
    for path in reversed(runs):
        try:
            meta = json.loads(path.read_text())
        except (OSError, ValueError):
            continue
        stamp = path.name.split("-", 1)[0]  # 20240131T120000
        meta["when"] = (f"{stamp[:4]}-{stamp[4:6]}-{stamp[6:8]} {stamp[9:11]}:{stamp[11:13]}:{stamp[13:15]} UTC"
                        if re.fullmatch(r"\d{8}T\d{6}", stamp) else stamp)
        return meta
    return None


# -- HTML -------------------------------------------------------------------------------

def esc(x) -> str:
    return html.escape(str(x), quote=True)


def slug(prefix: str, text: str) -> str:
    return f"{prefix}-{re.sub(r'[^A-Za-z0-9_-]+', '-', text).strip('-')}"


def _arrow(name: str) -> tuple[str, str]:
    return ("&#8593;", "higher is better") if higher_is_better(name) else ("&#8595;", "lower is better")


def pivot_html(p: Pivot) -> str:
    head1 = "".join(f"<th class='group' colspan='{len(p.metrics)}'>{esc(m)}</th>" for m in p.methods)
    head2 = ""
    for _ in p.methods:
        for k in p.metrics:
            arrow, word = _arrow(f"{p.study}/x/x/{k}")
            head2 += f"<th title='{word}'>{esc(k)} {arrow}</th>"
    body = []
    for row in p.rows:
        cells = []
        for method, metric in p.columns:
            v = p.values.get((row, method, metric))
            if v is None:
                cells.append("<td></td>")
                continue
            cls = "num best" if (row, method, metric) in p.best else "num"
            cells.append(f"<td class='{cls}' title='{esc(f'{p.study}/{row}/{method}/{metric} = {v!r}')}'>"
                         f"{esc(fmt(v))}</td>")
        tr = " class='mean'" if row == MEAN_ROW else ""
        body.append(f"<tr{tr}><th>{esc(row)}</th>{''.join(cells)}</tr>")
    n = len([r for r in p.rows if r != MEAN_ROW])
    return (f"<p class='meta'>{_plural(n, 'row')} &times; {esc(', '.join(p.methods))}</p>"
            f"<div class='scroll'><table class='pivot'><thead><tr><th class='corner' rowspan='2'></th>{head1}</tr>"
            f"<tr>{head2}</tr></thead><tbody>{''.join(body)}</tbody></table></div>")


def _flat_html(study: str, rest: dict[str, float], owner: dict[str, str]) -> str:
    rows = "".join(f"<tr><th title='{esc(k)}'>{esc(k[len(study) + 1:] or k)}</th>"
                   f"<td class='num' title='{esc(repr(v))}'>{esc(fmt(v))}</td><td>{esc(owner.get(k, ''))}</td></tr>"
                   for k, v in sorted(rest.items(), key=lambda kv: natural_key(kv[0])))
    return (f"<div class='scroll'><table class='flat'><thead><tr><th class='corner'>metric</th><th>value</th>"
            f"<th>node</th></tr></thead><tbody>{rows}</tbody></table></div>")


def _gallery(figures: list[Figure]) -> str:
    items = []
    for f in figures:
        src = "figures/" + quote(f.file)
        items.append(f"<figure><a href='{src}'><img src='{src}' loading='lazy' width='{f.width}' "
                     f"height='{f.height}' alt='{esc(f.node)}: {esc(f.name)}'></a>"
                     f"<figcaption><a href='#{esc(slug('prov', f.node))}'>{esc(f.node)}</a> &middot; "
                     f"{esc(f.name)}</figcaption></figure>")
    return f"<div class='gallery'>{''.join(items)}</div>"


def _json(v) -> str:
    return esc(json.dumps(v, indent=2, sort_keys=True, default=str))


def _prov_html(v: NodeView, *, full: bool) -> str:
    rec, prov = v.record or {}, v.provenance
    if full:
        shown = {k: x for k, x in prov.items() if k != "metrics"}
        shown.setdefault("host", rec.get("host"))
        body = f"<pre>{_json(shown)}</pre><p class='meta'>{len(v.metrics)} metrics, {len(v.figures)} figures</p>"
        anchor = f" id='{esc(slug('prov', v.name))}'"
    else:
        fields = {"params": prov.get("params"), "key": v.key, "code": prov.get("code"),
                  "inputs": prov.get("inputs", rec.get("inputs")), "created": rec.get("created"),
                  "seconds": rec.get("seconds"), "timing": prov.get("timing"), "host": rec.get("host")}
        items = "".join(f"<dt>{k}</dt><dd>" + (f"<pre>{_json(fields[k])}</pre>" if k in ("params", "inputs", "timing")
                                               else f"<code>{esc(fields[k])}</code>") + "</dd>"
                        for k in PROVENANCE_FIELDS if k != "timing" or fields[k])
        body, anchor = f"<dl class='info'>{items}</dl>", ""
    return (f"<details{anchor}><summary>{esc(v.name)} <code>{esc((v.key or '')[:12])}</code></summary>"
            f"{body}</details>")


def _study_html(ns: str, metrics: dict[str, float], nodes: list[NodeView], owner: dict[str, str]) -> str:
    """One namespace: pivot tables, other metrics, its nodes' figures and provenance."""
    tables, rest = pivots(metrics)
    figures = [f for v in nodes for f in v.figures]
    note = (" Shaded: the best method per metric in its row (&#8595; lower is better, &#8593; higher "
            "is better)." if tables else "")
    parts = [f"<section id='{esc(slug('ns', ns))}'><h2>{esc(ns)}</h2><p class='meta'>"
             f"{_plural(len(metrics), 'metric')} from {_plural(len(nodes), 'node')}.{note}</p>"]
    parts += [pivot_html(t) for t in tables]
    if rest:
        parts.append(("<h3>Other metrics</h3>" if tables else "") + _flat_html(ns, rest, owner))
    if figures:
        parts.append(f"<h3>Figures</h3>{_gallery(figures)}")
    parts.append("<h3>Produced by</h3>" + "".join(_prov_html(v, full=False) for v in nodes))
    return "".join(parts) + "</section>"


def _summary_html(views: list[NodeView]) -> str:
    """The tables nodes publish (attrs report_tables), in plan order: the page's first section."""
    parts = []
    for v in views:
        for t in v.tables:
            head = "".join(f"<th>{esc(h)}</th>" for h in t.get("header", []))
            body = "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in row) + "</tr>" for row in t["rows"])
            parts.append(f"<h3>{esc(t.get('title', v.name))}</h3><div class='scroll'><table class='summary'>"
                         f"<thead><tr>{head}</tr></thead><tbody>{body}</tbody></table></div>"
                         f"<p class='meta'>from <a href='#{esc(slug('prov', v.name))}'>{esc(v.name)}</a></p>")
    return f"<section id='summary'><h2>Summary</h2>{''.join(parts)}</section>" if parts else ""


def _status_html(views: list[NodeView]) -> str:
    rows = []
    for v in views:
        rec = v.record or {}
        bad = v.status in ("stale", "unreadable")
        name = (f"<a href='#{esc(slug('prov', v.name))}'>{esc(v.name)}</a>" if v.provenance else esc(v.name))
        rows.append(f"<tr{' class=stale' if bad else ''}><th>{name}</th>"
                    f"<td class='status-{esc(v.status)}'>{esc(v.status)}</td><td>{esc(v.reason)}</td>"
                    f"<td><code>{esc((v.key or '')[:12])}</code></td><td>{esc(rec.get('created', ''))}</td>"
                    f"<td class='num'>{esc('' if rec.get('seconds') is None else fmt(rec['seconds']))}</td>"
                    f"<td>{esc(rec.get('host', ''))}</td><td class='num'>{len(v.metrics) if v.record else ''}</td>"
                    f"<td class='num'>{len(v.figures) if v.provenance else ''}</td></tr>")
    return ("<div class='scroll'><table class='nodes'><thead><tr><th class='corner'>node</th><th>status</th>"
            "<th>why</th><th>key</th><th>created</th><th>seconds</th><th>host</th><th>metrics</th>"
            f"<th>figures</th></tr></thead><tbody>{''.join(rows)}</tbody></table></div>")


def _header(title, store, views, metrics, info, warnings) -> str:
    recs = [v.record for v in views if v.record]
    stale = [v.name for v in views if v.status in ("stale", "unreadable")]
    created = sorted(r.get("created") or "" for r in recs)
    hosts = sorted({r.get("host") for r in recs if r.get("host")})
    facts = {"generated": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
             "store": str(store.root),
             "nodes": f"{len(views)} ({len(views) - len(stale)} built, {len(stale)} not built)",
             "metrics": len(metrics), "figures": sum(len(v.figures) for v in views),
             "artifacts created": f"{created[0]} … {created[-1]}" if created else "none",
             "compute seconds": fmt(sum(float(r.get("seconds") or 0) for r in recs)),
             "hosts": ", ".join(hosts) or "unknown", **(info or {})}
    last = _last_run(store)
    if last:
        facts["last run"] = (f"{last['when']}: profile {last.get('profile', '?')}, targets "
                             f"{' '.join(last.get('targets') or []) or '(all)'}"
                             + (f", -p {' -p '.join(last['params'])}" if last.get("params") else ""))
    dl = "".join(f"<dt>{esc(k)}</dt><dd>{esc(v)}</dd>" for k, v in facts.items())
    notes = []
    if stale:
        notes.append(f"{len(stale)} nodes are not built, so their metrics and figures are missing: "
                     f"{esc(', '.join(stale[:8]))}{' …' if len(stale) > 8 else ''} (see <a href='#nodes'>Nodes</a>).")
    notes += [esc(w) for w in warnings]
    warn = "".join(f"<p class='warn'>{n}</p>" for n in notes)
    return f"<header><h1>{esc(title)}</h1><dl class='info'>{dl}</dl>{warn}</header>"


def write(planned, store, out_dir: Path, *, title: str = "Pipeline report", info: dict | None = None) -> Path:
    """Write `<out_dir>/index.html` and `<out_dir>/figures/*.png`; return the page's path.

    `planned` are the scheduler's planned items (cached ones carry a record); `info` adds
    lines to the header's run facts (e.g. {"profile": "ci"}).
    """
    out_dir = Path(out_dir)
    fig_dir = out_dir / "figures"
    try:
        fig_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PipelineError(f"cannot write report to {out_dir}: {exc.strerror}") from None
    warnings: list[str] = []
    views = _read(planned, store, fig_dir, warnings)

    metrics: dict[str, float] = {}
    owner: dict[str, str] = {}
    members: dict[str, list[NodeView]] = {}   # namespace -> producing nodes, plan order
    for v in views:
        for name, value in v.metrics.items():
            if name in metrics and not _same(metrics[name], value):
                warnings.append(f"metric {name} reported by {owner[name]} and {v.name} with different "
                                f"values; showing {owner[name]}'s")
                continue
            metrics.setdefault(name, value)
            owner.setdefault(name, v.name)
        for ns in dict.fromkeys(namespace(n) for n in v.metrics):
            members.setdefault(ns, []).append(v)
    # studies with figures first, then in the order the DAG produces them
    order = sorted(members, key=lambda ns: not any(v.figures for v in members[ns]))  # stable
    data_nodes: dict[str, list[NodeView]] = {}
    for v in views:
        if v.figures and not v.metrics:
            data_nodes.setdefault(v.node, []).append(v)

    sections, toc = [], []
    summary = _summary_html(views)
    if summary:
        sections.append(summary)
        toc.append(f"<li><a href='#summary'>Summary</a> <span class='meta'>"
                   f"{_plural(sum(len(v.tables) for v in views), 'table')}</span></li>")
    for ns in order:
        mine = {k: x for k, x in metrics.items() if namespace(k) == ns}
        n_fig = sum(len(v.figures) for v in members[ns])
        toc.append(f"<li><a href='#{esc(slug('ns', ns))}'>{esc(ns)}</a> <span class='meta'>"
                   f"{_plural(len(mine), 'metric')}, {_plural(n_fig, 'figure')}</span></li>")
        sections.append(_study_html(ns, mine, members[ns], owner))
    if data_nodes:
        n_fig = sum(len(v.figures) for vs in data_nodes.values() for v in vs)
        toc.append(f"<li><a href='#data'>Data</a> <span class='meta'>{n_fig} figures</span></li>")
        groups = "".join(f"<h3 id='{esc(slug('data', node))}'>{esc(node)}</h3>"
                         + _gallery([f for v in vs for f in v.figures])
                         for node, vs in sorted(data_nodes.items(), key=lambda kv: natural_key(kv[0])))
        sections.append(f"<section id='data'><h2>Data</h2><p class='meta'>Figures of nodes that report "
                        f"no metrics, by node.</p>{groups}</section>")
    toc.append(f"<li><a href='#nodes'>Nodes</a> <span class='meta'>{len(views)}</span></li>"
               "<li><a href='#provenance'>Provenance</a></li>")
    sections.append(f"<section id='nodes'><h2>Nodes</h2>{_status_html(views)}</section>")
    prov = "".join(_prov_html(v, full=True) for v in views if v.provenance)
    sections.append(f"<section id='provenance'><h2>Provenance</h2>{prov or '<p>none</p>'}</section>")

    page = (f"<!doctype html><html lang='en'><head><meta charset='utf-8'><title>{esc(title)}</title>"
            "<meta name='viewport' content='width=device-width,initial-scale=1'>"
            f"<link rel='icon' href='data:,'><style>{CSS}</style></head><body>"  # no favicon request
            f"{_header(title, store, views, metrics, info, warnings)}<main><nav class='toc'><h2>Contents</h2>"
            f"<ol>{''.join(toc)}</ol></nav>{''.join(sections)}</main></body></html>\n")
    index = out_dir / "index.html"
    tmp = out_dir / ".index.html.tmp"
    tmp.write_text(page, encoding="utf-8")
    tmp.replace(index)
    return index
