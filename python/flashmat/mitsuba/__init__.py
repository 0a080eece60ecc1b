"""flashmat neural materials (.nmat) in Mitsuba 3: the `neural_brdf` BSDF,
plus `flashmat_ggx`, flashmat's ground-truth GGX SVBRDF (REFERENCE section 2).

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import flashmat.mitsuba
    flashmat.mitsuba.register()      # registers "neural_brdf" and "flashmat_ggx" for the current variant
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": "material.nmat", "mode": "texture"})

register() needs a Mitsuba variant; call it again after switching variants.
"""
from .nmat import NmatError, read_nmat, reference_log_radiance  # noqa: F401
from .bsdf import NeuralBRDF, correction_matrix, neural_brdf_class  # noqa: F401
from .ggx import flashmat_ggx_class, ggx_radiance, load_svbrdf  # noqa: F401

__all__ = [
    "NeuralBRDF", "NmatError", "correction_matrix", "flashmat_ggx_class", "ggx_radiance", "load_svbrdf",
    "read_nmat", "reference_log_radiance", "register",
]


def register():
    """Registers `neural_brdf` and `flashmat_ggx` for the current Mitsuba variant (call after mi.set_variant)."""
    import mitsuba as mi

    neural, ggx = neural_brdf_class(), flashmat_ggx_class()
    mi.register_bsdf("neural_brdf", lambda props: neural(props))
    mi.register_bsdf("flashmat_ggx", lambda props: ggx(props))
