//! The fitted GGX maps as an evaluation method: `flashmat eval --model
//! FILE+fit` (or `FILE+fitSTEPS`) estimates a neural material with the
//! flashmat model FILE, fits GGX maps to it ([`super::fit_material`]) and
//! re-renders those maps with the GGX renderer, so the Reflect / Identity /
//! Hemisphere table shows what the analytic export loses against the
//! neural material (row `NAME`) and the analytic baseline network.

use super::{Method, ModelMethod};
use crate::fit::{fit_material, FitConfig};
use crate::geometry::LightView;
use anyhow::{Context, Result};
use std::path::Path;
use tch::{Device, Tensor};

/// Suffix of a `--model` value that selects the fitted variant.
pub const FIT_SUFFIX: &str = "+fit";

/// Row name of a model's fitted variant: `NAME+fitSTEPS`.
pub fn fitted_name(name: &str, steps: usize) -> String {
    format!("{name}{FIT_SUFFIX}{steps}")
}

/// `FILE+fit` -> (FILE, default steps), `FILE+fitSTEPS` -> (FILE, STEPS);
/// None for any other `--model` value.
pub fn split_fit_spec(spec: &str) -> Option<(&str, usize)> {
    let (path, steps) = spec.rsplit_once(FIT_SUFFIX)?;
    if path.is_empty() {
        return None;
    }
    if steps.is_empty() {
        return Some((path, FitConfig::default().steps));
    }
    Some((path, steps.parse().ok()?))
}

/// A flashmat model whose estimates are fitted with GGX maps and relit by
/// the GGX renderer.
pub struct FitMethod {
    name: String,
    model: ModelMethod,
    config: FitConfig,
    /// `[1, 10, H, W]` fitted maps of the prepared photo.
    maps: Option<Tensor>,
    device: Device,
}

impl FitMethod {
    /// Loads the flashmat model file `path`; its estimates handle the
    /// photo's exposure as `exposure` says.
    pub fn load(path: &Path, name: String, ldr_photo: bool, device: Device, config: FitConfig, exposure: &crate::infer::ExposureConfig) -> Result<Self> {
        config.validate()?;
        let model = ModelMethod::load(path, name.clone(), ldr_photo, device)?.with_exposure(*exposure);
        Ok(Self { name, model, config, maps: None, device })
    }

    /// The fitted maps `[10, H, W]` of the prepared photo, on the CPU.
    pub fn maps(&self) -> Option<Tensor> {
        self.maps.as_ref().map(|m| m.get(0).to_device(Device::Cpu))
    }
}

impl Method for FitMethod {
    fn name(&self) -> String {
        self.name.clone()
    }

    fn prepare(&mut self, photo_linear: &Tensor) -> Result<()> {
        self.model.prepare(photo_linear)?;
        let material = self.model.material().context("the model prepared no material")?;
        let fit = fit_material(material, &self.config, |_, _| {})?;
        self.maps = Some(fit.maps.to_device(self.device).unsqueeze(0));
        Ok(())
    }

    fn render(&self, configs: &[LightView]) -> Result<Tensor> {
        super::render_ggx_maps(&self.name, self.maps.as_ref(), configs, self.device)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fit_specs_and_names() {
        let d = FitConfig::default().steps;
        assert_eq!(split_fit_spec("models/flashmat.safetensors+fit"), Some(("models/flashmat.safetensors", d)));
        assert_eq!(split_fit_spec("m.safetensors+fit40"), Some(("m.safetensors", 40)));
        assert_eq!(split_fit_spec("m.safetensors"), None);
        assert_eq!(split_fit_spec("m.safetensors+fitx"), None);
        assert_eq!(split_fit_spec("+fit"), None);
        assert_eq!(fitted_name("flashmat", 150), "flashmat+fit150");
    }
}
