"""Small line charts drawn with opencv (no plotting library): learning curves and the like.

`line_chart(title, series, x_label, y_label, ...)` -> (H, W, 3) uint8 BGR image; each series is
(name, xs, ys, colour BGR). Axes get round tick values; the legend sits under the title. Save with
`cv2.imwrite` (ago_runtime.atomic.atomic_path for an atomic write).
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
