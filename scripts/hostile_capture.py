#!/usr/bin/env python3
"""The capture path under hostile input, as one job (issue 85): a corpus of
cases a careless or hostile user makes of `capture frame`, `capture`,
`capture --estimate` and `estimate --capture`, each run in its own folder
and judged on what it did:

- panic: exit 101, "panicked at" or a backtrace on stderr; crash: killed by a signal
- hang: still running after the time limit (300 s: the default size's fit takes under a minute)
- unclear: a refusal whose stderr is not one `error:` line, or whose line
  does not name what the case says it must (the file, the photo, the option)
- leftover: after a refusal, anything new in the case's folder (hidden
  temporaries included); after a success, a hidden temporary
- silent accept: exit 0 where the case must be refused
- wrong result: exit 0 with an output that a case's own check finds wrong
  (positions, the photo count, the frame's DPI)

    source scripts/env.sh   # cargo builds examples/frame_photos.rs
    ~/.cache/flashmat/venv/bin/python scripts/hostile_capture.py [BINARY] [WORK] [REPORT]
    # defaults: target/release/flashmat, /tmp/flashmat-hostile, reports/capture-hostile-corpus.md

The inputs are made here: frame photos by `examples/frame_photos.rs` (built
with cargo), a capture folder by `flashmat capture`, a synthetic one by
`flashmat svbrdf captures`, and broken, edited and misnamed copies of
them. Needs Pillow and numpy (the scripts' venv has both).
"""
import json
import os
import shutil
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
from PIL import Image

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.argv[1] if len(sys.argv) > 1 else ROOT / "target/release/flashmat").resolve()
WORK = Path(sys.argv[2] if len(sys.argv) > 2 else "/tmp/flashmat-hostile").resolve()
REPORT = Path(sys.argv[3] if len(sys.argv) > 3 else ROOT / "reports/capture-hostile-corpus.md")
LIMIT_S = 300
# One thread: the other core trains (docs/TRAINING.md, the CPU campaign).
ENV = dict(os.environ, OMP_NUM_THREADS="1", RAYON_NUM_THREADS="1", FLASHMAT_THREADS="1")
FAST = ["--size", "64", "--steps", "40"]


def sh(*args, **kw):
    return subprocess.run([str(a) for a in args], check=True, env=ENV, **kw)


def prepare():
    """The good inputs every case starts from."""
    base = WORK / "base"
    if (base / "done").exists():
        return base
    shutil.rmtree(base, ignore_errors=True)
    base.mkdir(parents=True)
    sh("cargo", "build", "--release", "--quiet", "--example", "frame_photos", cwd=ROOT)
    sh(ROOT / "target/release/examples/frame_photos", base / "frame", 4, 9, 1200, stderr=subprocess.DEVNULL)
    sh(BIN, "capture", *sorted((base / "frame").glob("*.jpg")), "--flash-offset", "8,0", "-o", base / "cap", stderr=subprocess.DEVNULL)
    sh(BIN, "svbrdf", "captures", "--svbrdf", "procedural-test:9", "--size", 128, "--photos", 3, "-o", base / "syn", stderr=subprocess.DEVNULL)
    (base / "done").write_text("")
    return base


BASE = None


def frame_photos():
    return sorted((BASE / "frame").glob("*.jpg"))


def copy_tree(src, dst):
    shutil.copytree(src, dst)
    return dst


def positions(path):
    return [[float(v) for v in line.replace(",", " ").split()] for line in path.read_text().split("\n") if line.strip()]


