"""Self-contained HTML pages of drgan's reports (the pipeline's report.html, analyze's statistics.html): one file that
opens in any browser, offline, anywhere it is copied to. The Markdown report rendered (markdown-it-py, CommonMark
with tables), its figures embedded as data URIs, the overlays browsable image by image, the particle table sortable
by any column (a few lines of inline JavaScript; no network, no library loaded)."""

from __future__ import annotations

import base64
import html
import io
import json
import re
from collections.abc import Sequence
from pathlib import Path

MAX_GALLERY = 200  # overlays embedded in one page (the rest: their folder)
GALLERY_WIDTH = 900  # px: overlays are embedded at most this wide, as JPEG (a page of 40 fields stays a few MB)

STYLE = """
body{font-family:system-ui,sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222;line-height:1.45}
table{border-collapse:collapse;margin:.8em 0;font-size:.92em}th,td{border:1px solid #ccc;padding:.25em .55em}
th{background:#f2f2f2;cursor:pointer;user-select:none}th.sorted-asc:after{content:" \\25B2"}
th.sorted-desc:after{content:" \\25BC"}code,pre{background:#f6f6f6}pre{padding:.6em;overflow-x:auto}
img.figure{max-width:100%;border:1px solid #ddd;margin:.4em 0}
.gallery img{width:min(100%,900px);border:1px solid #ddd;image-rendering:pixelated}
.gallery button{margin-right:.5em}.scroll{max-height:32em;overflow:auto}
"""

SORT_SCRIPT = """
function drganTable(id, rows, columns){
  const box=document.getElementById(id); const table=document.createElement('table');
  const head=table.createTHead().insertRow(); let key=null, dir=1;
  columns.forEach((c)=>{const th=document.createElement('th'); th.textContent=c; th.onclick=()=>{
    dir=(key===c)?-dir:1; key=c; rows.sort((a,b)=>{const x=a[c], y=b[c];
      const nx=parseFloat(x), ny=parseFloat(y);
      const r=(!isNaN(nx)&&!isNaN(ny))?nx-ny:String(x).localeCompare(String(y)); return dir*r;});
    head.querySelectorAll('th').forEach(h=>h.className=''); th.className=dir>0?'sorted-asc':'sorted-desc'; fill();};
    head.appendChild(th);});
  const body=table.createTBody();
  function fill(){body.innerHTML=''; rows.forEach(r=>{const tr=body.insertRow();
    columns.forEach(c=>{tr.insertCell().textContent=r[c]===undefined?'':r[c];});});}
  fill(); box.appendChild(table);
}
function drganGallery(id){
  const g=document.getElementById(id); const pick=g.querySelector('select'); const imgs=g.querySelectorAll('img');
  function show(i){imgs.forEach((im,k)=>im.style.display=(k===i)?'block':'none'); pick.selectedIndex=i;}
  pick.onchange=()=>show(pick.selectedIndex);
  g.querySelector('.prev').onclick=()=>show((pick.selectedIndex+imgs.length-1)%imgs.length);
  g.querySelector('.next').onclick=()=>show((pick.selectedIndex+1)%imgs.length);
  show(0);
}
"""


def data_uri(path: Path, max_width: int | None = None) -> str:
    """A PNG (or, downscaled to ``max_width``, a JPEG) as a data URI."""
    if max_width is None:
        return "data:image/png;base64," + base64.b64encode(Path(path).read_bytes()).decode()
    from PIL import Image

    with Image.open(path) as image:
        image = image.convert("RGB")
        if image.width > max_width:
            image = image.resize((max_width, round(image.height * max_width / image.width)))
        buf = io.BytesIO()
        image.save(buf, format="JPEG", quality=85)
    return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode()


