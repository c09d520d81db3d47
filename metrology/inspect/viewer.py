"""The inspection report's interactive 3-D view: a point renderer in plain JavaScript on a canvas.

The page opens from disk with no server and no network: the cloud (a seeded subsample of at
most :data:`VIEWER_MAX_POINTS` points) is embedded as base64 ``float32`` positions, ``uint8``
colours and ``float32`` deviations; the nominal's feature edges as ``float32`` segments. The
script projects the points orthographically into a z-buffer every frame (nearest point wins
each pixel), draws the nominal's edges faintly on top, rotates on drag, pans on shift-drag or
right-drag, zooms on the wheel and reads out the deviation of the point under the pointer.

The same view angles (:data:`VIEWS`) and projection (:func:`project`) give the report's static
pictures, so the pictures and the viewer's buttons show the part the same way.
"""

from __future__ import annotations

import base64
import html
import json
import math

import numpy as np
from numpy.typing import NDArray

from scanner.formats.meshes import TriangleMesh

__all__ = [
    "VIEWER_MAX_POINTS",
    "VIEWS",
    "cloud_viewer_html",
    "feature_edges",
    "project",
    "rasterise",
    "shade",
]

#: At most this many points go into the page (a seeded random subsample of bigger clouds).
VIEWER_MAX_POINTS = 60_000

#: Shading: a point facing the eye keeps its colour, one seen edge-on this share of it.
SHADE_FLOOR = 0.55

#: At most this many nominal edges go into the page and the pictures.
MAX_EDGES = 30_000

#: Named views: (yaw, pitch) in degrees; world z up. Yaw turns the part about z, pitch raises
#: the eye (90 looks straight down). ``iso`` looks from front-right-above like the other
#: reports' pictures.
VIEWS: dict[str, tuple[float, float]] = {
    "iso": (-31.0, 35.0),
    "top": (0.0, 90.0),
    "front": (0.0, 0.0),
    "side": (-90.0, 0.0),
    "rear iso": (149.0, 35.0),
}


def project(points: NDArray, yaw_deg: float, pitch_deg: float) -> NDArray[np.float64]:
    """Orthographic view coordinates of ``points``.

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        World points (z up), mm.
    yaw_deg, pitch_deg : float
        The view (see :data:`VIEWS`).

    Returns
    -------
    ndarray, shape (N, 3)
        Screen right, screen up and depth towards the eye, mm.
    """
    p = np.asarray(points, dtype=np.float64)
    a, e = math.radians(yaw_deg), math.radians(pitch_deg)
    x1 = math.cos(a) * p[:, 0] - math.sin(a) * p[:, 1]
    y1 = math.sin(a) * p[:, 0] + math.cos(a) * p[:, 1]
    z1 = p[:, 2]
    up = math.cos(e) * z1 + math.sin(e) * y1
    depth = math.sin(e) * z1 - math.cos(e) * y1
    return np.column_stack([x1, up, depth])


def shade(
    colours: NDArray, normals: NDArray, yaw_deg: float, pitch_deg: float
) -> NDArray[np.uint8]:
    """Colours ``(N, 3)`` uint8 darkened by how obliquely their normals ``(N, 3)`` face the eye.

    The same shading as the viewer's: ``SHADE_FLOOR + (1 - SHADE_FLOOR) |n . eye|``.
    """
    towards_eye = np.abs(project(normals, yaw_deg, pitch_deg)[:, 2])
    factor = SHADE_FLOOR + (1.0 - SHADE_FLOOR) * np.clip(towards_eye, 0.0, 1.0)
    return (np.asarray(colours, dtype=np.float64) * factor[:, None]).astype(np.uint8)


