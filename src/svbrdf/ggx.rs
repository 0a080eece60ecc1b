//! The constants of the paper's GGX model (REFERENCE section 2), in one
//! place for the f64 oracle (`scalar`), the f32 CPU renderer (`cpu`) and the
//! tensor renderer (`render`). The Mitsuba plugin reads the same values
//! from `python/flashmat/mitsuba/constants.py`; a test below keeps the two
//! files equal.

/// Clamp below every dot product of the model (n.h, n.v, n.l, v.h), the
/// GGX D denominator and the Schlick-GGX k.
pub const DOT_EPS: f64 = 1e-8;

/// Spherical-Gaussian Schlick Fresnel: F = ks + (1 - ks) 2^((A v.h + B) v.h).
pub const FRESNEL_SG_A: f64 = -5.55473;
pub const FRESNEL_SG_B: f64 = -6.98316;

/// Added to 4 (n.l)(n.v) in the specular denominator.
pub const SPECULAR_DENOM_EPS: f64 = 1e-12;

#[cfg(test)]
mod tests {
    use super::*;

    /// The Python plugin's constants module holds the same numbers.
    #[test]
    fn python_constants_match() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/python/flashmat/mitsuba/constants.py");
        let text = std::fs::read_to_string(path).unwrap();
        let value = |name: &str| -> f64 {
            let line = text.lines().find(|l| l.starts_with(&format!("{name} = "))).unwrap_or_else(|| panic!("{name} missing in {path}"));
            line.split('=').nth(1).unwrap().split('#').next().unwrap().trim().parse().unwrap()
        };
        assert_eq!(value("DOT_EPS"), DOT_EPS);
        assert_eq!(value("FRESNEL_SG_A"), FRESNEL_SG_A);
        assert_eq!(value("FRESNEL_SG_B"), FRESNEL_SG_B);
        assert_eq!(value("SPECULAR_DENOM_EPS"), SPECULAR_DENOM_EPS);
        // F(v.h = 1) = ks + (1 - ks) 2^(A + B): 2^-12.53789 = 1.68159e-4.
        assert!((2f64.powf(FRESNEL_SG_A + FRESNEL_SG_B) - 1.68159e-4).abs() < 1e-9);
    }
}