def markdown_html(text: str, base: Path) -> str:
    """Markdown -> HTML; every local image it shows (``![...](x.png)``) embedded, and every link to a local PNG
    followed by that figure, embedded (so the page holds what the Markdown only points to)."""
    from markdown_it import MarkdownIt

    body = MarkdownIt("commonmark").enable("table").render(text)

    def embed_img(match: re.Match) -> str:
        src = html.unescape(match.group(2))
        path = base / src
        if src.startswith(("http:", "https:", "data:")) or not path.is_file():
            return match.group(0)
        return f'{match.group(1)}"{data_uri(path)}" class="figure"'

    body = re.sub(r'(<img src=)"([^"]+)"', embed_img, body)
    paragraphs = []
    for block in re.split(r"(?<=</p>)\n", body):
        linked = [html.unescape(h) for h in re.findall(r'<a href="([^"]+)"', block)]
        figures = [h for h in dict.fromkeys(linked) if h.lower().endswith(".png") and (base / h).is_file()]
        extra = "".join(
            f'<figure><img class="figure" src="{data_uri(base / f)}" alt="{html.escape(f)}">'
            f"<figcaption>{html.escape(f)}</figcaption></figure>"
            for f in figures
        )
        paragraphs.append(block + extra)
    return "\n".join(paragraphs)


def gallery(element_id: str, images: Sequence[Path], title: str) -> str:
    """The images one at a time, with a list and previous / next buttons (the first ``MAX_GALLERY``)."""
    images = list(images)
    if not images:
        return ""
    shown = images[:MAX_GALLERY]
    options = "".join(f"<option>{html.escape(p.stem)}</option>" for p in shown)
    pictures = "".join(
        f'<img src="{data_uri(p, GALLERY_WIDTH)}" alt="{html.escape(p.stem)}" style="display:none">' for p in shown
    )
    more = (
        f"<p>{len(images) - len(shown)} more in {html.escape(str(images[0].parent))}.</p>"
        if len(images) > len(shown)
        else ""
    )
    return (
        f'<h2>{html.escape(title)}</h2><div class="gallery" id="{element_id}"><p><button class="prev">previous'
        f'</button><select>{options}</select> <button class="next">next</button></p>{pictures}</div>{more}'
        f"<script>drganGallery({json.dumps(element_id)});</script>"
    )


def sortable_table(element_id: str, rows: Sequence[dict], columns: Sequence[str], title: str) -> str:
    """The rows as a table that sorts by the column whose header is clicked (numbers as numbers)."""
    if not rows:
        return ""
    data = json.dumps([{c: r.get(c, "") for c in columns} for r in rows]).replace("</", "<\\/")
    return (
        f'<h2>{html.escape(title)}</h2><p>{len(rows)} rows; click a column to sort by it.</p><div class="scroll" '
        f'id="{element_id}"></div><script>drganTable({json.dumps(element_id)}, {data}, {json.dumps(list(columns))});'
        "</script>"
    )


def page(title: str, body: str) -> str:
    return (
        f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
        f"<style>{STYLE}</style><script>{SORT_SCRIPT}</script></head><body>\n{body}\n</body></html>\n"
    )


def read_csv_rows(path: Path) -> tuple[list[dict], list[str]]:
    import csv

    if not path.is_file():
        return [], []
    reader = csv.DictReader(io.StringIO(path.read_text()))
    rows = list(reader)
    return rows, list(reader.fieldnames or [])


def particles_and_overlays(folder: Path) -> str:
    """An analyze (or evaluate) folder's overlays gallery and particle table, as page sections."""
    rows, columns = read_csv_rows(folder / "particles.csv")
    shown = [c for c in columns if not c.startswith("bbox_")] or columns
    rows = [{c: _short(r.get(c, "")) for c in shown} for r in rows]
    return gallery("overlays", sorted((folder / "overlays").glob("*.png")), "Overlays, image by image") + (
        sortable_table("particles", rows, shown, "Particles (particles.csv)")
    )


def _short(value: str) -> str:
    """A CSV cell for reading: a float to 4 significant digits, anything else as it is."""
    if "." not in value:
        return value
    try:
        return f"{float(value):.4g}"
    except ValueError:
        return value
