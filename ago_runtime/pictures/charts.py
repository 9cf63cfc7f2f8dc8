"""Small charts drawn with opencv (no plotting library): learning curves, bars per class, matrices.

- `line_chart(title, series, x_label, y_label, ...)` -> (H, W, 3) uint8 BGR image; each series is
  (name, xs, ys, colour BGR). Axes get round tick values; the legend sits under the title. Save with
  `cv2.imwrite` (ago_runtime.atomic.atomic_path for an atomic write).
- `bar_chart(title, labels, series, marks, ylabel)`: grouped bars, one group per label, each series
  (name, values, colour); `marks` draws those labels in red ((200, 0, 0): an RGB image, save with
  `pictures.render.save_png`).
- `heatmap(title, rows, cols, values)`: a matrix as viridis cells with its names, RGB.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

PALETTE = [(180, 119, 31), (14, 127, 255), (44, 160, 44), (40, 39, 214), (189, 103, 148), (75, 86, 140),
           (194, 119, 227), (127, 127, 127)]   # BGR, the usual ten-colour cycle


def _ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    if hi <= lo:
        hi = lo + 1.0
    raw = (hi - lo) / max(n, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=raw)
    start = math.ceil(lo / step) * step
    out, v = [], start
    while v <= hi + 1e-9 * step:
        out.append(round(v, 10))
        v += step
    return out


def _fmt(v: float) -> str:
    if abs(v) >= 1000:
        return f"{v / 1000:g}k"
    return f"{v:g}"


def line_chart(title: str, series: list[tuple[str, list[float], list[float], tuple[int, int, int]]],
               x_label: str = "", y_label: str = "", width: int = 720, height: int = 420,
               y_range: tuple[float, float] | None = None, log_x: bool = False) -> np.ndarray:
    """Lines with dot markers; `log_x` puts x on a log10 axis (x must be > 0)."""
    img = np.full((height, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    left, right, top, bottom = 70, 20, 60, 55
    xs_all = [x for _, xs, _, _ in series for x in xs]
    ys_all = [y for _, _, ys, _ in series for y in ys if y is not None and np.isfinite(y)]
    if not xs_all or not ys_all:
        cv2.putText(img, f"{title}: no data", (10, 30), font, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
        return img
    fx = (lambda v: math.log10(v)) if log_x else (lambda v: float(v))
    x0, x1 = fx(min(xs_all)), fx(max(xs_all))
    if x1 <= x0:
        x0, x1 = x0 - 1, x1 + 1
    y0, y1 = y_range if y_range is not None else (min(0.0, min(ys_all)), max(ys_all) * 1.1 + 1e-9)

    def px(x, y):
        u = left + (fx(x) - x0) / (x1 - x0) * (width - left - right)
        v = height - bottom - (y - y0) / (y1 - y0) * (height - top - bottom)
        return int(round(u)), int(round(v))

    # axes, grid, ticks
    cv2.rectangle(img, (left, top), (width - right, height - bottom), (0, 0, 0), 1)
    for t in _ticks(y0, y1):
        _, v = px(min(xs_all), t)
        cv2.line(img, (left, v), (width - right, v), (225, 225, 225), 1)
        cv2.putText(img, _fmt(t), (8, v + 4), font, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
    xt = sorted(set(xs_all)) if log_x or len(set(xs_all)) <= 8 else _ticks(min(xs_all), max(xs_all))
    for t in xt:
        u, _ = px(t, y0)
        cv2.line(img, (u, height - bottom), (u, height - bottom + 4), (0, 0, 0), 1)
        label = _fmt(t)
        (w, _), _ = cv2.getTextSize(label, font, 0.4, 1)
        cv2.putText(img, label, (u - w // 2, height - bottom + 18), font, 0.4, (60, 60, 60), 1, cv2.LINE_AA)
    cv2.putText(img, title, (left, 22), font, 0.6, (0, 0, 0), 1, cv2.LINE_AA)
    if x_label:
        (w, _), _ = cv2.getTextSize(x_label, font, 0.45, 1)
        cv2.putText(img, x_label, ((width - w) // 2, height - 12), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    if y_label:
        cv2.putText(img, y_label, (8, top - 10), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    # legend
    lx = left
    for name, _, _, colour in series:
        cv2.line(img, (lx, 40), (lx + 18, 40), colour, 2)
        cv2.putText(img, name, (lx + 22, 44), font, 0.42, (0, 0, 0), 1, cv2.LINE_AA)
        (w, _), _ = cv2.getTextSize(name, font, 0.42, 1)
        lx += w + 40
    # lines
    for _, xs, ys, colour in series:
        pts = [px(x, y) for x, y in zip(xs, ys) if y is not None and np.isfinite(y)]
        for a, b in zip(pts[:-1], pts[1:]):
            cv2.line(img, a, b, colour, 2, cv2.LINE_AA)
        for p in pts:
            cv2.circle(img, p, 4, colour, -1, cv2.LINE_AA)
    return img


BLACK = (30, 30, 30)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def bar_chart(title: str, labels: list[str], series: list[tuple[str, list[float], tuple]], marks: list[bool],
              ylabel: str) -> np.ndarray:
    """Grouped vertical bars, one group per label; `marks` draws the labels that are unknown in red."""
    n, m = len(labels), len(series)
    bw, gap, left, top, H = 14, 14, 60, 50, 260
    W = left + n * (m * bw + gap) + 20
    img = np.full((top + H + 170, W, 3), 255, np.uint8)
    vmax = max([max(s[1]) for s in series if s[1]] + [1e-6])
    cv2.putText(img, title, (10, 24), FONT, 0.6, BLACK, 1, cv2.LINE_AA)
    cv2.line(img, (left, top + H), (W - 10, top + H), BLACK, 1)
    for t in np.linspace(0, vmax, 5):
        y = int(top + H - H * t / vmax)
        cv2.line(img, (left - 4, y), (W - 10, y), (225, 225, 225), 1)
        cv2.putText(img, f"{t:.2f}", (4, y + 4), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, ylabel, (4, top - 10), FONT, 0.4, BLACK, 1, cv2.LINE_AA)
    for i, lab in enumerate(labels):
        x0 = left + i * (m * bw + gap) + gap // 2
        for j, (_name, vals, col) in enumerate(series):
            h = int(H * vals[i] / vmax)
            cv2.rectangle(img, (x0 + j * bw, top + H - h), (x0 + (j + 1) * bw - 2, top + H), col, -1)
        txt = np.full((18, 140, 3), 255, np.uint8)   # right-aligned, so after rotation it hangs from the axis
        tw = cv2.getTextSize(lab[:20], FONT, 0.4, 1)[0][0]
        cv2.putText(txt, lab[:20], (138 - tw, 13), FONT, 0.4, (200, 0, 0) if marks[i] else BLACK, 1, cv2.LINE_AA)
        rot = cv2.rotate(txt, cv2.ROTATE_90_COUNTERCLOCKWISE)
        ys, xs = top + H + 4, x0 + (m * bw) // 2 - 9
        img[ys:ys + rot.shape[0], xs:xs + rot.shape[1]] = np.minimum(img[ys:ys + rot.shape[0], xs:xs + rot.shape[1]], rot)
    x = W - 10 - 170 * m
    for j, (name, _vals, col) in enumerate(series):
        cv2.rectangle(img, (x + 170 * j, 34), (x + 170 * j + 12, 46), col, -1)
        cv2.putText(img, name, (x + 170 * j + 16, 45), FONT, 0.42, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, "red labels: unknown classes", (left, img.shape[0] - 8), FONT, 0.4, (200, 0, 0), 1, cv2.LINE_AA)
    return img

def heatmap(title: str, rows: list[str], cols: list[str], values: np.ndarray, cell: int = 26) -> np.ndarray:
    """A matrix as coloured cells (viridis over its own range) with row / column names and values."""
    v = np.asarray(values, dtype=np.float64)
    lo, hi = float(np.nanmin(v)), float(np.nanmax(v))
    norm = np.clip((v - lo) / max(hi - lo, 1e-9), 0, 1)
    col = cv2.applyColorMap((norm * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)[:, :, ::-1]
    left, top = 150, 150
    img = np.full((top + cell * len(rows) + 40, left + cell * len(cols) + 20, 3), 255, np.uint8)
    cv2.putText(img, title, (6, 20), FONT, 0.5, BLACK, 1, cv2.LINE_AA)
    cv2.putText(img, f"rows: GT class; columns: class text; range {lo:.2f}..{hi:.2f}", (6, 40), FONT, 0.38,
                BLACK, 1, cv2.LINE_AA)
    for i in range(len(rows)):
        cv2.putText(img, rows[i][:20], (4, top + cell * i + cell - 8), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
        for j in range(len(cols)):
            y, x = top + cell * i, left + cell * j
            img[y:y + cell - 1, x:x + cell - 1] = col[i, j]
            if i == j:
                cv2.rectangle(img, (x, y), (x + cell - 2, y + cell - 2), (255, 60, 60), 1)
    for j in range(len(cols)):
        txt = np.full((16, top - 50, 3), 255, np.uint8)
        tw = cv2.getTextSize(cols[j][:16], FONT, 0.38, 1)[0][0]
        cv2.putText(txt, cols[j][:16], (top - 52 - tw, 12), FONT, 0.38, BLACK, 1, cv2.LINE_AA)
        rot = cv2.rotate(txt, cv2.ROTATE_90_COUNTERCLOCKWISE)
        x = left + cell * j + (cell - 16) // 2
        img[top - rot.shape[0] - 2:top - 2, x:x + 16] = rot
    return img
