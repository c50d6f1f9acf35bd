"""`pipeline report`: pivot tables, figures, provenance; the page checked in headless Chromium."""
import os
import re
import shutil
import time
from pathlib import Path

import pytest

from browser import Browser, find_chromium
from pipeline.report import MEAN_ROW, fmt, pivots
from toyproject import cli, run_json

# A study node (namespaced metrics + figures, one PNG named with HTML characters, one
# dataset that is not a PNG) and a node with figures and no metrics (the "Data" section).
GRAPH = '''
GRAPH.node("study", "toy.study:study", inputs={"summary": "summary"}, params={"scale": "scale"})
GRAPH.node("pictures", "toy.study:pictures", inputs={"base": "base"}, params={"offset": "offset.{letter}"},
           grid={"letter": "letters"})
'''

STUDY = '''
import struct
import zlib

import numpy as np

PAIRS = [f"Array{i}_Array{j}" for i in range(1, 5) for j in range(1, 5) if i != j]


def png(img):
    """Grayscale uint8 (H,W) -> PNG bytes, with the standard library only."""
    h, w = img.shape
    raw = b"".join(b"\\x00" + img[r].tobytes() for r in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    data = (b"\\x89PNG\\r\\n\\x1a\\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))
    return np.frombuffer(data, np.uint8)


def study(summary, scale):
    m = {}
    for i, pair in enumerate(PAIRS):
        m[f"study/{pair}/before/fid"] = 100.0 + i
        m[f"study/{pair}/m2m/fid"] = 51.234567 + i * scale       # lower is better: m2m wins
        m[f"study/{pair}/genforce/mae_fz"] = 0.125 + 0.01 * i    # lower is better: genforce wins
        m[f"study/{pair}/genforce/r2_fz"] = 0.9
        m[f"study/{pair}/source_only/mae_fz"] = 0.5
        m[f"study/{pair}/source_only/r2_fz"] = 0.95             # higher is better: source_only wins
    m["study/mean/m2m/fid"] = 60.0
    m["study/mean/before/fid"] = 105.5
    m["study/count"] = float(len(PAIRS))
    ramp = np.tile(np.arange(0, 256, 4, dtype=np.uint8), (48, 1))
    return {"figures": {"heat<map>": png(ramp), "trace": png(ramp.T.copy() // 2),
                        "not_png": np.arange(8, dtype=np.uint8)},
            "metrics": m}


def pictures(base, offset, letter):
    img = np.full((40, 60), int(offset * 40), np.uint8)
    img[10:30, 20:40] = 255
    return {"figures": {f"deform_{letter}": png(img)}, "x": np.asarray(base["x"]) + offset}
'''


def _report_project(toy: Path) -> Path:
    (toy / "toy" / "graph.py").write_text((toy / "toy" / "graph.py").read_text() + GRAPH)
    (toy / "toy" / "study.py").write_text(STUDY)
    return toy


def _referenced(index: Path) -> list[str]:
    return re.findall(r"<img src='([^']+)'", index.read_text())


def _rows(page: str, row: str) -> str:
    """The cells of every table row labelled `row` (a pair appears in each of its pivots)."""
    return "".join(re.findall(rf"<tr[^>]*><th>{re.escape(row)}</th>(.*?)</tr>", page))


def test_pivot_picks_best_per_metric_in_its_direction():
    metrics = {"s/B_A/m2m/fid": 40.0, "s/B_A/before/fid": 90.0,
               "s/A_B/m2m/fid": 55.0, "s/A_B/before/fid": 50.0,
               "s/A_B/genforce/mae_fz": 0.2, "s/A_B/oracle/mae_fz": 0.1,
               "s/A_B/genforce/r2_fz": 0.7, "s/A_B/oracle/r2_fz": 0.6,
               "s/mean/m2m/fid": 47.5, "s/mean/before/fid": 70.0,
               "s/A10_B/m2m/fid": 1.0, "s/A2_B/m2m/fid": 2.0,
               "s/A_B/kid": 0.01, "s/deep/a/b/c": 3.0}
    tables, rest = pivots(metrics)
    assert rest == {"s/A_B/kid": 0.01, "s/deep/a/b/c": 3.0}
    images, forces = sorted(tables, key=lambda t: len(t.metrics))
    assert images.methods == ["before", "m2m"] and images.metrics == ["fid"]
    assert images.rows == ["A2_B", "A10_B", "A_B", "B_A", MEAN_ROW]  # natural order, mean last
    assert ("A_B", "before", "fid") in images.best and ("A_B", "m2m", "fid") not in images.best
    assert ("B_A", "m2m", "fid") in images.best
    assert ("A2_B", "m2m", "fid") not in images.best  # one method only: nothing to compare
    assert forces.methods == ["genforce", "oracle"] and forces.metrics == ["mae_fz", "r2_fz"]
    assert forces.best == {("A_B", "oracle", "mae_fz"), ("A_B", "genforce", "r2_fz")}
    assert [fmt(v) for v in (51.234567, 0.0123456, 123456.7, 2.0, 0.0, float("nan"))] == \
        ["51.23", "0.01235", "123457", "2", "0", "nan"]


