#version 300 es
// One layer of ND_enc or M_render (docs/NMAT.md, "Rendering one pixel") for
// NOUT groups of 4 output channels, one render target each. The viewer
// inserts after the first line:
//   NOUT   1..8 output groups (draw buffers) of this pass
//   MODE   0: input = the direction encoding of the pixel, computed here
//          1: input = the previous layer (uIn, tile-local texture array)
//          2: input = concat(neural map, direction code) (M_render layer 0)
//   FB     ceil(F / 4) blocks of encoding frequencies;  MAPG ceil(C / 4) map layers
//   NW     vec4s of the weight block
//   OUTPUTS, DECLARE, ACCUMULATE, WRITE: NOUT copies of the output
//          declarations, accumulator declarations, ACC(o, a_o) and writes.
precision highp float;
precision highp int;
precision highp sampler2DArray;

// This pass's weights: NOUT x 4 rows of uInGroups vec4s, row-major,
// vec4 (4o + j) * uInGroups + g = W[4o + j][4g .. 4g+3] (rows of this pass,
// columns in the shader's input order). A uniform block: every pixel reads
// the same weights (the GPU's constant cache).
layout(std140) uniform Weights { vec4 uWB[NW]; };
uniform int uInGroups;         // input groups of 4 channels (MODE 2: map groups included)
uniform float uSlope;          // LeakyReLU slope after the layer; 1 = none
uniform sampler2DArray uIn;    // previous layer's output, tile-local
uniform sampler2DArray uMap;   // neural map, map pixels, row 0 = top
uniform vec4 uMapOffset[MAPG]; // 8-bit maps: value = offset + scale * texel; f16: 0 and 1
uniform vec4 uMapScale[MAPG];
uniform ivec2 uTarget0;        // target pixel of the tile's first pixel
uniform ivec2 uTile;           // render pixel (column, row from the top) of the tile's first pixel
uniform ivec2 uRender;         // render resolution (columns, rows)
uniform ivec2 uMapSize;        // map columns, rows
uniform vec2 uStep;            // (2 / W, -2 / H) as f32, as flashmat rounds them
uniform vec2 uExtent;          // half-extents (W, H) / min(W, H): the shorter side spans [-1, 1]
uniform vec3 uLight;
uniform vec3 uView;

// acc += x times the 4 x 4 block of weights of output group o at input group g:
// mat4 columns = rows of W, so (x * m)[j] = dot(x, W[4o + j][4g .. 4g+3]).
#define ACC(o, acc) { int r = 4 * (o) * uInGroups + g; acc += x * mat4(uWB[r], uWB[r + uInGroups], uWB[r + 2 * uInGroups], uWB[r + 3 * uInGroups]); }

OUTPUTS

// The map pixel (column, row from the top) a render pixel samples: the one
// under its centre (the identity at full resolution).
ivec2 mapPixel(ivec2 r) {
    return (ivec2(2) * r + ivec2(1)) * uMapSize / (ivec2(2) * uRender);
}

#if MODE == 0
// pi * ((2^k v) mod 2) of t = 2^k v (exact in floating point), taken in
// [-1, 1) instead of [0, 2) so that sin and cos see arguments in [-pi, pi).
vec4 phase(vec4 t) {
    return 3.14159265358979 * (t - 2.0 * floor((t + 1.0) * 0.5));
}
#endif

void main() {
    ivec2 local = ivec2(gl_FragCoord.xy) - uTarget0;
    ivec2 mp = mapPixel(uTile + local);
    DECLARE
#if MODE == 0
    // wi, wo and h as flashmat computes them in f32: P = (((j, i) + 0.5) * step
    // + (-1, 1)) * extent (geometry::pixel_positions; extent (1, 1) for square
    // maps); w = (X - P) / |X - P|; h = (wi + wo) / |wi + wo|.
    vec3 p = vec3(((vec2(mp) + 0.5) * uStep + vec2(-1.0, 1.0)) * uExtent, 0.0);
    vec3 a = uLight - p;
    vec3 b = uView - p;
    vec3 wi = a / max(sqrt(a.x * a.x + a.y * a.y + a.z * a.z), 1e-12);
    vec3 wo = b / max(sqrt(b.x * b.x + b.y * b.y + b.z * b.z), 1e-12);
    vec3 s = wi + wo;
    vec3 h = s / max(sqrt(s.x * s.x + s.y * s.y + s.z * s.z), 1e-12);
    // The encoding in the column order of the packed weights (viewer::encoding_column).
    vec4 v0 = vec4(wi, wo.x), v1 = vec4(wo.yz, h.xy);
    int g = 0;
    vec4 x = v0;
    ACCUMULATE g++;
    x = v1;
    ACCUMULATE g++;
    x = vec4(h.z, 0.0, 0.0, 0.0);
    ACCUMULATE g++;
    for (int blk = 0; blk < FB; blk++) {
        for (int kk = 0; kk < 4; kk++) {
            float scale = float(1 << (4 * blk + kk));
            vec4 p0 = phase(v0 * scale), p1 = phase(v1 * scale);
            x = sin(p0);
            ACCUMULATE g++;
            x = cos(p0);
            ACCUMULATE g++;
            x = sin(p1);
            ACCUMULATE g++;
            x = cos(p1);
            ACCUMULATE g++;
        }
        int k0 = 4 * blk;
        vec4 p2 = phase(h.z * vec4(float(1 << k0), float(1 << (k0 + 1)), float(1 << (k0 + 2)), float(1 << (k0 + 3))));
        x = sin(p2);
        ACCUMULATE g++;
        x = cos(p2);
        ACCUMULATE g++;
    }
#else
    for (int g = 0; g < uInGroups; g++) {
#if MODE == 1
        vec4 x = texelFetch(uIn, ivec3(local, g), 0);
#else
        vec4 x;
        if (g < MAPG) {
            x = uMapOffset[g] + uMapScale[g] * texelFetch(uMap, ivec3(mp, g), 0);
        } else {
            x = texelFetch(uIn, ivec3(local, g - MAPG), 0);
        }
#endif
        ACCUMULATE
    }
#endif
    WRITE
}
