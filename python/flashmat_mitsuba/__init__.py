"""flashmat neural materials (.nmat) in Mitsuba 3: the `neural_brdf` BSDF.

    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    import flashmat_mitsuba
    flashmat_mitsuba.register()      # registers "neural_brdf" for the current variant
    bsdf = mi.load_dict({"type": "neural_brdf", "filename": "material.nmat", "mode": "texture"})

register() needs a Mitsuba variant; call it again after switching variants.
"""
from .nmat import NmatError, read_nmat, reference_log_radiance  # noqa: F401
from .bsdf import NeuralBRDF, neural_brdf_class, register  # noqa: F401

__all__ = ["NeuralBRDF", "NmatError", "read_nmat", "reference_log_radiance", "register"]
