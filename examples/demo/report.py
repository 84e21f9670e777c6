"""report.html for a demo run: one self-contained page (images inlined as data URIs, charts as inline
SVG, no server and no network) with the held-out metrics, the training curve, held-out views,
closed-loop frames and step latencies.

The page checks itself when it loads: every image decoded and no script error. It writes the
result into <body data-selfcheck="ok|failed: ..."> so a headless browser can verify the page.
"""
import base64
import html
import os
import re

import numpy as np

import media


def _data_uri(data, mime):
    return f"data:{mime};base64," + base64.b64encode(data).decode("ascii")


def _img(data, mime, alt, cls=""):
    return f'<img class="{cls}" alt="{html.escape(alt)}" src="{_data_uri(data, mime)}">'


def svg_chart(series, x_label, y_label, width=640, height=220, vlines=()):
    """A line chart: series = [(name, colour, xs, ys)], shared axes; vlines = [(x, label)]."""
    pad_l, pad_r, pad_t, pad_b = 48, 12, 12, 32
    xs_all = np.concatenate([np.asarray(s[2], float) for s in series if len(s[2])] or [np.zeros(1)])
    ys_all = np.concatenate([np.asarray(s[3], float) for s in series if len(s[3])] or [np.zeros(1)])
    ys_all = ys_all[np.isfinite(ys_all)] if np.isfinite(ys_all).any() else np.zeros(1)
    x0, x1 = float(xs_all.min()), float(xs_all.max()) or 1.0
    y0, y1 = float(ys_all.min()), float(ys_all.max())
    if y1 - y0 < 1e-9:
        y0, y1 = y0 - 1, y1 + 1
    if x1 - x0 < 1e-9:
        x1 = x0 + 1

    def px(x):
        return pad_l + (x - x0) / (x1 - x0) * (width - pad_l - pad_r)

    def py(y):
        return height - pad_b - (y - y0) / (y1 - y0) * (height - pad_t - pad_b)

    out = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" class="chart">',
           f'<rect x="{pad_l}" y="{pad_t}" width="{width - pad_l - pad_r}" height="{height - pad_t - pad_b}" '
           'fill="#fafafa" stroke="#ccc"/>']
    for frac in (0, 0.5, 1):
        y = y0 + frac * (y1 - y0)
        out.append(f'<text x="{pad_l - 4}" y="{py(y) + 4:.1f}" text-anchor="end" font-size="11">{y:.3g}</text>')
        x = x0 + frac * (x1 - x0)
        out.append(f'<text x="{px(x):.1f}" y="{height - pad_b + 14}" text-anchor="middle" font-size="11">{x:.3g}</text>')
    out.append(f'<text x="{(pad_l + width) / 2}" y="{height - 4}" text-anchor="middle" font-size="12">'
               f'{html.escape(x_label)}</text>')
    out.append(f'<text x="12" y="{(pad_t + height - pad_b) / 2}" font-size="12" text-anchor="middle" '
               f'transform="rotate(-90 12 {(pad_t + height - pad_b) / 2})">{html.escape(y_label)}</text>')
    for x, label in vlines:
        out.append(f'<line x1="{px(x):.1f}" x2="{px(x):.1f}" y1="{pad_t}" y2="{height - pad_b}" stroke="#999" '
                   f'stroke-dasharray="4 3"/><text x="{px(x) + 4:.1f}" y="{pad_t + 12}" font-size="11">'
                   f'{html.escape(label)}</text>')
    for i, (name, colour, xs, ys) in enumerate(series):
        pts = " ".join(f"{px(x):.1f},{py(y):.1f}" for x, y in zip(xs, ys) if np.isfinite(y))
        out.append(f'<polyline fill="none" stroke="{colour}" stroke-width="1.6" points="{pts}"/>')
        out.append(f'<text x="{width - pad_r - 4}" y="{pad_t + 14 + 14 * i}" text-anchor="end" font-size="11" '
                   f'fill="{colour}">{html.escape(name)}</text>')
    out.append("</svg>")
    return "".join(out)


def _smooth(ys, n=10):
    ys = np.asarray(ys, float)
    if len(ys) < n:
        return ys
    return np.convolve(ys, np.ones(n) / n, mode="valid")


def _stem(view_name):
    """DecompositionStem (scene/train/decomposition.cc): the file stem eval writes for a view."""
    stem, ext = os.path.splitext(view_name)
    if not ext or len(ext) > 5:
        stem = view_name
    return re.sub(r"[^A-Za-z0-9_.-]", "_", stem)


