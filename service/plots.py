"""PNG charts for the benchmark reports, drawn with numpy alone (no plotting library to install):
grouped bars with error bars (the paper's Fig. 2) and lines over time, with a small pixel font
for titles, ticks and legends."""

from __future__ import annotations

import struct
import zlib
from collections.abc import Sequence
from pathlib import Path

import numpy as np

__all__ = ["bar_chart", "line_chart", "write_png"]

# 3x5 pixel glyphs, rows top to bottom; text is drawn upper-case.
_GLYPHS = {
    "0": "###|#.#|#.#|#.#|###", "1": ".#.|##.|.#.|.#.|###", "2": "###|..#|###|#..|###", "3": "###|..#|.##|..#|###",
    "4": "#.#|#.#|###|..#|..#", "5": "###|#..|###|..#|###", "6": "###|#..|###|#.#|###", "7": "###|..#|.#.|.#.|.#.",
    "8": "###|#.#|###|#.#|###", "9": "###|#.#|###|..#|###", "A": ".#.|#.#|###|#.#|#.#", "B": "##.|#.#|##.|#.#|##.",
    "C": ".##|#..|#..|#..|.##", "D": "##.|#.#|#.#|#.#|##.", "E": "###|#..|##.|#..|###", "F": "###|#..|##.|#..|#..",
    "G": ".##|#..|#.#|#.#|.##", "H": "#.#|#.#|###|#.#|#.#", "I": "###|.#.|.#.|.#.|###", "J": "..#|..#|..#|#.#|.#.",
    "K": "#.#|#.#|##.|#.#|#.#", "L": "#..|#..|#..|#..|###", "M": "#.#|###|###|#.#|#.#", "N": "##.|#.#|#.#|#.#|#.#",
    "O": ".#.|#.#|#.#|#.#|.#.", "P": "##.|#.#|##.|#..|#..", "Q": ".#.|#.#|#.#|##.|.##", "R": "##.|#.#|##.|#.#|#.#",
    "S": ".##|#..|.#.|..#|##.", "T": "###|.#.|.#.|.#.|.#.", "U": "#.#|#.#|#.#|#.#|###", "V": "#.#|#.#|#.#|#.#|.#.",
    "W": "#.#|#.#|###|###|#.#", "X": "#.#|#.#|.#.|#.#|#.#", "Y": "#.#|#.#|.#.|.#.|.#.", "Z": "###|..#|.#.|#..|###",
    ".": "...|...|...|...|.#.", "-": "...|...|###|...|...", ":": "...|.#.|...|.#.|...", "/": "..#|..#|.#.|#..|#..",
    "(": ".#.|#..|#..|#..|.#.", ")": ".#.|..#|..#|..#|.#.", "=": "...|###|...|###|...", "_": "...|...|...|...|###",
    ",": "...|...|...|.#.|#..", "%": "#.#|..#|.#.|#..|#.#", "+": "...|.#.|###|.#.|...", " ": "...|...|...|...|...",
}  # fmt: skip
_PALETTE = np.array(
    [[31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40], [148, 103, 189], [140, 86, 75], [227, 119, 194]],
    np.uint8,
)
_INK, _GRID, _WHITE = np.array([40, 40, 40], np.uint8), np.array([225, 225, 225], np.uint8), np.uint8(255)
_S = 2  # font scale: glyphs are 6 x 10 px


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an (H, W, 3) uint8 image as a PNG file."""
    h, w, _ = image.shape
    raw = b"".join(b"\x00" + image[y].tobytes() for y in range(h))

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    path = Path(path)
    header = chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + header + chunk(b"IDAT", zlib.compress(raw, 9)) + chunk(b"IEND", b""))
    return path


class _Canvas:
    def __init__(self, width: int, height: int):
        self.img = np.full((height, width, 3), _WHITE, np.uint8)

    def rect(self, x0: float, y0: float, x1: float, y1: float, color) -> None:
        h, w, _ = self.img.shape
        xa, xb = sorted((round(x0), round(x1)))
        ya, yb = sorted((round(y0), round(y1)))
        self.img[max(ya, 0) : min(yb + 1, h), max(xa, 0) : min(xb + 1, w)] = color

    def line(self, x0: float, y0: float, x1: float, y1: float, color, width: int = 1) -> None:
        n = int(max(abs(x1 - x0), abs(y1 - y0))) + 1
        for t in np.linspace(0.0, 1.0, n):
            x, y = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
            self.rect(x - width // 2, y - width // 2, x + (width - 1) // 2, y + (width - 1) // 2, color)

    def text(self, x: float, y: float, text: str, color=_INK, align: str = "left") -> None:
        width = len(text) * 4 * _S
        x = x - width if align == "right" else x - width / 2 if align == "center" else x
        for i, ch in enumerate(text.upper()):
            rows = _GLYPHS.get(ch, _GLYPHS[" "]).split("|")
            for r, row in enumerate(rows):
                for c, px in enumerate(row):
                    if px == "#":
                        gx, gy = x + (4 * i + c) * _S, y + r * _S
                        self.rect(gx, gy, gx + _S - 1, gy + _S - 1, color)


def _nice_max(value: float) -> tuple[float, float]:
    """An axis top at or above ``value`` and its tick step."""
    if value <= 0 or not np.isfinite(value):
        return 1.0, 0.25
    step = 10 ** np.floor(np.log10(value / 4))
    for m in (1, 2, 2.5, 5, 10):
        if value / (m * step) <= 6:
            step *= m
            break
    return float(np.ceil(value / step) * step), float(step)


def _axes(c: _Canvas, box: tuple[int, int, int, int], top: float, step: float, ylabel: str) -> None:
    left, up, right, bottom = box
    for v in np.arange(0.0, top + step / 2, step):
        y = bottom - (bottom - up) * v / top
        c.line(left, y, right, y, _GRID)
        c.text(left - 6, y - 5, f"{v:g}", align="right")
    c.line(left, up, left, bottom, _INK)
    c.line(left, bottom, right, bottom, _INK)
    c.text(left, up - 18, ylabel)


def _legend(c: _Canvas, x: int, y: int, labels: Sequence[str]) -> None:
    for i, label in enumerate(labels):
        c.rect(x, y + i * 16, x + 10, y + i * 16 + 10, _PALETTE[i % len(_PALETTE)])
        c.text(x + 16, y + i * 16, label)


def bar_chart(
    path: str | Path,
    title: str,
    groups: Sequence[str],
    series: Sequence[str],
    mean: np.ndarray,
    std: np.ndarray | None = None,
    ylabel: str = "ADD MM",
) -> Path:
    """Grouped bars: ``mean`` (len(groups), len(series)), error bars ``std``; NaN bars are left out."""
    mean = np.asarray(mean, float)
    std = np.zeros_like(mean) if std is None else np.asarray(std, float)
    width, height = max(520, 90 * len(groups) * max(1, len(series)) // 3 + 220), 360
    c = _Canvas(width, height)
    box = (60, 50, width - 130, height - 40)
    top, step = _nice_max(np.nanmax(mean + std) if np.isfinite(mean).any() else 1.0)
    c.text(width / 2, 10, title, align="center")
    _axes(c, box, top, step, ylabel)
    left, up, right, bottom = box
    slot = (right - left) / max(len(groups), 1)
    bar = slot * 0.8 / max(len(series), 1)
    for i, g in enumerate(groups):
        x0 = left + i * slot + slot * 0.1
        for j in range(len(series)):
            if not np.isfinite(mean[i, j]):
                continue
            y = bottom - (bottom - up) * min(mean[i, j], top) / top
            c.rect(x0 + j * bar + 1, y, x0 + (j + 1) * bar - 1, bottom - 1, _PALETTE[j % len(_PALETTE)])
            if std[i, j] > 0:
                xm = x0 + (j + 0.5) * bar
                y_hi = bottom - (bottom - up) * min(mean[i, j] + std[i, j], top) / top
                y_lo = bottom - (bottom - up) * max(mean[i, j] - std[i, j], 0.0) / top
                c.line(xm, y_hi, xm, y_lo, _INK)
                c.line(xm - 3, y_hi, xm + 3, y_hi, _INK)
        c.text(left + (i + 0.5) * slot, bottom + 8, g, align="center")
    _legend(c, right + 12, up, series)
    return write_png(path, c.img)


def line_chart(
    path: str | Path,
    title: str,
    series: dict[str, np.ndarray],
    x_step: float = 1.0,
    xlabel: str = "TIME S",
    ylabel: str = "ADD MM",
) -> Path:
    """One line per series over x = index * ``x_step``."""
    width, height = 720, 360
    c = _Canvas(width, height)
    box = (60, 50, width - 150, height - 40)
    values = [np.asarray(v, float) for v in series.values()]
    top, step = _nice_max(max((float(np.nanmax(v)) for v in values if v.size), default=1.0))
    c.text(width / 2, 10, title, align="center")
    _axes(c, box, top, step, ylabel)
    left, up, right, bottom = box
    n = max((v.size for v in values), default=1)
    span = max((n - 1) * x_step, 1e-9)
    xt, xs = _nice_max(span)
    for v in np.arange(0.0, xt + xs / 2, xs):
        if v <= span:
            x = left + (right - left) * v / span
            c.line(x, bottom, x, bottom + 4, _INK)
            c.text(x, bottom + 8, f"{v:g}", align="center")
    c.text(right, bottom + 22, xlabel, align="right")
    for j, v in enumerate(values):
        xs_px = left + (right - left) * np.arange(v.size) * x_step / span
        ys_px = bottom - (bottom - up) * np.clip(v, 0.0, top) / top
        for a in range(v.size - 1):
            c.line(xs_px[a], ys_px[a], xs_px[a + 1], ys_px[a + 1], _PALETTE[j % len(_PALETTE)])
    _legend(c, right + 12, up, list(series))
    return write_png(path, c.img)
