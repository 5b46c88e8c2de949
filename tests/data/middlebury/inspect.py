#!/usr/bin/env python3
"""Inspect the Middlebury stereo pairs in this folder (no OpenCV / PIL needed).

Usage (numpy is needed; on this machine it is in the system interpreter):
    /usr/bin/python3 tests/data/middlebury/inspect.py [scene ...]

For each scene (default: every sub-folder holding left.png, right.png and
disparity.pgm or disparity.png) it prints:
  * image sizes and the SHA-256 / git blob hash of each file;
  * the disparity scale assumed (grey value / scale = disparity in px, 0 = unknown),
    the fraction of pixels with known disparity and the min / max valid disparity;
  * a photometric check of the scale and sign: for every known pixel it samples
    the right image at x_right = x_left - d (linear interpolation) and reports
    the median |grey_left - grey_right| for several candidate scales and for the
    wrong sign. The true encoding gives by far the smallest residual.

Only numpy, zlib, struct and hashlib are used. PNG decoding covers what this
folder holds (8-bit grey / RGB / RGBA / palette, non-interlaced).
"""
import os
import sys

# This file is called inspect.py, which shadows the standard-library module
# `inspect` that numpy imports. Drop the script's own folder from sys.path first.
_HERE = os.path.dirname(os.path.abspath(__file__))
sys.path = [p for p in sys.path if os.path.abspath(p or os.curdir) != _HERE]

import hashlib  # noqa: E402
import struct  # noqa: E402
import zlib  # noqa: E402

import numpy as np  # noqa: E402

# grey value / SCALE = disparity in px; 0 = unknown (see README.md for the sources).
SCALES = {"teddy": 4, "cones": 4, "tsukuba": 16, "venus": 8}


def read_png(path):
    data = open(path, "rb").read()
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        raise ValueError(f"{path}: not a PNG (LFS pointer?)")
    pos, idat, plte, hdr = 8, [], None, None
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        typ, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        pos += 12 + n
        if typ == b"IHDR":
            hdr = struct.unpack(">IIBBBBB", body)
        elif typ == b"PLTE":
            plte = np.frombuffer(body, np.uint8).reshape(-1, 3)
        elif typ == b"IDAT":
            idat.append(body)
        elif typ == b"IEND":
            break
    w, h, depth, ctype, _, _, interlace = hdr
    if depth != 8 or interlace != 0:
        raise ValueError(f"{path}: unsupported PNG (depth {depth}, interlace {interlace})")
    ch = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}[ctype]
    stride = w * ch
    raw = np.frombuffer(zlib.decompress(b"".join(idat)), np.uint8).reshape(h, stride + 1)
    out = np.zeros((h, stride), np.uint8)
    prev = np.zeros(stride, np.int32)
    for y in range(h):
        f, line = raw[y, 0], raw[y, 1:].astype(np.int32)
        if f == 0:
            cur = line
        elif f == 1:
            cur = line.copy()
            for x in range(ch, stride):
                cur[x] = (cur[x] + cur[x - ch]) & 255
        elif f == 2:
            cur = (line + prev) & 255
        else:
            cur = np.zeros(stride, np.int32)
            for x in range(stride):
                a = int(cur[x - ch]) if x >= ch else 0
                b = int(prev[x])
                c = int(prev[x - ch]) if x >= ch else 0
                if f == 3:
                    p = (a + b) // 2
                else:  # Paeth
                    pa, pb, pc = abs(b - c), abs(a - c), abs(a + b - 2 * c)
                    p = a if (pa <= pb and pa <= pc) else (b if pb <= pc else c)
                cur[x] = (line[x] + p) & 255
        out[y] = cur
        prev = cur
    img = out.reshape(h, w, ch)
    if ctype == 3:
        img = plte[img[..., 0]]
    return img


