#version 300 es
// Display pass: the network's ln(1 + R) (or the input photo) to screen
// values as `flashmat relight` writes PNGs: R = exp(out) - 1 (out clamped
// at 80, R at 0) times the material's gain, times the exposure, the sRGB
// curve of clamp(., 0, 1) (`spaces::photo_encode`).
precision highp float;
precision highp int;
precision highp sampler2D;

uniform sampler2D uOut;    // ln(1 + R), render pixels, row 0 = top
uniform sampler2D uPhoto;  // linear input photo, map pixels, row 0 = top
uniform int uShowPhoto;
uniform float uExposure;
uniform vec3 uGain;        // the material's exposure gain per channel (.nmat `gain`): network radiance to the photo's
uniform ivec2 uRender;     // render resolution of uOut's valid part
uniform ivec2 uCanvas;     // canvas = map size (the display scales it)
out vec4 color;

float expm1(float x) {
    return abs(x) < 1e-3 ? x + 0.5 * x * x : exp(x) - 1.0;
}

void main() {
    ivec2 c = ivec2(int(gl_FragCoord.x), uCanvas.y - 1 - int(gl_FragCoord.y));
    vec3 radiance;
    if (uShowPhoto == 1) {
        radiance = texelFetch(uPhoto, c, 0).rgb;
    } else {
        ivec2 r = c * uRender / uCanvas;
        vec3 o = min(texelFetch(uOut, r, 0).rgb, vec3(80.0));
        radiance = max(vec3(expm1(o.r), expm1(o.g), expm1(o.b)), vec3(0.0)) * uGain;
    }
    vec3 v = clamp(radiance * uExposure, 0.0, 1.0);
    vec3 srgb = mix(1.055 * pow(v, vec3(1.0 / 2.4)) - 0.055, 12.92 * v, vec3(lessThanEqual(v, vec3(0.0031308))));
    color = vec4(srgb, 1.0);
}