def test_report_from_store_alone_drops_stale_figures_and_lists_missing(toy, tmp_path):
    proj = _report_project(toy)
    out = tmp_path / "report"
    run_json(proj)
    cli(proj, "report", "--out", str(out))
    first = _referenced(out / "index.html")
    page = (out / "index.html").read_text()
    assert len(first) == 4 and all((out / src).is_file() for src in first)  # 2 study + 2 pictures
    assert "heat&lt;map&gt;" in page and "<map>" not in page
    assert "<script" not in page and not re.search(r"(src|href)=['\"]?(https?:)?//", page)  # offline
    assert "figures/not_png is not a PNG image" in page
    assert page.index("id='ns-study'") < page.index("id='ns-toy'") < page.index("id='data'")
    best = re.findall(r"<td class='num best' title='study/Array1_Array2/(\w+)/(\w+) = [^']*'>([^<]*)<",
                      _rows(page, "Array1_Array2"))
    assert sorted(best) == [("genforce", "mae_fz", "0.125"), ("m2m", "fid", "51.23"), ("source_only", "r2_fz", "0.95")]
    assert "<tr class='mean'><th>mean</th>" in page

    run_json(proj, "-p", "scale=3.0")  # new study key: new figure files
    cli(proj, "report", "--out", str(out), "-p", "scale=3.0")
    second = _referenced(out / "index.html")
    study_old = {s for s in first if "heat" in s or "trace" in s}
    assert len(second) == 4 and not study_old & set(second)
    assert all((out / src).is_file() for src in second)
    assert not any((out / s).exists() for s in study_old)  # removed, not just unreferenced

    for p in (proj / "artifacts" / "objects").glob("*.h5"):  # report of a store with nothing left
        p.unlink()
    t0 = time.time()
    cli(proj, "report", "--out", str(out), "-p", "scale=3.0")
    page = (out / "index.html").read_text()
    assert _referenced(out / "index.html") == [] and not list((out / "figures").glob("*.png"))
    assert page.count("<tr class=stale>") == 9 and "9 nodes are not built" in page
    assert time.time() - t0 < 30


def test_report_page_in_headless_chromium(toy, tmp_path):
    binary = find_chromium()
    if binary is None:
        pytest.skip("no chromium binary ($CHROMIUM, or chromium / chromium-browser / google-chrome on PATH); "
                    "install it with: apt-get install -y chromium")
    proj = _report_project(toy)
    out = tmp_path / "report"
    run_json(proj)
    cli(proj, "report", "--out", str(out))
    with Browser.launch(binary, tmp_path / "chromium-profile") as browser:
        page = browser.open((out / "index.html").resolve().as_uri())
        images = page.evaluate("""(async () => {
            const imgs = [...document.images];
            imgs.forEach(i => { i.loading = 'eager'; });   // lazy images below the fold too
            await Promise.all(imgs.map(i => i.decode().catch(() => null)));
            return imgs.map(i => ({src: i.getAttribute('src'), complete: i.complete, width: i.naturalWidth}));
        })()""")
        cell = page.evaluate("document.querySelector(\"td[title^='study/Array1_Array2/m2m/fid ']\").textContent")
        best = page.evaluate("[...document.querySelector('table.pivot tbody tr').querySelectorAll('td.best')]"
                             ".map(td => td.title.split(' = ')[0])")
        mean_weight = page.evaluate("getComputedStyle(document.querySelector('tr.mean td')).fontWeight")
        pivot_rows = page.evaluate("document.querySelectorAll('table.pivot')[0].tBodies[0].rows.length")
        shot = page.screenshot(tmp_path / "report-screenshot.png")
        errors = page.errors
    assert errors == []
    assert len(images) == 4 and all(i["complete"] and i["width"] > 0 for i in images), images
    assert cell == "51.23"
    assert best == ["study/Array1_Array2/m2m/fid"]  # fid: lower is better
    assert pivot_rows in (12, 13)  # 12 pairs (+ mean in the image-metric table)
    assert int(mean_weight) >= 700
    assert shot.read_bytes().startswith(b"\x89PNG") and shot.stat().st_size > 10_000
    if os.environ.get("PIPELINE_TEST_OUTPUT"):
        dest = Path(os.environ["PIPELINE_TEST_OUTPUT"])
        dest.mkdir(parents=True, exist_ok=True)
        shot = Path(shutil.copy(shot, dest / "report-screenshot.png"))
    print(f"report screenshot: {shot}")


def test_an_on_demand_node_is_shown_once_built(toy, tmp_path):
    """An on-demand node (like the ablation) is left out of `pipeline run`; once run by name,
    the report shows its table, and it drops out again when its params change."""
    graph = toy / "toy" / "graph.py"
    graph.write_text(graph.read_text() + '\nGRAPH.node("extra", "toy.extra:extra", inputs={"summary": "summary"},'
                     ' params={"scale": "scale"}, on_demand=True)\n')
    (toy / "toy" / "extra.py").write_text(
        'def extra(summary, scale):\n'
        '    return {"attrs": {"report_tables": [{"title": "extra table", "header": ["a", "b"],'
        ' "rows": [["x", scale]]}]}, "metrics": {"extra/x": scale}}\n')
    out = tmp_path / "report"
    run_json(toy)
    cli(toy, "report", "--out", str(out))
    assert "extra table" not in (out / "index.html").read_text()
    run_json(toy, "extra")
    cli(toy, "report", "--out", str(out))
    assert "extra table" in (out / "index.html").read_text()
    cli(toy, "report", "--out", str(out), "-p", "scale=5.0")
    assert "extra table" not in (out / "index.html").read_text()
