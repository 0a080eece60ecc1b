"""The .nmat reader refuses damaged and foreign files with a clear ValueError."""
import json
import struct

import numpy as np
import pytest

from conftest import TINY_NMAT, synthetic_tensors, write_nmat
from flashmat.mitsuba.nmat import NmatError, read_nmat


def test_reads_synthetic(synthetic_nmat):
    nm = read_nmat(synthetic_nmat)
    assert nm.neural_map.shape == (16, 8, 8)
    assert nm.frequencies == 16 and len(nm.nd_enc) == 3 and len(nm.m_render) == 7


@pytest.mark.skipif(not TINY_NMAT.exists(), reason="fixture tests/fixtures/tiny.nmat missing")
def test_reads_flashmat_fixture():
    nm = read_nmat(TINY_NMAT)
    assert nm.meta["flashmat.format"] == "flashmat-nmat"
    assert nm.neural_map.shape[0] == nm.config["neural_channels"]


def expect_error(path, fragment):
    with pytest.raises(ValueError) as e:
        read_nmat(path)
    assert isinstance(e.value, NmatError)
    assert str(path) in str(e.value), str(e.value)
    assert fragment in str(e.value), str(e.value)


def test_damaged_byte(synthetic_nmat, tmp_path):
    data = bytearray(synthetic_nmat.read_bytes())
    data[-5] ^= 0x40
    p = tmp_path / "damaged.nmat"
    p.write_bytes(bytes(data))
    expect_error(p, "checksum mismatch")


def test_truncated(synthetic_nmat, tmp_path):
    data = synthetic_nmat.read_bytes()
    p = tmp_path / "truncated.nmat"
    p.write_bytes(data[: len(data) - 100])
    expect_error(p, "truncated")
    p.write_bytes(data[:5])
    expect_error(p, "too short")


def test_foreign_files(tmp_path):
    p = tmp_path / "photo.png"
    p.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(100))
    expect_error(p, "not a flashmat .nmat file")
    t, meta = synthetic_tensors()
    p = tmp_path / "model.safetensors"
    write_nmat(p, t, {**meta, "flashmat.format": "flashmat-model"})
    expect_error(p, "format tag 'flashmat-model'")
    # A safetensors file without flashmat metadata.
    header = json.dumps({"x": {"dtype": "F32", "shape": [1], "data_offsets": [0, 4]}}).encode()
    p = tmp_path / "plain.safetensors"
    p.write_bytes(struct.pack("<Q", len(header)) + header + np.float32(1).tobytes())
    expect_error(p, "no metadata")
    expect_error(tmp_path / "missing.nmat", "cannot read")


def test_other_version_and_shapes(tmp_path):
    t, meta = synthetic_tensors()
    p = tmp_path / "v5.nmat"
    write_nmat(p, t, {**meta, "flashmat.version": "5"})
    expect_error(p, "unsupported .nmat version '5'")
    t2 = dict(t)
    t2["renderer.m_render.6.weight"] = np.zeros((4, 8), np.float32)
    p = tmp_path / "shape.nmat"
    write_nmat(p, t2, meta)
    expect_error(p, "renderer.m_render.6.weight")


def test_plugin_raises_for_damaged_file(synthetic_nmat, tmp_path):
    from conftest import set_variant

    mi = set_variant("scalar_rgb")
    data = bytearray(synthetic_nmat.read_bytes())
    data[-1] ^= 1
    p = tmp_path / "bad.nmat"
    p.write_bytes(bytes(data))
    with pytest.raises(Exception) as e:
        mi.load_dict({"type": "neural_brdf", "filename": str(p)})
    assert "bad.nmat" in str(e.value) and "checksum" in str(e.value)


def test_header_checksum(tmp_path):
    """flashmat.meta_crc32 covers shapes and metadata, which flashmat.crc32 does not."""
    from flashmat.mitsuba.nmat import header_crc

    t, meta = synthetic_tensors(h=4, w=6)
    p = tmp_path / "sealed.nmat"
    write_nmat(p, t, meta)
    n = struct.unpack("<Q", p.read_bytes()[:8])[0]
    header = json.loads(p.read_bytes()[8 : 8 + n])
    meta_all = header.pop("__metadata__")
    write_nmat(p, t, {**meta, "flashmat.meta_crc32": f"{header_crc(header, meta_all):08x}"})
    assert read_nmat(p).neural_map.shape == (16, 4, 6)
    # Swapped dimensions and resolution: the tensor CRC still matches, the header CRC does not.
    sealed = {**meta, "flashmat.meta_crc32": f"{header_crc(header, meta_all):08x}", "resolution": json.dumps([6, 4])}
    swapped = {k: (v.reshape(v.shape[0], 6, 4) if k in ("neural_map", "input_photo") else v) for k, v in t.items()}
    bad = tmp_path / "swapped.nmat"
    write_nmat(bad, swapped, sealed)
    expect_error(bad, "header checksum mismatch")
    # A flip in the checksum's key name, prefix included, is damage, not an old file.
    for key in ("flashmat.meta_crc33", "blashmat.meta_crc32", "flaslmat.meta_crc32"):
        renamed = tmp_path / "renamed.nmat"
        write_nmat(renamed, t, {**meta, key: f"{header_crc(header, meta_all):08x}"})
        expect_error(renamed, "unknown integrity field")


def test_gain_of_versions_3_and_4(tmp_path):
    """Version 3's exposure gain (one number) and version 4's (one per channel) are read as (r, g, b); 1 when absent,
    as in versions 1 and 2; a gain that is not a positive number, or three of them, is refused."""
    t, meta = synthetic_tensors()
    p = tmp_path / "v1.nmat"
    write_nmat(p, t, meta)
    assert read_nmat(p).gain == (1.0, 1.0, 1.0)
    write_nmat(p, t, {**meta, "flashmat.version": "3", "gain": "0.0625"})
    assert read_nmat(p).gain == (0.0625, 0.0625, 0.0625)
    write_nmat(p, t, {**meta, "flashmat.version": "4", "gain": "[0.5, 0.25, 0.125]"})
    assert read_nmat(p).gain == (0.5, 0.25, 0.125)
    for bad in ("0", "-1", "nan", "inf", "bright", "[1, 2]", "[1, 0, 1]", "[1, true, 1]", '"1"'):
        write_nmat(p, t, {**meta, "flashmat.version": "4", "gain": bad})
        expect_error(p, "metadata field 'gain' must be a positive number")
