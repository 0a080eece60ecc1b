#version 300 es
// One layer of ND_enc or M_render (docs/NMAT.md, "Rendering one pixel") for
// NOUT groups of 4 output channels, one render target each. The viewer
// inserts after the first line:
//   NOUT   1..8 output groups (draw buffers) of this pass
//   MODE   0: input = the direction encoding of the pixel, computed here
//          1: input = the previous layer (uIn, tile-local texture array)
//          2: input = concat(neural map, direction code) (M_render layer 0)
//   FREQ   encoding frequencies F;  MAPG ceil(C / 4) map layers
precision highp float;
precision highp int;
precision highp sampler2D;
precision highp sampler2DArray;

uniform sampler2D uW;          // weights: texel (g, row) = W[row][4g .. 4g+3] (f16)
uniform int uRow0;             // texture row of this pass's first output channel
uniform int uInGroups;         // input groups of 4 channels (MODE 2: code groups only)
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
uniform vec3 uLight;
uniform vec3 uView;

OUTPUTS

// The map pixel (column, row from the top) a render pixel samples: the one
// under its centre (the identity at full resolution).
ivec2 mapPixel(ivec2 r) {
    return (ivec2(2) * r + ivec2(1)) * uMapSize / (ivec2(2) * uRender);
}

#if MODE == 0
float enc[9];

// wi, wo and h as flashmat computes them in f32: P = ((j, i) + 0.5) * step
// + (-1, 1); w = (X - P) / |X - P|; h = (wi + wo) / |wi + wo|.
void directions(ivec2 m) {
    vec2 xy = (vec2(m) + 0.5) * uStep + vec2(-1.0, 1.0);
    vec3 p = vec3(xy, 0.0);
    vec3 a = uLight - p;
    vec3 b = uView - p;
    vec3 wi = a / max(sqrt(a.x * a.x + a.y * a.y + a.z * a.z), 1e-12);
    vec3 wo = b / max(sqrt(b.x * b.x + b.y * b.y + b.z * b.z), 1e-12);
    vec3 s = wi + wo;
    vec3 h = s / max(sqrt(s.x * s.x + s.y * s.y + s.z * s.z), 1e-12);
    enc[0] = wi.x; enc[1] = wi.y; enc[2] = wi.z;
    enc[3] = wo.x; enc[4] = wo.y; enc[5] = wo.z;
    enc[6] = h.x; enc[7] = h.y; enc[8] = h.z;
}

// Channel n of [v (9) | sin(2^k pi v_c) (k-major) | cos(2^k pi v_c)], 0 past the end.
// The phase is pi * ((2^k v_c) mod 2), exact before the product, here moved
// to [-1, 1) so that sin and cos see arguments in [-pi, pi).
float encoding(int n) {
    if (n < 9) return enc[n];
    int j = n - 9;
    if (j >= 18 * FREQ) return 0.0;
    bool isCos = j >= 9 * FREQ;
    if (isCos) j -= 9 * FREQ;
    int k = j / 9;
    float t = enc[j - 9 * k] * float(1 << k);
    float r = t - 2.0 * floor((t + 1.0) * 0.5);
    float ph = 3.14159265358979 * r;
    return isCos ? cos(ph) : sin(ph);
}
#endif

void main() {
    ivec2 local = ivec2(gl_FragCoord.xy) - uTarget0;
    ivec2 rp = uTile + local;
    ivec2 mp = mapPixel(rp);
#if MODE == 0
    directions(mp);
#endif
    vec4 acc[NOUT];
    for (int o = 0; o < NOUT; o++) acc[o] = vec4(0.0);
#if MODE == 2
    int total = MAPG + uInGroups;
#else
    int total = uInGroups;
#endif
    for (int g = 0; g < total; g++) {
#if MODE == 0
        vec4 x = vec4(encoding(4 * g), encoding(4 * g + 1), encoding(4 * g + 2), encoding(4 * g + 3));
#elif MODE == 1
        vec4 x = texelFetch(uIn, ivec3(local, g), 0);
#else
        vec4 x;
        if (g < MAPG) {
            x = uMapOffset[g] + uMapScale[g] * texelFetch(uMap, ivec3(mp, g), 0);
        } else {
            x = texelFetch(uIn, ivec3(local, g - MAPG), 0);
        }
#endif
        for (int o = 0; o < NOUT; o++) {
            int r = uRow0 + 4 * o;
            // Columns = rows of W: (x * m)[j] = dot(x, W[r + j][4g .. 4g+3]).
            mat4 m = mat4(texelFetch(uW, ivec2(g, r), 0), texelFetch(uW, ivec2(g, r + 1), 0),
                          texelFetch(uW, ivec2(g, r + 2), 0), texelFetch(uW, ivec2(g, r + 3), 0));
            acc[o] += x * m;
        }
    }
    WRITES
}