def read_pnm(path):
    data = open(path, "rb").read()
    toks, pos = [], 0
    while len(toks) < 4:
        while data[pos:pos + 1].isspace():
            pos += 1
        if data[pos:pos + 1] == b"#":
            while data[pos:pos + 1] not in (b"\n", b"\r"):
                pos += 1
            continue
        start = pos
        while not data[pos:pos + 1].isspace():
            pos += 1
        toks.append(data[start:pos])
    pos += 1
    magic, w, h, maxval = toks[0], int(toks[1]), int(toks[2]), int(toks[3])
    if magic not in (b"P5", b"P6") or maxval != 255:
        raise ValueError(f"{path}: unsupported PNM {magic!r} maxval {maxval}")
    ch = 3 if magic == b"P6" else 1
    return np.frombuffer(data[pos:pos + w * h * ch], np.uint8).reshape(h, w, ch)


def read_image(path):
    return read_png(path) if path.endswith(".png") else read_pnm(path)


def grey(img):
    img = img[..., :3].astype(np.float64)
    return img.mean(axis=2) if img.shape[2] == 3 else img[..., 0]


def hashes(path):
    data = open(path, "rb").read()
    blob = hashlib.sha1(b"blob %d\0" % len(data) + data).hexdigest()
    return len(data), hashlib.sha256(data).hexdigest(), blob


def residual(gl, gr, raw, scale, sign):
    """Median |L(x,y) - R(x - sign*raw/scale, y)| over known pixels that stay inside R."""
    h, w = raw.shape
    ys, xs = np.nonzero(raw > 0)
    xr = xs - sign * raw[ys, xs] / scale
    ok = (xr >= 0) & (xr <= w - 1)
    ys, xs, xr = ys[ok], xs[ok], xr[ok]
    x0 = np.floor(xr).astype(int)
    x1 = np.minimum(x0 + 1, w - 1)
    t = xr - x0
    r = (1 - t) * gr[ys, x0] + t * gr[ys, x1]
    return float(np.median(np.abs(gl[ys, xs] - r)))


def inspect_scene(scene):
    d = os.path.join(_HERE, scene)
    disp_name = "disparity.pgm" if os.path.exists(os.path.join(d, "disparity.pgm")) else "disparity.png"
    files = ["left.png", "right.png", disp_name]
    print(f"== {scene}")
    imgs = {}
    for f in files:
        p = os.path.join(d, f)
        imgs[f] = read_image(p)
        size, sha256, blob = hashes(p)
        h, w, c = imgs[f].shape
        print(f"  {f:14s} {w}x{h}x{c}  {size:7d} bytes  sha256 {sha256}  git-blob {blob}")
    raw = imgs[disp_name][..., 0].astype(np.float64)
    scale = SCALES.get(scene)
    known = raw > 0
    print(f"  scale: grey/{scale} = disparity px, 0 = unknown")
    print(f"  known disparity: {known.mean() * 100:.2f}% of pixels ({int(known.sum())} of {raw.size})")
    print(f"  raw grey range (known): {int(raw[known].min())}..{int(raw[known].max())}; "
          f"disparity range: {raw[known].min() / scale:.2f}..{raw[known].max() / scale:.2f} px")
    gl, gr = grey(imgs["left.png"]), grey(imgs["right.png"])
    checks = [(s, +1) for s in (1, 2, 4, 8, 16)] + [(scale, -1)]
    parts = []
    for s, sign in checks:
        label = f"/{s}" + ("" if sign > 0 else " (x_r = x_l + d)")
        parts.append(f"{label}: {residual(gl, gr, raw, s, sign):.2f}")
    print("  median |L - R(x - d)| grey levels by assumed scale: " + ", ".join(parts))
    return {
        "known_frac": float(known.mean()),
        "dmin": raw[known].min() / scale,
        "dmax": raw[known].max() / scale,
    }


def main(argv):
    scenes = argv[1:] or sorted(
        s for s in os.listdir(_HERE)
        if os.path.isfile(os.path.join(_HERE, s, "left.png"))
    )
    for s in scenes:
        inspect_scene(s)


if __name__ == "__main__":
    main(sys.argv)
