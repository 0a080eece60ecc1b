//! The compute device named on the command line (`--device`), parsed in one
//! place below every command that takes it.

use anyhow::{bail, Result};
use tch::Device;

/// Parses `cpu`, `cuda` (or `gpu`), `cuda:N`; CUDA must be present.
pub fn parse_device(s: &str) -> Result<Device> {
    match s {
        "cpu" => Ok(Device::Cpu),
        "cuda" | "gpu" => {
            if !tch::Cuda::is_available() {
                bail!("--device cuda: no CUDA device is available (libtorch sees {} GPUs)", tch::Cuda::device_count());
            }
            Ok(Device::Cuda(0))
        }
        other => match other.strip_prefix("cuda:").and_then(|n| n.parse::<usize>().ok()) {
            Some(n) if (n as i64) < tch::Cuda::device_count() => Ok(Device::Cuda(n)),
            Some(n) => bail!("--device cuda:{n}: only {} CUDA device(s) available", tch::Cuda::device_count()),
            None => bail!("--device must be cpu, cuda or cuda:N (got '{other}')"),
        },
    }
}

/// The name [`parse_device`] reads back: `cpu` or `cuda:N`.
pub fn device_name(device: Device) -> String {
    match device {
        Device::Cuda(i) => format!("cuda:{i}"),
        _ => "cpu".into(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_cpu_and_refuses_the_rest() {
        assert_eq!(parse_device("cpu").unwrap(), Device::Cpu);
        let e = parse_device("tpu").unwrap_err().to_string();
        assert!(e.contains("cpu, cuda or cuda:N"), "{e}");
        if !tch::Cuda::is_available() {
            assert!(parse_device("cuda").unwrap_err().to_string().contains("no CUDA device"));
            assert!(parse_device("cuda:3").unwrap_err().to_string().contains("only 0 CUDA"));
        }
        // The name reads back as the device.
        assert_eq!(parse_device(&device_name(Device::Cpu)).unwrap(), Device::Cpu);
        assert_eq!(device_name(Device::Cuda(2)), "cuda:2");
    }
}
