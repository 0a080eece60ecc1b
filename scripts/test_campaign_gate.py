"""Tests of scripts/campaign_gate.py on hand-made evaluation files:
the verdict follows each of the gate's four conditions.

    python3 scripts/test_campaign_gate.py
"""

import subprocess
import sys
import tempfile
import unittest
from pathlib import Path

GATE = Path(__file__).with_name("campaign_gate.py")


def write_case(out, lpips, ratios, brightness):
    """lpips: {method: (identity, reflect, hemisphere)} for two materials alike;
    ratios: {method: (ghost, lobe, rest)}; brightness: {which: [values]}."""
    (out / "eval" / "highlights").mkdir(parents=True)
    (out / "photos").mkdir()
    for method, (i, r, h) in lpips.items():
        rows = ["material,case,lpips,rmse_log,psnr"]
        for m in ("test00", "test01"):
            rows += [f"{m},identity,{i},0.1,20", f"{m},reflect,{r},0.1,20", f"{m},hemisphere,{h},0.1,20"]
        (out / "eval" / f"{method}.csv").write_text("\n".join(rows) + "\n")
    rows = ["method,material,glossiness,photo_highlight_pixels,ghost,lobe,rest,ghost_lights,lobe_lights,lpips_ghost,lpips_lobe,relit_chroma"]
    for method, (g, l, r) in ratios.items():
        rows += [f"{method},test00,1,100,{g},{l},{r},3,3,0.1,0.1,0.01", f"{method},test01,1,100,{g},,{r},3,0,0.1,,0.01"]
    (out / "eval" / "highlights" / "ratios.csv").write_text("\n".join(rows) + "\n")
    lines = [f"IMG_{k} {which} {v}" for which, values in brightness.items() for k, v in enumerate(values)]
    (out / "photos" / "brightness.txt").write_text("\n".join(lines) + "\n")


def verdict(**case):
    with tempfile.TemporaryDirectory() as d:
        write_case(Path(d), **case)
        text = subprocess.run([sys.executable, str(GATE), d], check=True, capture_output=True, text=True).stdout
    return next(line for line in text.splitlines() if line.startswith(("PASS", "FAIL")))


BUNDLED_LPIPS = (0.100, 0.200, 0.300)
GOOD = dict(
    lpips={"flashmat": BUNDLED_LPIPS, "candidate": (0.102, 0.205, 0.300)},
    ratios={"flashmat": (2.0, 0.2, 1.0), "candidate": (1.4, 0.5, 1.0)},
    brightness={"bundled": [0.8, 1.1], "candidate": [0.9, 1.05]},
)


class GateTest(unittest.TestCase):
    def test_a_better_model_within_the_lpips_bound_passes(self):
        self.assertEqual(verdict(**GOOD), "PASS")

    def test_each_condition_fails_it_alone(self):
        worse_ghost = dict(GOOD, ratios={"flashmat": (2.0, 0.2, 1.0), "candidate": (2.1, 0.5, 1.0)})
        self.assertIn("ghost not lower", verdict(**worse_ghost))
        worse_lobe = dict(GOOD, ratios={"flashmat": (2.0, 0.2, 1.0), "candidate": (1.4, 0.2, 1.0)})
        self.assertIn("lobe not higher", verdict(**worse_lobe))
        # 0.104 is 1.04x the bundled 0.100: past the 3% bound.
        worse_identity = dict(GOOD, lpips={"flashmat": BUNDLED_LPIPS, "candidate": (0.104, 0.2, 0.3)})
        self.assertIn("identity LPIPS 0.104 above 1.03x 0.100", verdict(**worse_identity))
        # |ln 0.75| = 0.288 against the bundled |ln 0.8| = 0.223.
        darker = dict(GOOD, brightness={"bundled": [0.8, 1.1], "candidate": [0.75, 1.0]})
        self.assertIn("photos' worst brightness |ln b| 0.288 against 0.223", verdict(**darker))


if __name__ == "__main__":
    unittest.main()
