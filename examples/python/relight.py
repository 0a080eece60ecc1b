"""flashmat from Python, notebook style (docs/PYTHON.md).

    python examples/python/relight.py [OUT_DIR] [SIZE]

Estimates a bundled photo, relights it in a loop, shows the renders with
matplotlib (saved as OUT_DIR/relit.png), takes a gradient through `render`
and optimises the codes against a second photo. Each cell is a few lines.
"""
import math
import sys
from pathlib import Path

import torch

import flashmat

out = Path(sys.argv[1] if len(sys.argv) > 1 else "python-example")
size = int(sys.argv[2]) if len(sys.argv) > 2 else 128
out.mkdir(parents=True, exist_ok=True)
photos = Path(__file__).resolve().parents[1] / "photos"

# 1. Estimate: one flash photo in, a neural material out.
model = flashmat.load_model()  # the bundled model
material = model.estimate(photos / "IMG_20180104_210434.png", size=size)
print(material, "gain", [round(g, 3) for g in material.gain])

# 2. Relight in a loop: a light circling the material, camera overhead.
frames = []
with torch.no_grad():
    for i in range(6):
        a = 2 * math.pi * i / 6
        frames.append(material.render(light=(2 * math.cos(a), 2 * math.sin(a), 3.0)))

# 3. Show them (display transform: clamp, sRGB-ish gamma).
import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

fig, axes = plt.subplots(1, len(frames), figsize=(2 * len(frames), 2.2))
for ax, frame in zip(axes, frames):
    ax.imshow(frame.clamp(0, 1).pow(1 / 2.2).permute(1, 2, 0).numpy())
    ax.axis("off")
fig.savefig(out / "relit.png", dpi=80, bbox_inches="tight")
print("wrote", out / "relit.png")

# 4. A gradient through the renderer: how the brightness under a light
#    depends on each code.
codes = material.codes  # the material's own tensor [C, H, W]
codes.requires_grad_(True)
material.render(light=(1.0, 0.0, 2.0)).mean().backward()
print("d(mean radiance)/d(codes): |grad| mean", codes.grad.abs().mean().item())
codes.requires_grad_(False)

# 5. Optimise the codes so that the material's photo render matches a
#    second photo (another material): ten lines of plain PyTorch.
target = model.estimate(photos / "IMG_20180115_135508.png", size=size).input_photo
codes = material.codes.detach().clone().requires_grad_(True)
material.codes = codes  # the material now renders from this tensor
optimiser = torch.optim.Adam([codes], lr=0.05)
error = lambda: (torch.log1p(material.render(flashmat.OVERHEAD)) - torch.log1p(target)).abs().mean()
start = error().item()
for step in range(40):
    optimiser.zero_grad()
    loss = error()
    loss.backward()
    optimiser.step()
print(f"log error to the second photo: {start:.4f} -> {error().item():.4f}")
material.save(out / "optimised.nmat")
