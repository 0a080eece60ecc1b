"""Renders a `flashmat fit` glTF (DIR/gltf/material.gltf) with Mitsuba 3.

Mitsuba has no glTF importer, so this reads the file the way a glTF viewer
does, with nothing but the JSON and the files it names: the mesh (POSITION,
TEXCOORD_0, indices from the buffer), the metallic-roughness material
(baseColorTexture as sRGB; metallicRoughnessTexture: roughness = G,
metallic = B, linear; normalTexture as a tangent-space map) and its factors.
The material becomes Mitsuba's `principled` BSDF (alpha = roughness^2 and
F0 = 0.04 for dielectrics, as in glTF) under a `normalmap`.

Usage: python scripts/render_gltf.py DIR/gltf/material.gltf OUT.png [--res 320] [--spp 64]
       (source scripts/env.sh first: Mitsuba 3 is in flashmat's Python environment)
"""
import argparse
import json
import math
import os

import numpy as np
import mitsuba as mi

COMPONENTS = {5126: np.float32, 5123: np.uint16, 5125: np.uint32}
WIDTHS = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4}


def accessor(doc, buffers, index):
    a = doc["accessors"][index]
    view = doc["bufferViews"][a["bufferView"]]
    data = buffers[view["buffer"]]
    start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
    dtype = COMPONENTS[a["componentType"]]
    width = WIDTHS[a["type"]]
    count = a["count"] * width
    return np.frombuffer(data, dtype=dtype, count=count, offset=start).reshape(a["count"], width)


def load(path):
    base = os.path.dirname(path)
    with open(path) as f:
        doc = json.load(f)
    buffers = []
    for b in doc["buffers"]:
        with open(os.path.join(base, b["uri"]), "rb") as f:
            buffers.append(f.read())
    prim = doc["meshes"][0]["primitives"][0]
    attrs = prim["attributes"]
    positions = accessor(doc, buffers, attrs["POSITION"]).astype(np.float32)
    uvs = accessor(doc, buffers, attrs["TEXCOORD_0"]).astype(np.float32)
    faces = accessor(doc, buffers, prim["indices"]).reshape(-1, 3).astype(np.uint32)
    material = doc["materials"][prim["material"]]

    def image(texture_info):
        tex = doc["textures"][texture_info["index"]]
        return os.path.join(base, doc["images"][tex["source"]]["uri"])

    return positions, uvs, faces, material, image


def bsdf_of(mi, material, image):
    pbr = material["pbrMetallicRoughness"]
    mr = np.array(mi.Bitmap(image(pbr["metallicRoughnessTexture"]))).astype(np.float32) / 255.0

    def channel(c, factor):
        return {"type": "bitmap", "data": mi.TensorXf(np.ascontiguousarray(mr[:, :, c:c + 1] * factor)), "raw": True, "filter_type": "bilinear"}

    principled = {
        "type": "principled",
        # An 8-bit PNG read with raw = False is decoded from sRGB to linear.
        "base_color": {"type": "bitmap", "filename": image(pbr["baseColorTexture"]), "raw": False},
        "roughness": channel(1, pbr.get("roughnessFactor", 1.0)),
        "metallic": channel(2, pbr.get("metallicFactor", 1.0)),
        "specular": 0.5,  # F0 = 0.08 * 0.5 = 0.04: glTF's dielectric
    }
    if "normalTexture" in material:
        return {"type": "normalmap", "normalmap": {"type": "bitmap", "filename": image(material["normalTexture"]), "raw": True}, "bsdf": principled}
    return principled


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("gltf")
    ap.add_argument("output")
    ap.add_argument("--res", type=int, default=320)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--camera", type=float, nargs=3, default=[0.0, -2.6, 3.0])
    ap.add_argument("--light", type=float, nargs=3, default=[0.9, 1.2, 1.6])
    args = ap.parse_args()
    mi.set_variant("llvm_ad_rgb" if "llvm_ad_rgb" in mi.variants() else "scalar_rgb")
    positions, uvs, faces, material, image = load(args.gltf)

    mesh = mi.Mesh("square", vertex_count=len(positions), face_count=len(faces), has_vertex_normals=False, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.ravel())
    # glTF puts UV (0, 0) at the image's top left; Mitsuba's bitmap lookups
    # put v = 0 at the bottom row, hence 1 - v.
    params["vertex_texcoords"] = mi.Float(np.stack([uvs[:, 0], 1.0 - uvs[:, 1]], 1).ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    # Mitsuba meshes get their BSDF when loaded: go through a PLY file.
    ply = args.output + ".square.ply"
    mesh.write_ply(ply)
    r0 = math.dist(args.light, (0.0, 0.0, 0.0))
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {
            "type": "perspective", "fov": 40, "fov_axis": "x",
            "to_world": mi.ScalarTransform4f().look_at(origin=args.camera, target=[0, 0, 0], up=[0, 0, 1]),
            "film": {"type": "hdrfilm", "width": args.res, "height": args.res, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": args.spp},
        },
        # Intensity pi r0^2: at the square's centre a pixel value is flashmat's R (no fall-off there).
        "light": {"type": "point", "position": args.light, "intensity": {"type": "rgb", "value": math.pi * r0 * r0}},
        "ambient": {"type": "constant", "radiance": {"type": "rgb", "value": 0.02}},
        "square": {"type": "ply", "filename": ply, "bsdf": bsdf_of(mi, material, image)},
    })
    os.remove(ply)
    img = mi.render(scene)
    mi.util.write_bitmap(args.output, img)
    print(f"wrote {args.output}")


if __name__ == "__main__":
    main()
