"""The Python API (flashmat, python/src/lib.rs): results equal the CLI's,
tensors cross without copies, gradients are right, bad input raises."""
import subprocess
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

import flashmat
from conftest import FIXTURES, REPO, TINY_NMAT, find_flashmat

PHOTO = REPO / "examples" / "photos" / "IMG_20180104_210434.png"
SIZE = 64  # small maps keep the dev-profile build's tests quick
LIGHT = (0.8, -0.5, 2.5)
VIEW = (0.3, 0.2, 3.0)
needs_cli = pytest.mark.skipif(find_flashmat() is None, reason="flashmat binary not built (cargo build)")


@pytest.fixture(scope="module")
def model():
    return flashmat.load_model()


@pytest.fixture(scope="module")
def estimated(model):
    return model.estimate(PHOTO, size=SIZE)


def read_exr(path):
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    return torch.from_numpy(np.array(mi.Bitmap(str(path)), dtype=np.float32)).permute(2, 0, 1)


@needs_cli
def test_estimate_equals_the_cli(model, estimated, tmp_path):
    out = tmp_path / "cli.nmat"
    subprocess.run([find_flashmat(), "estimate", str(PHOTO), "-o", str(out), "--size", str(SIZE)], check=True, capture_output=True)
    cli = flashmat.load(out)
    assert cli.size == estimated.size == (SIZE, SIZE)
    # Same library calls on the same photo, same thread count: bit for bit.
    assert torch.equal(estimated.codes, cli.codes)
    assert estimated.gain == cli.gain
    assert torch.equal(estimated.input_photo, cli.input_photo)
    # Pixels of the same photo give the same material as its file.
    import mitsuba as mi

    mi.set_variant("scalar_rgb")
    pixels = np.array(mi.Bitmap(str(PHOTO)))  # [H, W, 3] uint8, sRGB
    assert pixels.dtype == np.uint8
    from_pixels = model.estimate(pixels, size=SIZE)
    assert torch.equal(from_pixels.codes, cli.codes)
    chw = torch.from_numpy(pixels).permute(2, 0, 1).float() / 255
    from_floats = model.estimate(chw, size=SIZE, encoding="srgb")
    assert torch.equal(from_floats.codes, cli.codes)


@needs_cli
def test_render_equals_the_cli(estimated, tmp_path):
    nmat = tmp_path / "m.nmat"
    estimated.save(nmat)
    out = tmp_path / "relit.exr"
    light, view = ",".join(map(str, LIGHT)), ",".join(map(str, VIEW))
    subprocess.run([find_flashmat(), "relight", str(nmat), "--light", light, "--view", view, "-o", str(out)], check=True, capture_output=True)
    cli = read_exr(out)
    with torch.no_grad():
        py = flashmat.load(nmat).render(LIGHT, VIEW)
    assert py.shape == (3, SIZE, SIZE) and py.dtype == torch.float32
    # EXR keeps f32; the CLI renders in row bands, Python in one piece,
    # with the same per-pixel arithmetic: bit for bit.
    assert torch.equal(py, cli)
    assert py.mean() > 0.01


