"""The sampling half shared by flashmat's BSDFs: a reflection-only lobe
whose value comes from the class's `_value(si, wo, active) -> (value,
valid)`, sampled cosine-weighted over the upper hemisphere (the paper's
plugin does the same), with the matching pdf.

nanobind classes take one base, so this is a base class made per
variant (`cosine_sampled_base()`), subclassed by each BSDF.
"""

import drjit as dr
import mitsuba as mi


_BASES = {}


def cosine_sampled_base():
    """mi.BSDF subclass with the shared methods, for the current variant."""
    variant = mi.variant()
    if variant not in _BASES:

        class CosineSampledReflection(mi.BSDF):
            def _enabled(self, ctx):
                return ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 0)

            def eval(self, ctx, si, wo, active=True):
                if not self._enabled(ctx):
                    return mi.Color3f(0.0)
                value, _ = self._value(si, wo, active)
                return value

            def pdf(self, ctx, si, wo, active=True):
                if not self._enabled(ctx):
                    return mi.Float(0.0)
                ok = active & (mi.Frame3f.cos_theta(si.wi) > 0) & (mi.Frame3f.cos_theta(wo) > 0)
                return dr.select(ok, mi.warp.square_to_cosine_hemisphere_pdf(wo), 0.0)

            def eval_pdf(self, ctx, si, wo, active=True):
                return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

            def sample(self, ctx, si, sample1, sample2, active=True):
                bs = dr.zeros(mi.BSDFSample3f)
                if not self._enabled(ctx):
                    return bs, mi.Color3f(0.0)
                active = active & (mi.Frame3f.cos_theta(si.wi) > 0)
                bs.wo = mi.warp.square_to_cosine_hemisphere(sample2)
                bs.pdf = dr.select(active, mi.warp.square_to_cosine_hemisphere_pdf(bs.wo), 0.0)
                bs.eta = 1.0
                bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
                bs.sampled_component = mi.UInt32(0)
                value, ok = self._value(si, bs.wo, active)
                ok = ok & (bs.pdf > 0)
                weight = dr.select(ok, value / dr.select(ok, bs.pdf, 1.0), 0.0)
                return bs, weight

        _BASES[variant] = CosineSampledReflection
    return _BASES[variant]
