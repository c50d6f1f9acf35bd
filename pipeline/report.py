"""A static HTML page of the current DAG's artifacts: metrics, figures, provenance.

Figures are datasets under "figures/" holding PNG bytes (uint8, 1-D); they are written
beside the page. Everything comes from the store: nothing is recomputed.
"""
from __future__ import annotations

import html
import json
import time
from pathlib import Path

from pipeline.errors import PipelineError

CSS = """body{font-family:system-ui,sans-serif;margin:2em;max-width:1200px;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 8px;font-size:13px}
th{background:#f3f3f3}.stale{color:#b00}code{font-size:12px}figure{display:inline-block;margin:8px}
img{max-width:520px;border:1px solid #ddd}details{margin:4px 0}"""


def write(planned, store, out_dir: Path, *, title: str = "Pipeline report") -> Path:
    out_dir = Path(out_dir)
    try:
        (out_dir / "figures").mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PipelineError(f"cannot write report to {out_dir}: {exc.strerror}") from None
    esc = html.escape
    rows, figs, metrics, prov = [], [], {}, []
    for p in planned:
        rec = p.record or {}
        cls = "" if p.record else " class='stale'"
        rows.append(f"<tr{cls}><td>{esc(p.name)}</td><td>{esc(p.status)}</td><td>{esc(p.reason)}</td>"
                    f"<td><code>{esc((p.key or '')[:12])}</code></td><td>{esc(rec.get('created', ''))}</td>"
                    f"<td>{rec.get('seconds', '')}</td></tr>")
        metrics.update(rec.get("metrics") or {})
        if not p.record:
            continue
        from pipeline.artifact import Artifact
        with Artifact(store.path(p.key)) as a:
            for name in a:
                if name.startswith("figures/"):
                    fname = f"{p.key[:12]}-{name.split('/', 1)[1].replace('/', '_')}.png"
                    (out_dir / "figures" / fname).write_bytes(bytes(a[name][()]))
                    figs.append(f"<figure><img src='figures/{esc(fname)}' alt='{esc(name)}'>"
                                f"<figcaption>{esc(p.name)}: {esc(name[8:])}</figcaption></figure>")
            pv = a.provenance
        prov.append(f"<details><summary>{esc(p.name)}</summary><pre>"
                    f"{esc(json.dumps({k: pv.get(k) for k in ('key', 'digest', 'code', 'params', 'grid', 'inputs', 'created', 'seconds', 'host')}, indent=1))}"
                    "</pre></details>")
    mrows = "".join(f"<tr><td>{esc(k)}</td><td>{v:.6g}</td></tr>" for k, v in sorted(metrics.items()))
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>{esc(title)}</title>
<style>{CSS}</style></head><body><h1>{esc(title)}</h1>
<p>Generated {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())} from store <code>{esc(str(store.root))}</code>.</p>
<h2>Metrics</h2><table><tr><th>metric</th><th>value</th></tr>{mrows}</table>
<h2>Figures</h2>{''.join(figs) or '<p>none yet</p>'}
<h2>Nodes</h2><table><tr><th>node</th><th>status</th><th>why</th><th>key</th><th>created</th><th>seconds</th></tr>
{''.join(rows)}</table>
<h2>Provenance</h2>{''.join(prov)}
</body></html>"""
    index = out_dir / "index.html"
    index.write_text(page)
    return index