def test_a_batch_of_lights_renders_each(estimated):
    with torch.no_grad():
        lights = [LIGHT, (0.0, 0.0, 3.0), (-1.0, 1.0, 2.0)]
        batch = estimated.render(lights, VIEW)
        assert batch.shape == (3, 3, SIZE, SIZE)
        for k, light in enumerate(lights):
            torch.testing.assert_close(batch[k], estimated.render(light, VIEW), rtol=1e-5, atol=1e-6)
        half = estimated.render(LIGHT, VIEW, size=SIZE // 2)
        assert half.shape == (3, SIZE // 2, SIZE // 2)
        # Bilinear codes at half the resolution: close to the render's 2x2 means.
        pooled = torch.nn.functional.avg_pool2d(batch[0][None], 2)[0]
        assert (half - pooled).abs().mean() < 0.2 * pooled.mean()


def test_codes_are_shared_not_copied(estimated):
    m = estimated.clone()
    codes = m.codes
    assert codes.dim() == 3 and codes.shape[1:] == (SIZE, SIZE)
    assert m.codes.data_ptr() == codes.data_ptr() == m.codes.data_ptr()
    before = m.render(LIGHT).detach()
    with torch.no_grad():
        codes[:, : SIZE // 2] = m.codes[:, SIZE // 2 :].clone()  # a change made in Python ...
    after = m.render(LIGHT).detach()
    # ... shows in the next render: the left half now renders the right half's codes.
    assert not torch.equal(before[:, : SIZE // 2], after[:, : SIZE // 2])
    torch.testing.assert_close(after[:, SIZE // 2 :], before[:, SIZE // 2 :])
    # Renders, photos, weights and fitted maps come back as the library's
    # own tensors: every one of their pointers lies in memory flashmat owns.
    assert m.input_photo.data_ptr() == m.input_photo.data_ptr()
    params = m.parameters()
    assert all(p.data_ptr() == q.data_ptr() for p, q in zip(params.values(), m.parameters().values()))
    # Refinement writes back into the same memory.
    m.refine(steps=2)
    assert m.codes.data_ptr() == codes.data_ptr()
    # An assigned tensor is used as it is.
    new = torch.zeros_like(codes)
    m.codes = new
    assert m.codes.data_ptr() == new.data_ptr()


def random_directions(h, w, seed):
    gen = torch.Generator().manual_seed(seed)
    tilt = torch.rand(h, w, 3, generator=gen) * torch.tensor([1.0, 1.0, 0.0]) - torch.tensor([0.5, 0.5, -1.0])
    return torch.nn.functional.normalize(tilt, dim=-1)


def check_gradients(m, points, eps):
    """Autograd's gradients of a weighted sum of render_dirs against central
    differences at `points` [(name, index)] of the codes ("codes") and the
    first renderer weight ("weight")."""
    h, w = m.size
    wi, wo = random_directions(h, w, 1), random_directions(h, w, 2)
    weights = torch.rand(3, h, w, generator=torch.Generator().manual_seed(3))
    tensors = {"codes": m.codes, "weight": next(iter(m.parameters().values()))}
    for t in tensors.values():
        t.requires_grad_(True)
    (m.render_dirs(wi, wo) * weights).sum().backward()

    def objective():
        with torch.no_grad():
            # Summed in float64: only the render itself is float32.
            return (m.render_dirs(wi, wo).double() * weights.double()).sum().item()

    for name, index in points:
        t = tensors[name]
        with torch.no_grad():
            t[index] += eps
            up = objective()
            t[index] -= 2 * eps
            down = objective()
            t[index] += eps
        numeric = (up - down) / (2 * eps)
        assert t.grad[index].item() == pytest.approx(numeric, rel=2e-2, abs=1e-3), (name, index)
    for t in tensors.values():
        t.requires_grad_(False)


def reference_render(m, wi, wo):
    """docs/NMAT.md's "Rendering one pixel" in float64 torch, from the
    material's codes and weights: wi, wo [H, W, 3] -> R [3, H, W]."""
    p = {k: v.detach().double() for k, v in m.parameters().items()}
    v = torch.cat([wi, wo, torch.nn.functional.normalize(wi + wo, dim=-1)], -1)
    f = (p["renderer.nd_enc.0.weight"].shape[1] - 9) // 18
    phase = torch.cat([v * 2.0**k for k in range(f)], -1)
    phase = phase - 2 * torch.floor(phase / 2)
    x = torch.cat([v, torch.sin(torch.pi * phase), torch.cos(torch.pi * phase)], -1)
    for i in range(3):
        x = x @ p[f"renderer.nd_enc.{i}.weight"].T
        x = torch.nn.functional.leaky_relu(x, 0.01) if i < 2 else x
    x = torch.cat([m.codes.double().permute(1, 2, 0), x], -1) @ p["renderer.m_render.0.weight"].T
    layers = sum(k.startswith("renderer.m_render.") for k in p)
    for i in range(1, layers):
        x = torch.nn.functional.leaky_relu(x @ p[f"renderer.m_render.{i}.weight"].T, 0.01 if i < layers - 1 else 0.001)
    r = (torch.exp(x.clamp_max(80)) - 1).clamp_min(0) * torch.tensor(m.gain, dtype=torch.float64)
    return r.permute(2, 0, 1)


def test_render_is_differentiable_in_codes_weights_and_directions():
    # Central differences of the float32 renderer, within 2%: eps 1e-2
    # keeps rounding noise (~1e-7 of a pixel's radiance / eps) and
    # curvature error (~eps^2) small against these gradients.
    check_gradients(flashmat.load(TINY_NMAT), [("codes", (0, 1, 2)), ("codes", (5, 3, 3)), ("weight", (0, 0)), ("weight", (7, 20))], 1e-2)
    # Directions: ND_enc's top frequency (2^15 pi) makes the float32 render
    # vary within its own rounding of a direction (difference quotients of
    # a direction scatter by tens of percent), so the directions' gradients
    # are checked against autograd of the same network in float64
    # (reference_render), whose values must match the render first.
    m = flashmat.load(TINY_NMAT)
    h, w = m.size
    wi, wo = random_directions(h, w, 1), random_directions(h, w, 2)
    with torch.no_grad():
        torch.testing.assert_close(torch.log1p(m.render_dirs(wi, wo)).double(), torch.log1p(reference_render(m, wi.double(), wo.double())), rtol=1e-4, atol=1e-4)
    # With the encoding's weights for 4 pi and up set to zero (in place: the
    # material renders from its parameters' own memory), float32 and float64
    # gradients agree to rounding (3e-7 measured); at full frequency one
    # entry in a hundred differs by percents: float32's rounding of the
    # phase, times 2^15 pi.
    enc = m.parameters()["renderer.nd_enc.0.weight"]  # [hidden, 9 + 18 f]: v, sin(2^k pi v), cos(2^k pi v)
    f = (enc.shape[1] - 9) // 18
    with torch.no_grad():
        for k in range(2, f):
            enc[:, 9 + 9 * k : 9 + 9 * (k + 1)] = 0
            enc[:, 9 + 9 * f + 9 * k : 9 + 9 * f + 9 * (k + 1)] = 0
    weights = torch.rand(3, h, w, generator=torch.Generator().manual_seed(3))
    # ln(1 + R): the radiance spans seven decades for this tiny model.
    wi.requires_grad_(True)
    (torch.log1p(m.render_dirs(wi, wo)) * weights).sum().backward()
    wi64 = wi.detach().double().requires_grad_(True)
    (torch.log1p(reference_render(m, wi64, wo.double())) * weights.double()).sum().backward()
    assert wi64.grad.abs().max() > 0.01  # gradients worth comparing (0.022 here)
    torch.testing.assert_close(wi.grad.double(), wi64.grad, rtol=1e-4, atol=1e-5 * wi64.grad.abs().max().item())


def test_render_dirs_equals_render_for_the_same_directions(estimated):
    # The overhead camera and a point light, as directions per pixel.
    h, w = estimated.size
    xs = (torch.arange(w) + 0.5) / w * 2 - 1
    ys = 1 - (torch.arange(h) + 0.5) / h * 2
    p = torch.stack([xs[None, :].expand(h, w), ys[:, None].expand(h, w), torch.zeros(h, w)], -1)
    to = lambda q: torch.nn.functional.normalize(torch.tensor(q) - p, dim=-1)
    with torch.no_grad():
        torch.testing.assert_close(estimated.render_dirs(to(LIGHT), to(VIEW)), estimated.render(LIGHT, VIEW), rtol=1e-3, atol=1e-4)


def test_save_load_round_trip_and_pbr_maps(estimated, tmp_path):
    path = tmp_path / "a.nmat"
    estimated.save(path)
    back = flashmat.load(path)
    assert torch.equal(back.codes, estimated.codes) and back.gain == estimated.gain
    maps = estimated.fit(steps=5, samples=8, output=tmp_path / "pbr")
    assert maps["diffuse"].shape == (3, SIZE, SIZE) and maps["roughness"].shape == (1, SIZE, SIZE)
    assert torch.allclose(maps["normal"].norm(dim=0), torch.ones(SIZE, SIZE), atol=1e-4)
    assert 0 <= maps["metallic"].min() and maps["metallic"].max() <= 1
    # Maps share the fit's one tensor.
    assert maps["diffuse"].untyped_storage().data_ptr() == maps["specular"].untyped_storage().data_ptr()
    assert (tmp_path / "pbr" / "fit.json").is_file()
    estimated.view(tmp_path / "m.html")
    assert (tmp_path / "m.html").read_text().startswith("<!DOCTYPE html>")


def test_capture_folders_make_a_material(tmp_path):
    exe = find_flashmat()
    if exe is None:
        pytest.skip("flashmat binary not built (cargo build)")
    folder = tmp_path / "capture"
    subprocess.run([exe, "svbrdf", "captures", "--svbrdf", "procedural-test:3", "--size", "64", "--photos", "3", "-o", str(folder)], check=True, capture_output=True)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        m = flashmat.capture(folder, photos=3, size=32, steps=20)
    assert m.size == (32, 32)
    with torch.no_grad():
        assert m.render(LIGHT).mean() > 0
    # A size the memory allowed cannot reach: refused before any work, as the CLI refuses it.
    with pytest.raises(Exception, match='needs about .* GiB, more than max_memory="1G"'):
        flashmat.capture(folder, photos=3, size=4096, max_memory="1G")


@pytest.mark.parametrize(
    "photo, kwargs, error, words",
    [
        (REPO / "no-such-photo.png", {}, FileNotFoundError, "no-such-photo.png"),
        (torch.rand(2, 32, 32), {"encoding": "linear"}, ValueError, "[3, H, W] or [H, W, 3]"),
        (torch.zeros(32, 32, 3, dtype=torch.int32), {}, ValueError, "uint8 or floats"),
        (torch.rand(3, 32, 32), {}, ValueError, "encoding='srgb'"),
        (torch.full((3, 32, 32), float("nan")), {"encoding": "linear"}, ValueError, "NaN"),
        (torch.rand(3, 32, 32) * 3, {"encoding": "srgb"}, ValueError, "encoding='linear'"),
        (torch.zeros(3, 32, 32), {"encoding": "linear"}, ValueError, "black"),
        (PHOTO, {"exposure_mode": "sideways"}, ValueError, "exposure_mode"),
        (PHOTO, {"size": 60}, ValueError, "multiple of 8"),
        ("x", {"encoding": "srgb"}, ValueError, "encoding is for pixels"),
    ],
)
def test_bad_photos_raise_one_clear_error(model, photo, kwargs, error, words):
    with pytest.raises(error) as info:
        model.estimate(photo, **kwargs)
    assert words in str(info.value) and "\n" not in str(info.value)


def test_bad_files_and_arguments_raise(estimated, tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        flashmat.load(tmp_path / "missing.nmat")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        flashmat.load_model(tmp_path / "missing.safetensors")
    foreign = tmp_path / "other.safetensors"
    # A valid safetensors file that is no flashmat file.
    header = b'{"w":{"dtype":"F32","shape":[1],"data_offsets":[0,4]}}'
    foreign.write_bytes(len(header).to_bytes(8, "little") + header + b"\0\0\0\0")
    for load in (flashmat.load, flashmat.load_model):
        with pytest.raises(ValueError, match="flashmat"):
            load(foreign)
    with pytest.raises(ValueError, match="z"):
        estimated.render((0.0, 0.0, -1.0))
    with pytest.raises(ValueError, match="light .* and view"):
        estimated.render([LIGHT, LIGHT], [VIEW, VIEW, VIEW])
    with pytest.raises(TypeError):
        estimated.render("up")
    with pytest.raises(ValueError, match=r"\[H, W, 3\]"):
        estimated.render_dirs(torch.zeros(3, SIZE, SIZE), torch.zeros(3, SIZE, SIZE))
    with pytest.raises(ValueError, match="NaN"):
        d = torch.full((SIZE, SIZE, 3), float("nan"))
        estimated.render_dirs(d, d)
    with pytest.raises(ValueError, match="codes must be"):
        estimated.clone().codes = torch.zeros(3, 3)
    with pytest.raises(TypeError, match="torch.Tensor"):
        estimated.render_dirs(np.zeros((SIZE, SIZE, 3)), np.zeros((SIZE, SIZE, 3)))
    with pytest.raises(ValueError, match="device"):
        estimated.to("gpu7")
    with pytest.raises(ValueError, match=".nmat"):
        estimated.save(tmp_path / "x.png")


def test_the_notebook_example_runs(tmp_path):
    import sys

    r = subprocess.run([sys.executable, str(REPO / "examples" / "python" / "relight.py"), str(tmp_path), "32"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "relit.png").stat().st_size > 1000 and (tmp_path / "optimised.nmat").is_file()
    # The ten-line optimisation brings the photo render toward the second photo.
    line = next(l for l in r.stdout.splitlines() if l.startswith("log error"))
    start, end = (float(v) for v in line.split(":")[1].split("->"))
    assert end < 0.5 * start


def test_running_out_of_memory_raises_memory_error(monkeypatch):
    m = flashmat.load(TINY_NMAT)
    # A render of 10^8 x 10^8 pixels: libtorch's allocator refuses its
    # codes (2.4e18 bytes) at once, a panic inside tch that must come out
    # as MemoryError with the CLI's line, and leave grad mode as it was.
    monkeypatch.setenv("FLASHMAT_MAX_MATERIAL_SIZE", str(10**8))
    with pytest.raises(MemoryError, match=r"^out of memory \(tried to allocate .* GiB\): lower max_memory"):
        m.render(LIGHT, size=10**8)
    assert torch.is_grad_enabled()
    assert m.render(LIGHT).shape == (3, *m.size)


def test_materials_move_between_devices():
    m = flashmat.load(TINY_NMAT)
    for device in ("cpu", torch.device("cpu")):
        c = m.to(device)
        assert c.device == "cpu" and torch.equal(c.codes, m.codes)
    if not torch.cuda.is_available():
        pytest.skip("no CUDA device here: the CUDA half of this test runs on a GPU machine")
    g = m.to("cuda")
    assert g.device == "cuda:0" and g.codes.is_cuda
    with torch.no_grad():
        torch.testing.assert_close(g.render(LIGHT).cpu(), m.render(LIGHT), rtol=1e-4, atol=1e-5)
    codes = g.codes.requires_grad_(True)
    g.render(LIGHT).sum().backward()
    assert codes.grad is not None and codes.grad.is_cuda


def test_another_torch_version_is_refused_at_import():
    import sys

    code = "import torch; torch.__version__ = '2.10.0'; import flashmat"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("ImportError: flashmat was built against torch 2.11") and "torch 2.10.0" in last, last


@needs_cli
def test_errors_carry_the_cli_line(model, tmp_path):
    foreign = tmp_path / "foreign.nmat"
    foreign.write_bytes(b"not a safetensors file at all")
    cases = [
        (["estimate", str(tmp_path / "gone.png"), "-o", str(tmp_path / "x.nmat")], lambda: model.estimate(tmp_path / "gone.png"), FileNotFoundError),
        (["relight", str(foreign), "--light", "0,0,3", "-o", str(tmp_path / "x.png")], lambda: flashmat.load(foreign), ValueError),
    ]
    for args, call, error in cases:
        r = subprocess.run([find_flashmat(), *args], capture_output=True, text=True)
        line = r.stderr.strip().splitlines()[-1]
        assert r.returncode == 1 and line.startswith("error: ")
        with pytest.raises(error) as info:
            call()
        assert str(info.value) == line[len("error: "):]