def _heldout_views(heldout, decomposition_dir, log_dir, count=3):
    """The worst, median and best held-out view: render | logged image, and the moving-object mask."""
    frames = sorted(heldout["frames"], key=lambda f: f["psnr"])
    picks = [frames[0], frames[len(frames) // 2], frames[-1]][:count] if len(frames) >= 3 else frames
    rows = []
    for f in picks:
        stem = os.path.join(decomposition_dir, _stem(f["name"]))
        if not os.path.isfile(stem + "_full.png"):
            raise FileNotFoundError(f"eval wrote no {stem}_full.png")
        rendered = media.load_rgb(stem + "_full.png")
        logged = media.load_rgb(os.path.join(log_dir, "image_02", "data", f"{f['frame']:010d}.png"))
        pair = media.side_by_side(rendered, logged)
        # The moving-object pixels that PSNR* is measured on, when the log gives a mask.
        mask = ""
        if os.path.isfile(stem + "_mask.png"):
            mask = _img(media.encode(media.load_rgb(stem + "_mask.png"), "JPEG", 80), "image/jpeg",
                        "moving-object pixels", "half")
        dynamic = "" if f.get("psnr_dynamic") is None else f", PSNR* {f['psnr_dynamic']:.2f} dB"
        rows.append(f'<figure>{_img(media.encode(pair, "JPEG", 85), "image/jpeg", "held-out " + f["name"])}{mask}'
                    f'<figcaption>frame {f["frame"]}: PSNR {f["psnr"]:.2f} dB, SSIM {f["ssim"]:.3f}{dynamic}. '
                    f'Rendered (left) and logged (right){"; below, the pixels of moving objects (PSNR*)" if mask else ""}.'
                    f'</figcaption></figure>')
    return "\n".join(rows)


SELF_CHECK = """
<script>
window.__errors = [];
window.addEventListener('error', function (e) {
  var t = e.target;
  window.__errors.push(t && t.tagName ? 'resource ' + t.tagName : 'script: ' + e.message);
}, true);
window.addEventListener('load', function () {
  var bad = [];
  document.querySelectorAll('img').forEach(function (img, i) {
    if (!img.complete || img.naturalWidth === 0) bad.push('image ' + i + ' (' + img.alt + ')');
  });
  var problems = window.__errors.concat(bad);
  document.body.dataset.selfcheck = problems.length ? 'failed: ' + problems.join('; ') : 'ok';
  document.getElementById('selfcheck').textContent =
    problems.length ? 'page check failed: ' + problems.join('; ') : 'page check: ' +
    document.images.length + ' images decoded, no script error';
});
</script>
"""

VIEWER = """
<script>
(function () {
  var frames = document.querySelectorAll('#loop img');
  var slider = document.getElementById('loop-slider');
  var label = document.getElementById('loop-label');
  function show(i) {
    frames.forEach(function (f, k) { f.style.display = k === i ? 'block' : 'none'; });
    label.textContent = frames[i].alt;
  }
  slider.max = frames.length - 1;
  slider.addEventListener('input', function () { show(Number(slider.value)); });
  show(0);
})();
</script>
"""

STYLE = """
body { font-family: sans-serif; margin: 24px auto; padding: 0 12px; max-width: 1260px; color: #222; }
h1 { margin-bottom: 4px; } .sub { color: #666; margin-top: 0; }
.cards { display: flex; flex-wrap: wrap; gap: 12px; }
.card { border: 1px solid #ddd; border-radius: 6px; padding: 10px 14px; min-width: 150px; }
.card b { display: block; font-size: 22px; }
figure { margin: 12px 0; } figure img { max-width: 100%; display: block; } img.half { max-width: 66%; }
figcaption { color: #555; font-size: 13px; }
table { border-collapse: collapse; font-size: 13px; } td, th { border: 1px solid #ddd; padding: 3px 8px; text-align: right; }
code { background: #f3f3f3; padding: 1px 4px; } #selfcheck { color: #888; font-size: 12px; }
"""


def write(path, summary, trained, heldout, drove, decomposition_dir, log_dir):
    curve = np.array(trained["curve"], dtype=float)  # wall_s, iteration, loss, psnr, gaussians
    fine_start = [(float(r[0]), "fine stage (field) starts") for r in trained["curve"]
                  if r[1] >= trained["static_iterations"]][:1]
    n = 10
    psnr_chart = svg_chart([("training-view PSNR, mean of 10 logged views", "#1f5fbf", curve[n - 1:, 0] if len(curve) >= n else curve[:, 0],
                             _smooth(curve[:, 3], n))], "training wall time (s)", "PSNR (dB)", vlines=fine_start)
    loss_chart = svg_chart([("loss", "#bf3f1f", curve[:, 0], curve[:, 2])], "training wall time (s)", "loss",
                           vlines=fine_start)
    dec = drove["decisions"]
    t = [(d.time_us - dec[0].time_us) * 1e-6 for d in dec]
    drive_chart = svg_chart([("speed (m/s)", "#1f5fbf", t, [d.speed_mps for d in dec]),
                             ("gap ahead (m, capped at 40)", "#bf7f1f", t, [min(d.gap_m, 40) if d.gap_m is not None else 40 for d in dec]),
                             ("lateral offset (m)", "#3f9f3f", t, [d.lateral_m for d in dec])],
                            "scene time (s)", "planner")
    lat = drove["latency_ms"]
    latency_chart = svg_chart([("step latency (ms)", "#7f3fbf", list(range(len(lat))), lat)], "step", "ms")
    frames = "".join(_img(jpeg, "image/jpeg", f"closed-loop step {i}: t {t[i]:.1f} s, {dec[i].state}, "
                          f"speed {dec[i].speed_mps:.1f} m/s")
                     for i, jpeg in drove["frames"])
    rows = "".join(f"<tr><td>{f['frame']}</td><td>{f['psnr']:.2f}</td><td>{f['ssim']:.3f}</td>"
                   f"<td>{'' if f.get('psnr_dynamic') is None else '%.2f' % f['psnr_dynamic']}</td></tr>"
                   for f in sorted(heldout["frames"], key=lambda f: f["frame"]))
    m = heldout["mean"]
    cards = [("held-out PSNR", f"{m['psnr']:.2f} dB"), ("held-out SSIM", f"{m['ssim']:.3f}"),
             ("PSNR* (moving pixels)", "n/a" if m.get("psnr_dynamic") is None else f"{m['psnr_dynamic']:.2f} dB"),
             ("training", f"{summary['train_wall_s'] / 60:.1f} min, {summary['train_iterations']} it"),
             ("Gaussians", f"{summary['gaussians']:,}"), ("scene", "dynamic (field)" if summary["dynamic"] else "static"),
             ("closed-loop steps", str(summary["steps"])),
             ("step p50 / p99", f"{summary['step_p50_ms']:.0f} / {summary['step_p99_ms']:.0f} ms")]
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>streetsim demo report</title>
<style>{STYLE}</style>{SELF_CHECK}</head>
<body data-selfcheck="pending">
<h1>streetsim demo</h1>
<p class="sub">{html.escape(os.path.basename(os.path.normpath(log_dir)))}, preset <code>{html.escape(summary['preset'])}</code>:
trained, evaluated on every 4th frame (held out), served on 127.0.0.1 and driven in a closed loop
through the Python client.</p>
<div class="cards">{''.join(f'<div class="card">{html.escape(k)}<b>{html.escape(v)}</b></div>' for k, v in cards)}</div>

<h2>Training</h2>
<p><code>{html.escape(summary['train_command'])}</code></p>
{psnr_chart}{loss_chart}

<h2>Held-out views</h2>
{_heldout_views(heldout, decomposition_dir, log_dir)}
<details><summary>Every held-out view</summary>
<table><tr><th>frame</th><th>PSNR (dB)</th><th>SSIM</th><th>PSNR* (dB)</th></tr>{rows}</table></details>

<h2>Closed loop</h2>
<p>The planner follows the road of the log, keeps its distance to what the rendered LiDAR shows
ahead in its lane (Intelligent Driver Model) and changes lane to the left when it is held up and
the LiDAR sees the next lane free; lane changes: {summary['lane_changes']} (the next lane was free at
{summary['left_lane_free_steps']} of {summary['steps']} steps). Camera
{summary['camera'][0]}x{summary['camera'][1]} (RGB + depth), LiDAR {summary['lidar'][0]}x{summary['lidar'][1]}.</p>
<input type="range" id="loop-slider" min="0" value="0" step="1" style="width: 100%">
<p id="loop-label"></p>
<div id="loop">{frames}</div>
{drive_chart}{latency_chart}
<p id="selfcheck">page check did not run</p>
{VIEWER}
</body></html>
"""
    with open(path + ".tmp", "w") as f:
        f.write(page)
    os.replace(path + ".tmp", path)
