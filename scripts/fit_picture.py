"""One JPEG row of a `flashmat fit` folder: photo | base colour | roughness |
metallic | normal map | fit error | a render of the glTF (scripts/render_gltf.py).

Usage: python scripts/fit_picture.py FIT_DIR PHOTO.png GLTF_RENDER.png OUT.jpg [--cell 128]
"""
import argparse
import os

import numpy as np
import mitsuba as mi


def load(path):
    a = np.array(mi.Bitmap(path)).astype(np.float32)
    a = a / 255.0 if a.max() > 1.5 else a
    if a.ndim == 2:
        a = a[:, :, None]
    if a.shape[2] == 1:
        a = np.repeat(a, 3, 2)
    return a[:, :, :3]


# Colours and scale of flashmat's error.png (src/fit/export.rs: HEAT_STOPS, ERROR_SCALE).
HEAT_STOPS = np.array([[0.0, 0.0, 0.0], [0.45, 0.1, 0.55], [0.95, 0.45, 0.1], [1.0, 1.0, 0.75]], np.float32)
ERROR_SCALE = 0.1


def heat(path):
    e = np.array(mi.Bitmap(path)).astype(np.float32)
    t = np.clip(e.reshape(e.shape[0], e.shape[1]) / ERROR_SCALE, 0, 1) * (len(HEAT_STOPS) - 1)
    i = np.minimum(np.floor(t).astype(int), len(HEAT_STOPS) - 2)
    f = (t - i)[:, :, None]
    return HEAT_STOPS[i] * (1 - f) + HEAT_STOPS[i + 1] * f


def square(a):
    h, w = a.shape[:2]
    s = min(h, w)
    return a[(h - s) // 2:(h - s) // 2 + s, (w - s) // 2:(w - s) // 2 + s]


def resize(a, n):
    """Area average to n x n (nearest for enlarging)."""
    s = a.shape[0]
    idx = (np.arange(n + 1) * s) // n
    out = np.zeros((n, n, 3), np.float32)
    for i in range(n):
        for j in range(n):
            out[i, j] = a[idx[i]:max(idx[i + 1], idx[i] + 1), idx[j]:max(idx[j + 1], idx[j] + 1)].mean((0, 1))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("fit_dir")
    ap.add_argument("photo")
    ap.add_argument("render")
    ap.add_argument("output")
    ap.add_argument("--cell", type=int, default=128)
    args = ap.parse_args()
    mi.set_variant("scalar_rgb")
    maps = os.path.join(args.fit_dir, "maps")
    cells = [load(args.photo)] + [load(os.path.join(maps, f)) for f in ("base_color.png", "roughness.png", "metallic.png", "normal.png")]
    cells += [heat(os.path.join(args.fit_dir, "error.exr")), load(args.render)]
    gap = 3
    n = args.cell
    row = np.full((n + 2 * gap, len(cells) * (n + gap) + gap, 3), 0.08, np.float32)
    for k, c in enumerate(cells):
        row[gap:gap + n, gap + k * (n + gap):gap + k * (n + gap) + n] = resize(square(c), n)
    bmp = mi.Bitmap((np.clip(row, 0, 1) * 255 + 0.5).astype(np.uint8), pixel_format=mi.Bitmap.PixelFormat.RGB)
    bmp.write(args.output, quality=82)
    print(f"wrote {args.output} ({os.path.getsize(args.output)} bytes)")


if __name__ == "__main__":
    main()
