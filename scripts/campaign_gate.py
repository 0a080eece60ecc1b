"""The CPU campaign's gate (issue 86): a candidate single-photo model
against the bundled one, from `scripts/cpu-campaign.sh gate`'s outputs.

Reads OUT/eval/{flashmat,candidate}.csv (flashmat eval: LPIPS per
material and case), OUT/eval/highlights/ratios.csv (the moved-highlight
test per material) and OUT/photos/brightness.txt (the 13 photos' identity
brightness, "NAME bundled|candidate VALUE" lines), and prints gate.md: the
table and, on its first line of verdict, PASS or FAIL with the reasons.

The candidate passes when it beats the bundled model on the moved-highlight
test (ghost lower, lobe higher; geometric means over the materials), its
Identity, Reflect and Hemisphere LPIPS stay within 3% of the bundled
model's, and the photos' worst identity brightness |ln b| is no worse.

    python3 scripts/campaign_gate.py OUT
"""

import csv
import math
import sys
from collections import defaultdict
from pathlib import Path

LPIPS_TOLERANCE = 1.03
CASES = ["identity", "reflect", "hemisphere"]


def lpips_means(path):
    sums = defaultdict(list)
    with open(path) as f:
        for row in csv.DictReader(f):
            sums[row["case"]].append(float(row["lpips"]))
    return {case: sum(v) / len(v) for case, v in sums.items()}


def geometric(values):
    values = [v for v in values if v > 0]
    return math.exp(sum(math.log(v) for v in values) / len(values)) if values else float("nan")


def highlight_means(path, method):
    cols = defaultdict(list)
    with open(path) as f:
        for row in csv.DictReader(f):
            if row["method"] != method:
                continue
            for key in ("ghost", "lobe", "rest"):
                if row[key] not in ("", "nan"):
                    cols[key].append(float(row[key]))
    return {key: geometric(v) for key, v in cols.items()}


def main(out):
    out = Path(out)
    lp = {m: lpips_means(out / "eval" / f"{m}.csv") for m in ("flashmat", "candidate")}
    hl = {m: highlight_means(out / "eval" / "highlights" / "ratios.csv", m) for m in ("flashmat", "candidate")}
    bright = defaultdict(dict)
    for line in (out / "photos" / "brightness.txt").read_text().splitlines():
        name, which, value = line.split()
        bright[which][name] = float(value)
    worst = {w: max(abs(math.log(v)) for v in bright[w].values()) for w in ("bundled", "candidate") if bright[w]}
    reasons = []
    if not hl["candidate"].get("ghost", math.inf) < hl["flashmat"].get("ghost", -math.inf):
        reasons.append("ghost not lower")
    if not hl["candidate"].get("lobe", -math.inf) > hl["flashmat"].get("lobe", math.inf):
        reasons.append("lobe not higher")
    for case in CASES:
        if not lp["candidate"][case] <= LPIPS_TOLERANCE * lp["flashmat"][case]:
            reasons.append(f"{case} LPIPS {lp['candidate'][case]:.3f} above 1.03x {lp['flashmat'][case]:.3f}")
    if "candidate" not in worst or "bundled" not in worst:
        reasons.append("no photo brightness measured")
    elif worst["candidate"] > worst["bundled"] + 1e-9:
        reasons.append(f"photos' worst brightness |ln b| {worst['candidate']:.3f} against {worst['bundled']:.3f}")
    print("# The CPU campaign's gate\n")
    print("PASS" if not reasons else "FAIL: " + "; ".join(reasons))
    print("\n| model | ghost | lobe | rest | LPIPS Identity | Reflect | Hemisphere | photos' brightness (range) |")
    print("|---|---|---|---|---|---|---|---|")
    for m, w in (("flashmat", "bundled"), ("candidate", "candidate")):
        b = bright.get(w, {})
        rng = f"{min(b.values()):.2f}-{max(b.values()):.2f}" if b else "-"
        h = hl[m]
        print(f"| {w} | {h.get('ghost', math.nan):.2f} | {h.get('lobe', math.nan):.2f} | {h.get('rest', math.nan):.2f} | "
              f"{lp[m]['identity']:.3f} | {lp[m]['reflect']:.3f} | {lp[m]['hemisphere']:.3f} | {rng} |")
    print("\n(50 held-out materials at 16 configurations per case, 8-bit photos; the moved-highlight figures are "
          "geometric means over the materials; the photos are examples/photos' 13.)")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: campaign_gate.py OUT")
    main(sys.argv[1])