def feature_edges(mesh: TriangleMesh, angle_deg: float = 30.0) -> NDArray[np.float64]:
    """The edges a drawing of the mesh shows: boundaries and creases.

    Parameters
    ----------
    mesh : TriangleMesh
    angle_deg : float
        An edge shared by two faces is a crease when their normals differ by more than this.

    Returns
    -------
    ndarray, shape (E, 2, 3)
        End points of the edges, the mesh's frame, mm (at most :data:`MAX_EDGES`, the longest
        kept).
    """
    tri = np.asarray(mesh.triangles, dtype=np.int64)
    if len(tri) == 0:
        return np.zeros((0, 2, 3))
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    faces = np.tile(np.arange(len(tri)), 3)
    unique, inverse, counts = np.unique(edges, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    normals = mesh.face_normals()
    first = faces[order[starts]]
    second = faces[order[np.minimum(starts + 1, len(order) - 1)]]
    cos_limit = math.cos(math.radians(angle_deg))
    crease = np.einsum("ij,ij->i", normals[first], normals[second]) < cos_limit
    keep = (counts != 2) | crease
    segments = mesh.vertices[unique[keep]]
    if len(segments) > MAX_EDGES:
        length = np.linalg.norm(segments[:, 1] - segments[:, 0], axis=1)
        segments = segments[np.argsort(-length)[:MAX_EDGES]]
    return segments


def rasterise(
    view: NDArray,
    colours: NDArray,
    box: tuple[float, float, float, float],
    pixels: tuple[int, int] = (560, 420),
) -> tuple[NDArray[np.uint8], tuple[float, float, float, float]]:
    """A z-buffered picture of view coordinates ``(N, 3)`` inside ``box`` (x0, x1, y0, y1).

    Returns the RGB image ``(H, W, 3)`` (nearest point wins each pixel, 2 x 2 pixel points) and
    its extent in view coordinates (the box, grown to whole pixels).
    """
    x0, x1, y0, y1 = box
    s = min(pixels[0] / max(x1 - x0, 1e-9), pixels[1] / max(y1 - y0, 1e-9))
    w, h = max(int(np.ceil((x1 - x0) * s)), 1), max(int(np.ceil((y1 - y0) * s)), 1)
    u = np.floor((view[:, 0] - x0) * s).astype(np.int64)
    v = np.floor((y1 - view[:, 1]) * s).astype(np.int64)
    offsets = ((0, 0), (1, 0), (0, 1), (1, 1))
    uu = np.concatenate([u + du for du, _ in offsets])
    vv = np.concatenate([v + dv for _, dv in offsets])
    depth = np.tile(view[:, 2], len(offsets))
    which = np.tile(np.arange(len(view)), len(offsets))
    inside = (uu >= 0) & (uu < w) & (vv >= 0) & (vv < h)
    pixel = vv[inside] * w + uu[inside]
    order = np.lexsort((-depth[inside], pixel))
    winner = order[np.unique(pixel[order], return_index=True)[1]]
    image = np.full((h * w, 3), 255, np.uint8)
    image[pixel[winner]] = colours[which[inside][winner]]
    return image.reshape(h, w, 3), (x0, x0 + w / s, y1 - h / s, y1)


def _b64(array: NDArray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")


_VIEWER_CSS = """
.viewer { position: relative; border: 1px solid var(--line); background: #fff;
          display: inline-block; max-width: 100%; }
.viewer canvas { display: block; width: 100%; height: auto; cursor: grab; touch-action: none; }
.viewer .bar { display: flex; flex-wrap: wrap; gap: 6px 14px; align-items: center;
               padding: 6px 10px; border-top: 1px solid var(--line); background: #f7f8fa;
               font-size: 12.5px; }
.viewer button { font: inherit; padding: 1px 8px; border: 1px solid var(--line);
                 border-radius: 4px; background: #fff; cursor: pointer; }
.viewer .readout { font-family: "DejaVu Sans Mono", Menlo, Consolas, monospace;
                   color: var(--ink); min-width: 22em; }
.legend { display: flex; align-items: center; gap: 8px; font-size: 12px; padding: 6px 10px; }
.legend .ramp { position: relative; width: 320px; height: 14px; border: 1px solid #888; }
.legend .tick { position: absolute; top: -3px; width: 0; height: 18px;
                border-left: 1.5px solid #222; }
.legend .swatch { display: inline-block; width: 14px; height: 14px; border: 1px solid #888;
                  vertical-align: middle; }
"""

# The renderer. Placeholders: __ID__ (element id) and __DATA__ (JSON with base64 arrays).
_VIEWER_JS = """
(function () {
  "use strict";
  var D = __DATA__;
  var root = document.getElementById("__ID__");
  var canvas = root.querySelector("canvas");
  var ctx = canvas.getContext("2d");
  var readout = root.querySelector(".readout");
  function bytes(s) {
    var bin = atob(s), out = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
    return out.buffer;
  }
  var P = new Float32Array(bytes(D.points)), C = new Uint8Array(bytes(D.colours));
  var V = new Float32Array(bytes(D.deviation)), F = new Uint8Array(bytes(D.outlier));
  var E = new Float32Array(bytes(D.edges));
  var N = new Int8Array(bytes(D.normals)), shaded = N.length === 3 * V.length;
  var n = V.length, W = canvas.width, H = canvas.height;
  var zbuf = new Float32Array(W * H), ibuf = new Int32Array(W * H);
  var image = ctx.createImageData(W, H);
  var deg = Math.PI / 180;
  var st = { yaw: D.views.iso[0] * deg, pitch: D.views.iso[1] * deg, zoom: 1, px: 0, py: 0,
             size: 2, edges: true, outliers: true };
  var pending = false;
  function rot() {
    var ca = Math.cos(st.yaw), sa = Math.sin(st.yaw), ce = Math.cos(st.pitch),
        se = Math.sin(st.pitch);
    // rows: screen right, screen up, depth towards the eye (world z up)
    return [ca, -sa, 0, se * sa, se * ca, ce, -ce * sa, -ce * ca, se];
  }
  function scale() { return st.zoom * 0.46 * Math.min(W, H) / D.radius; }
  function draw() {
    pending = false;
    var r = rot(), s = scale(), cx = W / 2 + st.px, cy = H / 2 + st.py, k = st.size;
    var px = image.data;
    zbuf.fill(-Infinity); ibuf.fill(-1);
    for (var q = 0; q < px.length; q += 4) { px[q] = 255; px[q + 1] = 255; px[q + 2] = 255;
                                             px[q + 3] = 255; }
    for (var i = 0; i < n; i++) {
      if (F[i] && !st.outliers) continue;
      var x = P[3 * i], y = P[3 * i + 1], z = P[3 * i + 2];
      var u = (cx + s * (r[0] * x + r[1] * y + r[2] * z)) | 0;
      var v = (cy - s * (r[3] * x + r[4] * y + r[5] * z)) | 0;
      var d = r[6] * x + r[7] * y + r[8] * z, f = 1;
      if (shaded && !F[i]) {
        f = SHADE_FLOOR + (1 - SHADE_FLOOR) / 127 *
            Math.abs(r[6] * N[3 * i] + r[7] * N[3 * i + 1] + r[8] * N[3 * i + 2]);
      }
      for (var a = 0; a < k; a++) {
        var yy = v + a; if (yy < 0 || yy >= H) continue;
        for (var b = 0; b < k; b++) {
          var xx = u + b; if (xx < 0 || xx >= W) continue;
          var o = yy * W + xx;
          if (d > zbuf[o]) {
            zbuf[o] = d; ibuf[o] = i;
            px[4 * o] = f * C[3 * i]; px[4 * o + 1] = f * C[3 * i + 1];
            px[4 * o + 2] = f * C[3 * i + 2];
          }
        }
      }
    }
    ctx.putImageData(image, 0, 0);
    if (st.edges && E.length) {
      ctx.strokeStyle = "rgba(40, 44, 52, 0.45)"; ctx.lineWidth = 1; ctx.beginPath();
      for (var j = 0; j < E.length; j += 3) {
        var sx = cx + s * (r[0] * E[j] + r[1] * E[j + 1] + r[2] * E[j + 2]);
        var sy = cy - s * (r[3] * E[j] + r[4] * E[j + 1] + r[5] * E[j + 2]);
        if ((j / 3) % 2 === 0) ctx.moveTo(sx, sy); else ctx.lineTo(sx, sy);
      }
      ctx.stroke();
    }
    drawAxes(r);
  }
  function drawAxes(r) {
    var ox = 38, oy = H - 38, names = ["x", "y", "z"], cols = ["#c0392b", "#27ae60", "#2e6fd0"];
    ctx.lineWidth = 2; ctx.font = "12px sans-serif";
    for (var a = 0; a < 3; a++) {
      var ex = ox + 26 * r[a], ey = oy - 26 * r[3 + a];
      ctx.strokeStyle = cols[a]; ctx.fillStyle = cols[a];
      ctx.beginPath(); ctx.moveTo(ox, oy); ctx.lineTo(ex, ey); ctx.stroke();
      ctx.fillText(names[a], ex + 3 * (ex - ox) / 26 - 3, ey + 3 * (ey - oy) / 26 + 4);
    }
  }
  function later() { if (!pending) { pending = true; requestAnimationFrame(draw); } }
  function toCanvas(ev) {
    var b = canvas.getBoundingClientRect();
    return [(ev.clientX - b.left) * W / b.width, (ev.clientY - b.top) * H / b.height];
  }
  var drag = null;
  canvas.addEventListener("pointerdown", function (ev) {
    drag = { x: ev.clientX, y: ev.clientY, pan: ev.shiftKey || ev.button === 2 };
    canvas.setPointerCapture(ev.pointerId); canvas.style.cursor = "grabbing";
  });
  canvas.addEventListener("pointerup", function (ev) {
    drag = null; canvas.releasePointerCapture(ev.pointerId); canvas.style.cursor = "grab";
  });
  canvas.addEventListener("contextmenu", function (ev) { ev.preventDefault(); });
  canvas.addEventListener("pointermove", function (ev) {
    if (drag) {
      var dx = ev.clientX - drag.x, dy = ev.clientY - drag.y;
      drag.x = ev.clientX; drag.y = ev.clientY;
      if (drag.pan) { st.px += dx * W / canvas.clientWidth; st.py += dy * H / canvas.clientHeight; }
      else {
        st.yaw += dx * 0.01;
        st.pitch = Math.max(-Math.PI / 2, Math.min(Math.PI / 2, st.pitch + dy * 0.01));
      }
      later(); return;
    }
    var c = toCanvas(ev), best = -1;
    for (var a = -3; a <= 3 && best < 0; a++) for (var b = -3; b <= 3; b++) {
      var xx = (c[0] | 0) + b, yy = (c[1] | 0) + a;
      if (xx >= 0 && xx < W && yy >= 0 && yy < H && ibuf[yy * W + xx] >= 0) {
        best = ibuf[yy * W + xx]; break;
      }
    }
    if (best < 0) { readout.textContent = "\\u00a0"; return; }
    var dev = V[best], text = Math.abs(dev) < 0.0005 ? "0.000" :
      (dev > 0 ? "+" : "") + dev.toFixed(3);
    readout.textContent = "deviation " + text + " mm" +
      (F[best] ? " (outlier)" : "") + " at (" + [0, 1, 2].map(function (m) {
        return (P[3 * best + m] + D.centre[m]).toFixed(2); }).join(", ") + ") mm";
  });
  canvas.addEventListener("wheel", function (ev) {
    ev.preventDefault();
    st.zoom = Math.max(0.2, Math.min(50, st.zoom * Math.exp(-ev.deltaY * 0.0015)));
    later();
  }, { passive: false });
  canvas.addEventListener("dblclick", function () { setView("iso"); });
  function setView(name) {
    st.yaw = D.views[name][0] * deg; st.pitch = D.views[name][1] * deg;
    st.zoom = 1; st.px = 0; st.py = 0; later();
  }
  root.querySelectorAll("button[data-view]").forEach(function (btn) {
    btn.addEventListener("click", function () { setView(btn.getAttribute("data-view")); });
  });
  root.querySelector("input.edges").addEventListener("change", function (ev) {
    st.edges = ev.target.checked; later(); });
  root.querySelector("input.outliers").addEventListener("change", function (ev) {
    st.outliers = ev.target.checked; later(); });
  root.querySelector("select.size").addEventListener("change", function (ev) {
    st.size = parseInt(ev.target.value, 10); later(); });
  canvas.setAttribute("data-points", String(n));
  draw();
  canvas.setAttribute("data-drawn", "1");
})();
"""


def cloud_viewer_html(
    points: NDArray,
    deviation_mm: NDArray,
    colours: NDArray,
    outlier: NDArray,
    edges: NDArray,
    legend_html: str = "",
    *,
    normals: NDArray | None = None,
    max_points: int = VIEWER_MAX_POINTS,
    seed: int = 0,
    element_id: str = "inspect-viewer",
    size_px: tuple[int, int] = (1100, 640),
) -> str:
    """The interactive view as an HTML fragment (style, canvas, controls, legend, script).

    Parameters
    ----------
    points : ndarray, shape (N, 3)
        The cloud, world z up, mm.
    deviation_mm : ndarray, shape (N,)
        Shown in the read-out under the pointer.
    colours : ndarray, shape (N, 3), uint8
        RGB of each point.
    outlier : ndarray, shape (N,), bool
        Points the "outliers" box hides.
    edges : ndarray, shape (E, 2, 3)
        Segments drawn faintly over the points (the nominal's feature edges), mm.
    legend_html : str
        HTML shown under the controls (the colour scale).
    normals : ndarray, shape (N, 3), optional
        Unit normals of the points: shades them by how they face the eye (none: flat colours).
    max_points : int
        Bigger clouds are subsampled (seeded) to this many points.
    seed : int
        Seed of the subsample.
    element_id : str
        The ``id`` of the viewer's element (unique in the page).
    size_px : (int, int)
        The canvas's pixel size; the page scales it to its width.

    Returns
    -------
    str
        HTML with inline CSS and JavaScript only (no external resources).
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points: expected (N, 3), got {p.shape}")
    count = len(p)
    dev = np.asarray(deviation_mm, dtype=np.float32)
    col = np.asarray(colours, dtype=np.uint8)
    out = np.asarray(outlier, dtype=bool)
    if dev.shape != (count,) or col.shape != (count, 3) or out.shape != (count,):
        raise ValueError(
            f"deviation_mm, colours, outlier: expected ({count},), ({count}, 3), ({count},), "
            f"got {dev.shape}, {col.shape}, {out.shape}"
        )
    nrm = np.zeros((0, 3)) if normals is None else np.asarray(normals, dtype=np.float64)
    if normals is not None and nrm.shape != (count, 3):
        raise ValueError(f"normals: expected ({count}, 3), got {nrm.shape}")
    if max_points < 1:
        raise ValueError(f"max_points: expected >= 1, got {max_points}")
    if count > max_points:
        pick = np.sort(np.random.default_rng(seed).choice(count, max_points, replace=False))
        p, dev, col, out = p[pick], dev[pick], col[pick], out[pick]
        nrm = nrm[pick] if len(nrm) else nrm
    seg = np.asarray(edges, dtype=np.float64).reshape(-1, 2, 3)
    everything = np.concatenate([p, seg.reshape(-1, 3)]) if len(seg) else p
    if len(everything):
        lower, upper = everything.min(axis=0), everything.max(axis=0)
    else:
        lower = upper = np.zeros(3)
    centre = 0.5 * (lower + upper)
    radius = max(0.5 * float(np.linalg.norm(upper - lower)), 1e-6)
    data = {
        "points": _b64((p - centre).astype("<f4")),
        "colours": _b64(col),
        "deviation": _b64(dev.astype("<f4")),
        "outlier": _b64(out.astype(np.uint8)),
        "normals": _b64(np.round(np.clip(nrm, -1.0, 1.0) * 127).astype(np.int8)),
        "edges": _b64((seg.reshape(-1, 3) - centre).astype("<f4")),
        "centre": [float(c) for c in centre],
        "radius": radius,
        "views": VIEWS,
    }
    # JSON inside <script>: no "</" may close the element early.
    payload = json.dumps(data).replace("</", "<\\/")
    script = (
        _VIEWER_JS.replace("__DATA__", payload)
        .replace("__ID__", element_id)
        .replace("SHADE_FLOOR", repr(SHADE_FLOOR))
    )
    buttons = "".join(
        f'<button type="button" data-view="{html.escape(name)}">{html.escape(name)}</button>'
        for name in VIEWS
    )
    shown = (
        f"{len(p):,} of {count:,} points" if count > len(p) else f"all {count:,} points"
    ).replace(",", "\u2009")
    return (
        f"<style>{_VIEWER_CSS}</style>\n"
        f'<div class="viewer" id="{html.escape(element_id)}">\n'
        f'<canvas width="{int(size_px[0])}" height="{int(size_px[1])}" '
        f'aria-label="interactive 3-D view of the cloud"></canvas>\n'
        f'<div class="bar">{buttons}'
        '<label><input type="checkbox" class="edges" checked> nominal edges</label>'
        '<label><input type="checkbox" class="outliers" checked> outliers</label>'
        '<label>point size <select class="size"><option value="1">1</option>'
        '<option value="2" selected>2</option><option value="3">3</option>'
        '<option value="4">4</option></select></label>'
        f'<span class="note">{shown}; drag: rotate, shift-drag: pan, wheel: zoom, '
        "double-click: reset</span>"
        '<span class="readout">\u00a0</span></div>\n'
        f"{legend_html}"
        f"<script>{script}</script>\n</div>\n"
    )
