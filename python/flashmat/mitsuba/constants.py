"""Constants of the paper's GGX model (REFERENCE section 2), shared by the
numpy and Dr.Jit GGX code of this package. The Rust side holds the same
values in src/svbrdf/ggx.rs; its test `python_constants_match` keeps them equal."""

DOT_EPS = 1e-8  # clamp below every dot product, the D denominator and k
FRESNEL_SG_A = -5.55473  # F = ks + (1 - ks) * 2**((A * voh + B) * voh)
FRESNEL_SG_B = -6.98316
SPECULAR_DENOM_EPS = 1e-12  # added to 4 * nol * nov