def png_bomb(path, w=60000, h=60000):
    """A PNG whose header claims w x h pixels, with almost no data."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 1000)) + chunk(b"IEND", b""))


def png16(path, rgb16):
    """A 16-bit RGB PNG of rgb16 `[H, W, 3]` (Pillow writes 16 bits for grey only)."""
    def chunk(kind, data):
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)
    h, w, _ = rgb16.shape
    rows = b"".join(b"\0" + rgb16[y].astype(">u2").tobytes() for y in range(h))
    ihdr = struct.pack(">IIBBBBB", w, h, 16, 2, 0, 0, 0)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


def edit_image(src, dst, fn, **save):
    im = Image.open(src)
    exif = im.info.get("exif")
    out = fn(im)
    if exif is not None and "exif" not in save and dst.suffix.lower() in (".jpg", ".jpeg"):
        save["exif"] = exif
    out.save(dst, **save)


def with_exif(src, dst, **tags):
    """A JPEG with its EXIF edited: ExposureTime, FNumber, ISO, FocalLengthIn35mmFilm, Orientation."""
    im = Image.open(src)
    exif = im.getexif()
    ifd = exif.get_ifd(0x8769)
    ids = {"ExposureTime": 0x829A, "FNumber": 0x829D, "ISO": 0x8827, "FocalLengthIn35mmFilm": 0xA405, "FocalLength": 0x920A}
    for k, v in tags.items():
        if k == "Orientation":
            exif[0x0112] = v
        else:
            ifd[ids[k]] = v
    im.save(dst, exif=exif.tobytes(), quality=92)


CASES = []


def case(name, cls, expect, must_name=None, check=None, limit=LIMIT_S):
    """Registers a case: setup(dir) -> argv (flashmat's arguments)."""
    def register(setup):
        CASES.append(dict(name=name, cls=cls, expect=expect, must_name=must_name, check=check, setup=setup, limit=limit))
        return setup
    return register


# ---------------------------------------------------------------- estimate --capture on a capture folder

def syn(d, edit=None):
    """A copy of the synthetic capture folder in d/c, edited by edit(folder)."""
    c = copy_tree(BASE / "syn", d / "c")
    if edit:
        edit(c)
    return c


def write(path, text):
    path.write_text(text)


def lines_edit(file, fn):
    def edit(c):
        p = c / file
        p.write_text("\n".join(fn(p.read_text().strip().split("\n"))) + "\n")
    return edit


def estimate_case(name, cls, expect, edit=None, extra=(), must_name=None, check=None, out="m.nmat"):
    @case(f"estimate --capture: {name}", cls, expect, must_name, check)
    def _(d):
        c = syn(d, edit)
        return ["estimate", "--capture", c, "-o", d / out, *extra]


# The folder itself.
@case("estimate --capture: the folder does not exist", "missing", "refuse", "nope")
def _(d):
    return ["estimate", "--capture", d / "nope", "-o", d / "m.nmat"]


@case("estimate --capture: the folder is a file", "missing", "refuse", "c")
def _(d):
    (d / "c").write_text("x")
    return ["estimate", "--capture", d / "c", "-o", d / "m.nmat"]


@case("estimate --capture: an empty folder", "missing", "refuse", "c")
def _(d):
    (d / "c").mkdir()
    return ["estimate", "--capture", d / "c", "-o", d / "m.nmat"]


for f in ["camera_pos.txt", "light_pos.txt", "image_size.txt"]:
    estimate_case(f"{f} missing", "missing", "refuse", lambda c, f=f: (c / f).unlink(), must_name=f)
    estimate_case(f"{f} empty", "corrupt", "refuse", lambda c, f=f: write(c / f, ""), must_name=f)
    estimate_case(f"{f} binary garbage", "corrupt", "refuse", lambda c, f=f: (c / f).write_bytes(os.urandom(64)), must_name=f)
for f in ["camera_pos.txt", "light_pos.txt"]:
    estimate_case(f"{f}: a line short", "inconsistent", "refuse", lines_edit(f, lambda l: l[:-1]), must_name=f)
    estimate_case(f"{f}: two numbers on a line", "corrupt", "refuse", lines_edit(f, lambda l: [l[0].rsplit(",", 1)[0]] + l[1:]), must_name=f)
    estimate_case(f"{f}: spaces for commas", "benign", "either", lines_edit(f, lambda l: [x.replace(",", " ") for x in l]), extra=FAST)
    for bad in ["nan", "inf", "-inf", "1e300", "abc", "0x10"]:
        estimate_case(f"{f}: {bad} in a position", "absurd", "refuse", lines_edit(f, lambda l, bad=bad: [f"{bad},0,4"] + l[1:]), must_name=f)
    estimate_case(f"{f}: a position below the sample (z < 0)", "absurd", "refuse", lines_edit(f, lambda l: ["0,0,-4"] + l[1:]), must_name=f)
    estimate_case(f"{f}: a position on the sample's plane (z = 0)", "absurd", "refuse", lines_edit(f, lambda l: ["0,0,0"] + l[1:]), must_name=f)
    estimate_case(f"{f}: a position 1e6 sample widths away", "absurd", "refuse", lines_edit(f, lambda l: ["0,0,1e7"] + l[1:]), must_name=f)
    estimate_case(f"{f}: Windows line ends", "benign", "ok", lines_edit(f, lambda l: [x + "\r" for x in l]), extra=FAST)
    estimate_case(f"{f}: comment line and blank lines", "benign", "either", lines_edit(f, lambda l: ["# positions", ""] + l + [""]), extra=FAST)
estimate_case("camera_pos.txt: an extra line", "inconsistent", "refuse", lines_edit("camera_pos.txt", lambda l: l + ["0,0,4"]), must_name="camera_pos.txt")
estimate_case("every photo at one position (different photos)", "silent accept", "refuse",
              lambda c: [write(c / f, (c / f).read_text().split("\n")[0] + "\n" + (c / f).read_text().split("\n")[0] + "\n" + (c / f).read_text().split("\n")[0] + "\n") for f in ["camera_pos.txt", "light_pos.txt"]], must_name="01")
for bad in ["0", "-10", "1e-30", "abc", "nan", "1e300", ""]:
    estimate_case(f"image_size.txt: {bad!r}", "absurd", "refuse", lambda c, bad=bad: write(c / "image_size.txt", bad + "\n"), must_name="image_size.txt")
estimate_case("image_size.txt: in millimetres (100)", "benign", "ok", lambda c: [write(c / "image_size.txt", "100\n"), [write(c / f, "\n".join(",".join(str(float(v) * 10) for v in row) for row in positions(c / f)) + "\n") for f in ["camera_pos.txt", "light_pos.txt"]]], extra=FAST)

# The photos.
estimate_case("a photo of 0 bytes", "corrupt", "refuse", lambda c: write(c / "01.png", ""), must_name="01.png")
estimate_case("a truncated photo", "corrupt", "refuse", lambda c: (c / "01.png").write_bytes((c / "01.png").read_bytes()[:3000]), must_name="01.png")
estimate_case("a text file named 01.png", "corrupt", "refuse", lambda c: write(c / "01.png", "hello"), must_name="01.png")
estimate_case("a JPEG named 01.png", "benign", "either", lambda c: edit_image(c / "01.png", c / "01.png", lambda im: im.convert("RGB"), format="JPEG", quality=95), extra=FAST)
estimate_case("a PNG claiming 60000x60000 pixels", "resources", "refuse", lambda c: png_bomb(c / "01.png"), must_name="01.png")
estimate_case("a folder named 01.png", "corrupt", "refuse", lambda c: [(c / "01.png").unlink(), (c / "01.png").mkdir()], must_name="01.png")
estimate_case("a photo of another size (downscaled)", "inconsistent", "refuse", lambda c: edit_image(c / "01.png", c / "01.png", lambda im: im.resize((64, 64))), must_name="01")
estimate_case("a photo of another shape", "inconsistent", "refuse", lambda c: edit_image(c / "01.png", c / "01.png", lambda im: im.crop((0, 0, 128, 100))), must_name="01")
estimate_case("the same photo twice at two positions", "silent accept", "refuse", lambda c: shutil.copy(c / "00.png", c / "01.png"), must_name="01")
estimate_case("a white photo (all clipped)", "silent accept", "refuse", lambda c: Image.new("RGB", (128, 128), (255, 255, 255)).save(c / "01.png"), must_name="01")
estimate_case("a black photo", "silent accept", "refuse", lambda c: Image.new("RGB", (128, 128), (0, 0, 0)).save(c / "01.png"), must_name="01")
estimate_case("a grey photo among colour ones", "silent accept", "refuse", lambda c: edit_image(c / "01.png", c / "01.png", lambda im: im.convert("L").convert("RGB")), must_name="01")
estimate_case("a 16-bit PNG photo", "benign", "ok", lambda c: png16(c / "01.png", np.asarray(Image.open(c / "01.png").convert("RGB")).astype(np.uint16) * 257), extra=FAST)
estimate_case("an RGBA photo", "benign", "ok", lambda c: edit_image(c / "01.png", c / "01.png", lambda im: im.convert("RGBA")), extra=FAST)
estimate_case("a photo of another material", "silent accept", "either", lambda c: edit_image(c / "01.png", c / "01.png", lambda im: im.transpose(Image.Transpose.ROTATE_90).point(lambda v: v // 2)), extra=FAST)
estimate_case("numbering with a gap, three position lines", "wrong result", "refuse", lambda c: shutil.move(c / "02.png", c / "03.png"), must_name="02")
estimate_case("numbering with a gap, lines for 00-03", "wrong result", "either",
              lambda c: [shutil.move(c / "02.png", c / "03.png")] + [write(c / f, "\n".join((c / f).read_text().strip().split("\n")[:2] + ["0,0,9", (c / f).read_text().strip().split("\n")[2]]) + "\n") for f in ["camera_pos.txt", "light_pos.txt"]], extra=FAST)
estimate_case("00.png and 00.jpg both", "inconsistent", "refuse", lambda c: edit_image(c / "00.png", c / "00.jpg", lambda im: im.convert("RGB"), quality=95), must_name="00")
estimate_case("a notes.txt beside the photos", "benign", "ok", lambda c: write(c / "notes.txt", "taken on Tuesday"), extra=FAST)
estimate_case("a subfolder beside the photos", "benign", "ok", lambda c: (c / "old").mkdir(), extra=FAST)
estimate_case("photos named 0.png, 1.png, 2.png", "inconsistent", "either", lambda c: [shutil.move(c / f"0{i}.png", c / f"{i}.png") for i in range(3)], extra=FAST)
estimate_case("one photo only", "benign", "either", lambda c: [(c / "01.png").unlink(), (c / "02.png").unlink()] + [write(c / f, (c / f).read_text().split("\n")[0] + "\n") for f in ["camera_pos.txt", "light_pos.txt"]], extra=FAST)
# exposures.txt
for bad, why in [("1e300", "absurd"), ("0", "absurd"), ("-1", "absurd"), ("nan", "absurd"), ("abc", "corrupt"), ("inf", "absurd"), ("1 1", "corrupt"), ("1e-12", "absurd")]:
    estimate_case(f"exposures.txt with {bad!r} for a photo", why, "refuse", lambda c, bad=bad: write(c / "exposures.txt", f"1\n{bad}\n1\n"), must_name="exposures.txt")
estimate_case("exposures.txt a line short", "inconsistent", "refuse", lambda c: write(c / "exposures.txt", "1\n1\n"), must_name="exposures.txt")
estimate_case("exposures.txt: one stop apart (bracketing)", "benign", "ok", lambda c: write(c / "exposures.txt", "1\n2\n1\n"), extra=FAST)
estimate_case("exposures.txt: three numbers a photo (white balance)", "benign", "ok", lambda c: write(c / "exposures.txt", "1 1 1\n1 1.05 0.95\n1 1 1\n"), extra=FAST)

# Options.
for v in ["0", "7", "31", "4097", "8192", "-8", "abc", "1e3", ""]:
    estimate_case(f"--size {v!r}", "option", "refuse", extra=["--size", v], must_name="size")
for v in ["-1", "abc", "1e9", "100000000"]:
    estimate_case(f"--steps {v!r}", "option", "refuse", extra=["--steps", v, "--size", "64"], must_name="steps")
estimate_case("--steps 0", "option", "either", extra=["--steps", "0", "--size", "64"])
for v in ["cuda", "cuda:7", "tpu", "gpu", ""]:
    estimate_case(f"--device {v!r}", "option", "refuse", extra=["--device", v, *FAST], must_name="device" if v in ("tpu", "gpu", "") else "cuda")
for v in ["1K", "abc", "0", "-1G", "1e400"]:
    estimate_case(f"--max-memory {v!r}", "option", "refuse", extra=["--max-memory", v, *FAST], must_name="memory")
estimate_case("--max-memory 2G with --size 4096", "resources", "refuse", extra=["--max-memory", "2G", "--size", "4096"], must_name="4096")
for v in ["0", "99", "-1", "abc"]:
    estimate_case(f"--photos {v!r}", "option", "refuse", extra=["--photos", v, *FAST], must_name="photos")
estimate_case("--photos 2", "benign", "ok", extra=["--photos", "2", *FAST])
for opt in [["--refine"], ["--tile"], ["--highlight-fill"], ["--fov", "30"], ["--exposure", "1"], ["--square"]]:
    estimate_case(f"{' '.join(opt)} (single-photo only)", "option", "refuse", extra=[*opt, *FAST], must_name=opt[0])
estimate_case("-o into a folder that does not exist", "output", "either", extra=FAST, out="new/dir/m.nmat")
estimate_case("-o an existing folder", "output", "refuse", edit=None, extra=FAST, out="c", must_name="c")
estimate_case("-o a .png", "output", "refuse", extra=FAST, out="m.png", must_name="m.png")
estimate_case("-o /proc (unwritable)", "output", "refuse", extra=FAST, out="/proc/m.nmat", must_name="/proc")


@case("estimate --capture: -o an existing .nmat (replaced whole)", "output", "ok")
def _(d):
    c = syn(d)
    (d / "m.nmat").write_text("old")
    return ["estimate", "--capture", c, "-o", d / "m.nmat", *FAST]


for where, why in [("file", "a file"), ("proc", "unwritable")]:
    @case(f"estimate --capture: --pbr into {why}, after nothing is written", "leftovers", "refuse", "pbr" if where == "file" else "/proc")
    def _(d, where=where):
        c = syn(d)
        pbr = d / "pbr"
        if where == "file":
            pbr.write_text("x")
        else:
            pbr = Path("/proc/pbr")
        return ["estimate", "--capture", c, "-o", d / "m.nmat", "--pbr", pbr, *FAST]

for bad, why in [("missing", "nope.safetensors"), ("garbage", "model.safetensors"), ("nmat", "model.safetensors")]:
    @case(f"estimate --capture: --model {bad}", "corrupt", "refuse", why)
    def _(d, bad=bad, why=why):
        c = syn(d)
        if bad == "garbage":
            (d / why).write_bytes(os.urandom(5000))
        elif bad == "nmat":
            (d / why).write_bytes(b"NMAT" + os.urandom(100))
        return ["estimate", "--capture", c, "-o", d / "m.nmat", "--model", d / why, *FAST]


# The default size, as a user runs it.
for name, extra in [("defaults", []), ("--pbr maps/", ["--pbr", "maps"]), ("--photo-gains", ["--photo-gains"])]:
    @case(f"estimate --capture: {name} (the default size)", "benign", "ok")
    def _(d, extra=extra):
        c = syn(d)
        return ["estimate", "--capture", c, "-o", d / "m.nmat", *[d / e if e == "maps" else e for e in extra]]


# ---------------------------------------------------------------- capture (frame photos)

def photos_in(d, edit=None, names=None):
    """Copies of the frame photos in d/p; edit(list of paths) edits them."""
    p = d / "p"
    p.mkdir()
    out = []
    for i, f in enumerate(frame_photos()):
        dst = p / (names[i] if names else f.name)
        shutil.copy(f, dst)
        out.append(dst)
    if edit:
        out = edit(out) or out
    return out


def lens_check(expect_mm, index=1, tol=15.0):
    """The capture folder's camera_pos line `index` within tol mm of expect_mm."""
    def check(d):
        cap = next((x for x in [d / "out", d / "m-capture"] if (x / "camera_pos.txt").exists()), None)
        if cap is None:
            return "no capture folder"
        rows = positions(cap / "camera_pos.txt")
        got = rows[index]
        far = max(abs(a - b) for a, b in zip(got, expect_mm))
        return None if far <= tol else f"photo {index}'s lens at {got}, expected {expect_mm}"
    return check


TRUE_LENSES = [[0, 0, 200], [45, -35, 185], [-40, 45, 190], [43, 40, 180]]


def capture_case(name, cls, expect, edit=None, extra=(), must_name=None, check=None, out="out", estimate=False, offset=True):
    @case(f"capture{' --estimate' if estimate else ''}: {name}", cls, expect, must_name, check)
    def _(d):
        photos = photos_in(d, edit)
        args = ["capture", *photos, "-o", d / out]
        if offset:
            args += ["--flash-offset", "8,0"]
        if estimate:
            args += ["--estimate"]
        return args + list(extra)


def after(*_effects, photos=None):
    """A case's setup as one expression: its edits (the arguments, already
    done when this runs) and then the photos to pass (None: the originals)."""
    return photos


def replace(i, fn, **save):
    def edit(ps):
        edit_image(ps[i], ps[i], fn, **save)
    return edit


def cover_half_the_opening(im):
    """A grey card over the left half of the photo's middle (where the opening is)."""
    a = np.array(im)
    h, w = a.shape[:2]
    a[h // 2 - 150:h // 2 + 150, w // 2 - 150:w // 2] = 90
    return Image.fromarray(a)


for est in [False, True]:
    o = "m.nmat" if est else "out"
    ex = ["--size", "64", "--steps", "40"] if est else []
    capture_case("the four photos", "benign", "ok", extra=ex, out=o, estimate=est, check=lens_check(TRUE_LENSES[1]))
    capture_case("a photo of 0 bytes", "corrupt", "refuse", lambda ps: write(ps[1], ""), ex, "IMG_01", out=o, estimate=est)
    capture_case("a truncated JPEG", "corrupt", "refuse", lambda ps: after(ps[1].write_bytes(ps[1].read_bytes()[:20000])), ex, "IMG_01", out=o, estimate=est)
    capture_case("a text file named .jpg", "corrupt", "refuse", lambda ps: write(ps[1], "hello"), ex, "IMG_01", out=o, estimate=est)
    capture_case("a photo that does not exist", "missing", "refuse", lambda ps: ps[1].unlink(), ex, "IMG_01", out=o, estimate=est)
    capture_case("a folder given as a photo", "missing", "refuse", lambda ps: after(ps[1].unlink(), ps[1].mkdir()), ex, "IMG_01", out=o, estimate=est)
    capture_case("a JPEG claiming 60000x60000 (a PNG bomb named .png)", "resources", "refuse", lambda ps: after(ps[1].unlink(), png_bomb(ps[1].with_suffix(".png")), photos=[ps[0], ps[1].with_suffix(".png"), *ps[2:]]), ex, "IMG_01", out=o, estimate=est)
    capture_case("a photo without the frame", "wrong input", "refuse", lambda ps: after(shutil.copy(next((ROOT / "examples/photos").glob("*.png")), ps[1])), ex, "IMG_01", out=o, estimate=est)
    capture_case("a mirrored photo", "wrong input", "refuse", replace(1, lambda im: im.transpose(Image.Transpose.FLIP_LEFT_RIGHT), quality=92), ex, "mirrored", out=o, estimate=est)
    capture_case("a photo turned 90 degrees, no EXIF orientation", "benign", "ok", replace(1, lambda im: im.transpose(Image.Transpose.ROTATE_90), quality=92), ex, out=o, estimate=est, check=lens_check(TRUE_LENSES[1]))
    capture_case("a photo turned 180 degrees", "benign", "ok", replace(2, lambda im: im.transpose(Image.Transpose.ROTATE_180), quality=92), ex, out=o, estimate=est, check=lens_check(TRUE_LENSES[2], 2))
    capture_case("a photo downscaled to half, EXIF dropped", "wrong result", "ok", replace(1, lambda im: im.resize((im.width // 2, im.height // 2)), quality=92, exif=b""), ex, out=o, estimate=est, check=lens_check(TRUE_LENSES[1]))
    capture_case("a photo cropped", "wrong result", "refuse", replace(1, lambda im: im.crop((100, 0, im.width - 100, im.height)), quality=92), ex, "IMG_01", out=o, estimate=est)
    capture_case("the same photo twice", "silent accept", "refuse", lambda ps: ps + [ps[1]], ex, "IMG_01", out=o, estimate=est)
    capture_case("the same photo thirty times", "silent accept", "refuse", lambda ps: ps + [ps[1]] * 29, ex, "IMG_01", out=o, estimate=est)
    capture_case("a copy of a photo under another name", "silent accept", "refuse", lambda ps: after(shutil.copy(ps[1], ps[1].parent / "copy.jpg"), photos=ps + [ps[1].parent / "copy.jpg"]), ex, "copy", out=o, estimate=est)
    capture_case("a white photo", "silent accept", "refuse", replace(1, lambda im: Image.new("RGB", im.size, (255, 255, 255)), quality=92), ex, "IMG_01", out=o, estimate=est)
    capture_case("a black photo", "silent accept", "refuse", replace(1, lambda im: Image.new("RGB", im.size, (0, 0, 0)), quality=92), ex, "IMG_01", out=o, estimate=est)
    capture_case("a grey photo among colour ones", "silent accept", "refuse", replace(1, lambda im: im.convert("L").convert("RGB"), quality=92), ex, "IMG_01", out=o, estimate=est)
    capture_case("a photo two stops darker (auto exposure)", "benign", "ok", replace(1, lambda im: im.point(lambda v: int(255 * ((v / 255) ** 2.2 / 4) ** (1 / 2.2))), quality=92), ex, out=o, estimate=est)
    capture_case("a tone-mapped photo (linear ^ 0.5)", "wrong input", "either", replace(1, lambda im: im.point(lambda v: int(255 * (((v / 255) ** 2.2) ** 0.5) ** (1 / 2.2))), quality=92), ex, out=o, estimate=est)
    capture_case("the opening half covered in one photo", "silent accept", "refuse", replace(1, cover_half_the_opening, quality=92), ex, "IMG_01", out=o, estimate=est)
    capture_case("a PNG photo among JPEGs", "benign", "ok", lambda ps: after(edit_image(ps[1], ps[1].with_suffix(".png"), lambda im: im), ps[1].unlink(), photos=[ps[0], ps[1].with_suffix(".png"), *ps[2:]]), ex, out=o, estimate=est)
    capture_case("a corrupt .dng", "corrupt", "refuse", lambda ps: after(write(ps[1].with_suffix(".dng"), "II*\0garbage"), photos=[ps[0], ps[1].with_suffix(".dng"), *ps[2:]]), ex, "IMG_01", out=o, estimate=est)
    capture_case("a .heic that is a JPEG", "corrupt", "either", lambda ps: after(shutil.copy(ps[1], ps[1].with_suffix(".heic")), photos=[ps[0], ps[1].with_suffix(".heic"), *ps[2:]]), ex, out=o, estimate=est)
    capture_case("a .gif photo", "corrupt", "refuse", lambda ps: after(edit_image(ps[1], ps[1].with_suffix(".gif"), lambda im: im), photos=[ps[0], ps[1].with_suffix(".gif"), *ps[2:]]), ex, "IMG_01", out=o, estimate=est)
    capture_case("one photo", "option", "refuse", lambda ps: ps[:1], ex, "2", out=o, estimate=est)
    capture_case("an EXIF exposure time of 4e9 s", "absurd", "refuse", lambda ps: with_exif(ps[1], ps[1], ExposureTime=4e9), ex, "IMG_01", out=o, estimate=est)
    capture_case("an EXIF ISO of 0", "absurd", "either", lambda ps: with_exif(ps[1], ps[1], ISO=0), ex, out=o, estimate=est)
    capture_case("an EXIF focal length of 1000 mm (35 mm equivalent)", "absurd", "either", lambda ps: with_exif(ps[1], ps[1], FocalLengthIn35mmFilm=1000), ex, out=o, estimate=est)
    capture_case("EXIF orientation 6 on an upright photo", "wrong input", "either", lambda ps: with_exif(ps[1], ps[1], Orientation=6), ex, out=o, estimate=est)
    for v in ["8", "a,b", "8,0,0", "nan,0", "1e9,0", "", "8;0"]:
        capture_case(f"--flash-offset {v!r}", "option", "refuse", extra=["--flash-offset", v, *ex], must_name="flash-offset", out=o, estimate=est, offset=False)
    capture_case("--flash-offset -8,3", "option", "ok", extra=["--flash-offset", "-8,3", *ex], out=o, estimate=est, offset=False)
    capture_case("no --flash-offset (8 mm taken as 0)", "benign", "ok", extra=ex, out=o, estimate=est, offset=False)
    for v in ["0", "7", "abc", "-1"]:
        capture_case(f"--max-size {v!r}", "option", "refuse", extra=["--max-size", v, *ex], must_name="max-size", out=o, estimate=est)
    # A cap above the photo's own resolution of the opening caps nothing (the help says so).
    capture_case("--max-size 100000", "option", "either", extra=["--max-size", "100000", *ex], out=o, estimate=est)
    capture_case("-o under a folder that does not exist", "output", "either", extra=ex, out=f"new/{o}", estimate=est)
    capture_case("-o /proc (unwritable)", "output", "refuse", extra=ex, out=f"/proc/{o}", estimate=est, must_name="/proc")

    @case(f"capture{' --estimate' if est else ''}: -o a non-empty folder", "output", "refuse", "out2")
    def _(d, est=est, ex=ex):
        (d / "out2").mkdir()
        (d / "out2" / "keep.txt").write_text("mine")
        return ["capture", *photos_in(d), "-o", d / "out2", "--flash-offset", "8,0", *(["--estimate"] if est else []), *ex]

for opt in [["--size", "64"], ["--steps", "10"], ["--device", "cpu"]]:
    capture_case(f"{opt[0]} without --estimate", "option", "refuse", extra=opt, must_name="--estimate")
for v in ["7", "0", "4097", "abc"]:
    capture_case(f"--size {v!r}", "option", "refuse", extra=["--size", v], must_name="size", out="m.nmat", estimate=True)
for v in ["-1", "abc"]:
    capture_case(f"--steps {v!r}", "option", "refuse", extra=["--steps", v, "--size", "64"], must_name="steps", out="m.nmat", estimate=True)
capture_case("--device tpu", "option", "refuse", extra=["--device", "tpu", "--size", "64"], must_name="device", out="m.nmat", estimate=True)
capture_case("--device cuda (none here)", "option", "refuse", extra=["--device", "cuda", "--size", "64"], must_name="cuda", out="m.nmat", estimate=True)
capture_case("-o a .png", "output", "refuse", extra=["--size", "64"], out="m.png", estimate=True, must_name="m.png")
capture_case("the default size", "benign", "ok", out="m.nmat", estimate=True)


@case("capture --estimate: m-capture/ already there and not empty", "leftovers", "refuse", "m-capture")
def _(d):
    (d / "m-capture").mkdir()
    (d / "m-capture" / "keep.txt").write_text("mine")
    return ["capture", *photos_in(d), "-o", d / "m.nmat", "--flash-offset", "8,0", "--estimate", "--size", "64"]


@case("capture --estimate: --size 7 refused before m-capture/ is written", "leftovers", "refuse", "size")
def _(d):
    return ["capture", *photos_in(d), "-o", d / "m.nmat", "--flash-offset", "8,0", "--estimate", "--size", "7"]


@case("capture: a stale temporary folder of a killed run is cleared", "leftovers", "ok")
def _(d):
    (d / ".out.tmp-999999-0").mkdir()
    (d / ".out.tmp-999999-0" / "00.png").write_text("partial")
    return ["capture", *photos_in(d), "-o", d / "out", "--flash-offset", "8,0"]


# ---------------------------------------------------------------- capture frame

def dpi_check(dpi):
    def check(d):
        im = Image.open(d / "f.png")
        got = im.info.get("dpi")
        return None if got and abs(got[0] - dpi) < 1 else f"the PNG says {got} dpi, {dpi} asked"
    return check


def frame_case(name, cls, expect, args, must_name=None, check=None):
    @case(f"capture frame: {name}", cls, expect, must_name, check)
    def _(d, args=args):
        return ["capture", "frame", *[str(d / a[2:]) if isinstance(a, str) and a.startswith("@/") else a for a in args]]


frame_case("-o f.pdf", "benign", "ok", ["-o", "@/f.pdf"])
frame_case("-o f.png", "benign", "ok", ["-o", "@/f.png"], check=dpi_check(300))
frame_case("-o f.png --dpi 150", "benign", "ok", ["-o", "@/f.png", "--dpi", "150"], check=dpi_check(150))
frame_case("--paper letter", "benign", "ok", ["-o", "@/f.pdf", "--paper", "letter"])
for v in ["0", "-1", "1e9", "abc", "99999", ""]:
    frame_case(f"--dpi {v!r}", "option", "refuse", ["-o", "@/f.png", "--dpi", v], "dpi")
frame_case("--dpi with a PDF", "option", "refuse", ["-o", "@/f.pdf", "--dpi", "300"], "dpi")
for v in ["4", "15", "0", "-10", "abc", "10.5"]:
    frame_case(f"--opening {v!r}", "option", "refuse", ["-o", "@/f.pdf", "--opening", v], "opening")
frame_case("--paper a3", "option", "refuse", ["-o", "@/f.pdf", "--paper", "a3"], "a3")
frame_case("-o f.txt", "output", "refuse", ["-o", "@/f.txt"], "f.txt")
frame_case("-o with no extension", "output", "refuse", ["-o", "@/frame"], "frame")
frame_case("-o /proc/f.pdf", "output", "refuse", ["-o", "/proc/f.pdf"], "/proc")
frame_case("-o under a missing folder", "output", "either", ["-o", "@/new/f.pdf"])


# ---------------------------------------------------------------- the runner

def snapshot(d):
    return {str(p.relative_to(d)) for p in d.rglob("*")}


def judge(c, d, before, rc, err, seconds, timed_out):
    after = snapshot(d)
    new = sorted(after - before)
    hidden = [p for p in new if any(part.startswith(".") and ".tmp" in part for part in Path(p).parts)]
    problems = []
    error_lines = [l for l in err.splitlines() if l.startswith("error")]
    if timed_out:
        problems.append("hang")
    elif rc == 101 or "panicked at" in err or "stack backtrace" in err.lower():
        problems.append("panic")
    elif rc < 0:
        problems.append(f"crash (signal {-rc})")
    if not timed_out and rc != 0:
        if len(error_lines) != 1 or not err.rstrip().splitlines()[-1].startswith("error"):
            problems.append("unclear: not one error line")
        elif c["must_name"] and c["must_name"].lower() not in error_lines[0].lower():
            problems.append(f"unclear: does not name {c['must_name']!r}")
        if new:
            problems.append(f"leftover: {', '.join(new[:3])}")
        if c["expect"] == "ok":
            problems.append("refused a good input")
    if not timed_out and rc == 0:
        if c["expect"] == "refuse":
            problems.append("silent accept")
        if hidden:
            problems.append(f"leftover: {', '.join(hidden[:3])}")
        if c["check"]:
            wrong = c["check"](d)
            if wrong:
                problems.append(f"wrong result: {wrong}")
    outcome = "hang" if timed_out else ("exit 0" if rc == 0 else f"exit {rc}")
    said = error_lines[0] if error_lines else ""
    warn = [l for l in err.splitlines() if l.startswith("warning")]
    return dict(name=c["name"], cls=c["cls"], expect=c["expect"], outcome=outcome, seconds=round(seconds, 1), said=said[:220], warnings=len(warn), first_warning=(warn[0][:160] if warn else ""), problems=problems)


def main():
    global BASE
    BASE = prepare()
    cases_dir = WORK / "cases"
    shutil.rmtree(cases_dir, ignore_errors=True)
    cases_dir.mkdir(parents=True)
    only = os.environ.get("ONLY")
    results = []
    t_all = time.time()
    for i, c in enumerate(CASES):
        if only and only.lower() not in c["name"].lower():
            continue
        d = cases_dir / f"{i:03d}"
        d.mkdir()
        try:
            argv = c["setup"](d)
        except Exception as e:  # a broken case is the harness's fault: say so and go on
            results.append(dict(name=c["name"], cls=c["cls"], expect=c["expect"], outcome="setup failed", seconds=0, said=str(e)[:200], warnings=0, first_warning="", problems=["harness"]))
            continue
        before = snapshot(d)
        t0 = time.time()
        try:
            p = subprocess.run([str(BIN), *[str(a) for a in argv]], cwd=d, env=ENV, capture_output=True, text=True, errors="replace", timeout=c["limit"])
            rc, err, timed_out = p.returncode, p.stderr, False
        except subprocess.TimeoutExpired as e:
            rc, err, timed_out = None, (e.stderr or b"").decode(errors="replace") if isinstance(e.stderr, bytes) else (e.stderr or ""), True
        r = judge(c, d, before, rc, err, time.time() - t0, timed_out)
        results.append(r)
        flag = "ok " if not r["problems"] else "BAD"
        print(f"{flag} {i:03d} {r['outcome']:>8} {r['seconds']:6.1f}s {c['name']}: {'; '.join(r['problems']) or r['said'][:100]}", flush=True)
        if not r["problems"]:
            shutil.rmtree(d, ignore_errors=True)
    (WORK / "results.json").write_text(json.dumps(results, indent=1))
    write_report(results, time.time() - t_all)


def write_report(results, seconds):
    def count(word):
        return sum(any(p.startswith(word) for p in r["problems"]) for r in results)
    lines = [
        "# The capture path under hostile input: the corpus, run as one job (issue 85)",
        "",
        f"`source scripts/env.sh && ~/.cache/flashmat/venv/bin/python scripts/hostile_capture.py` ({len(results)} cases, {seconds / 60:.0f} minutes on one thread; "
        "the cases and their judges are in the script). A case is one command on inputs made for it "
        "(frame photos of `examples/frame_photos.rs`, a capture folder of `flashmat capture`, a synthetic one of `flashmat svbrdf captures`, edited), "
        "expected to be refused (`refuse`), to succeed (`ok`) or either (`either`: a judgement call, read the row).",
        "",
        "| | cases | panics | crashes | hangs | unclear errors | leftovers | silent accepts | wrong results | good input refused | harness |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
        f"| {time.strftime('%Y-%m-%d')} | {len(results)} | {count('panic')} | {count('crash')} | {count('hang')} | {count('unclear')} | {count('leftover')} | {count('silent')} | {count('wrong')} | {count('refused a good')} | {count('harness')} |",
        "",
        "| # | case | class | expected | outcome | s | what it said | problems |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for i, r in enumerate(results):
        said = r["said"] or (f"({r['warnings']} warnings) {r['first_warning']}" if r["warnings"] else "")
        said = said.replace("|", "\\|").replace("\n", " ")
        lines.append(f"| {i} | {r['name'].replace('|', '/')} | {r['cls']} | {r['expect']} | {r['outcome']} | {r['seconds']} | {said} | {'; '.join(r['problems']).replace('|', '/')} |")
    REPORT.write_text("\n".join(lines) + "\n")
    print(f"{len(results)} cases; report: {REPORT}")


if __name__ == "__main__":
    main()
