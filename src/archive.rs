//! Named f32 tensors plus string metadata in one safetensors file, with a
//! format tag, a version and a CRC-32 of the tensor bytes so that truncated,
//! damaged or foreign files are refused with a clear message. Used by
//! training checkpoints, exported models and `.nmat` neural materials.
//! Writes are atomic (temporary file, then rename).

use anyhow::{bail, Context, Result};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use tch::{Device, Kind, Tensor};

const KEY_FORMAT: &str = "flashmat.format";
const KEY_VERSION: &str = "flashmat.version";
const KEY_CRC: &str = "flashmat.crc32";

/// Tensors (CPU copies) and metadata read from or to be written to an archive.
#[derive(Default)]
pub struct Archive {
    pub tensors: BTreeMap<String, Tensor>,
    pub metadata: BTreeMap<String, String>,
    /// Store tensors of at least [`HALF_MIN_NUMEL`] values as IEEE f16
    /// (halves exported models); smaller ones (biases, BatchNorm
    /// statistics, whose variances can fall below f16's normal range) stay
    /// f32. Reading always gives f32.
    pub store_half: bool,
}

/// Smallest tensor stored as f16 when [`Archive::store_half`] is set.
pub const HALF_MIN_NUMEL: usize = 1024;

impl Archive {
    pub fn new() -> Self {
        Self::default()
    }

    /// Adds a tensor (copied to CPU f32 contiguous).
    pub fn insert(&mut self, name: impl Into<String>, t: &Tensor) {
        let t = t.detach().to_device(Device::Cpu).to_kind(Kind::Float).contiguous();
        self.tensors.insert(name.into(), t);
    }

    /// Adds every tensor of a name -> tensor map under `prefix`.
    pub fn insert_all(&mut self, prefix: &str, vars: &HashMap<String, Tensor>) {
        for (name, t) in vars {
            self.insert(format!("{prefix}{name}"), t);
        }
    }

    pub fn set_meta(&mut self, key: &str, value: impl Into<String>) {
        self.metadata.insert(key.to_string(), value.into());
    }

    pub fn meta(&self, key: &str) -> Result<&str> {
        self.metadata.get(key).map(|s| s.as_str()).with_context(|| format!("metadata field '{key}' is missing"))
    }

    pub fn tensor(&self, name: &str) -> Result<&Tensor> {
        self.tensors.get(name).with_context(|| format!("tensor '{name}' is missing"))
    }

    /// Tensors whose name starts with `prefix`, with the prefix removed.
    pub fn with_prefix(&self, prefix: &str) -> HashMap<String, Tensor> {
        self.tensors
            .iter()
            .filter_map(|(k, v)| k.strip_prefix(prefix).map(|rest| (rest.to_string(), v.shallow_clone())))
            .collect()
    }

    /// Writes the archive atomically with the given format tag and version.
    pub fn save(&self, path: &Path, format: &str, version: u32) -> Result<()> {
        let buffers: Vec<(String, Dtype, Vec<u8>, Vec<usize>)> = self
            .tensors
            .iter()
            .map(|(name, t)| {
                let numel = t.numel();
                let mut values = vec![0f32; numel];
                t.copy_data(&mut values, numel);
                let (dtype, bytes): (Dtype, Vec<u8>) = if self.store_half && numel >= HALF_MIN_NUMEL {
                    (Dtype::F16, values.iter().flat_map(|v| half::f16::from_f32(*v).to_le_bytes()).collect())
                } else {
                    (Dtype::F32, values.iter().flat_map(|v| v.to_le_bytes()).collect())
                };
                (name.clone(), dtype, bytes, t.size().iter().map(|&d| d as usize).collect())
            })
            .collect();
        let mut crc = crc32fast::Hasher::new();
        for (name, _, bytes, _) in &buffers {
            crc.update(name.as_bytes());
            crc.update(bytes);
        }
        let mut metadata: HashMap<String, String> = self.metadata.clone().into_iter().collect();
        metadata.insert(KEY_FORMAT.into(), format.into());
        metadata.insert(KEY_VERSION.into(), version.to_string());
        metadata.insert(KEY_CRC.into(), format!("{:08x}", crc.finalize()));
        let views: Vec<(String, TensorView)> = buffers
            .iter()
            .map(|(name, dtype, bytes, shape)| Ok((name.clone(), TensorView::new(*dtype, shape.clone(), bytes)?)))
            .collect::<Result<_>>()?;
        let data = safetensors::tensor::serialize(views, Some(metadata)).context("serializing tensors")?;
        crate::io::atomic_write_bytes(path, &data)
    }

    /// Reads and verifies an archive of the given format; versions other than
    /// `version` are refused. Errors name the file.
    pub fn load(path: &Path, format: &str, version: u32) -> Result<Self> {
        Self::load_inner(path, format, version).with_context(|| format!("{}", path.display()))
    }

    fn load_inner(path: &Path, format: &str, version: u32) -> Result<Self> {
        let data = std::fs::read(path).context("cannot read file")?;
        let (_, header) = SafeTensors::read_metadata(&data).map_err(|e| anyhow::anyhow!("not a valid {format} file (damaged or truncated: {e})"))?;
        let meta: BTreeMap<String, String> = header.metadata().clone().unwrap_or_default().into_iter().collect();
        match meta.get(KEY_FORMAT) {
            Some(f) if f == format => {}
            Some(f) => bail!("this is a '{f}' file, expected a '{format}' file"),
            None => bail!("not a flashmat {format} file (no format tag)"),
        }
        let found: u32 = meta.get(KEY_VERSION).and_then(|v| v.parse().ok()).context("missing format version")?;
        if found != version {
            bail!("{format} version {found} is not supported (this flashmat reads version {version})");
        }
        let st = SafeTensors::deserialize(&data).map_err(|e| anyhow::anyhow!("damaged {format} file: {e}"))?;
        let mut names: Vec<String> = st.names().into_iter().map(|s| s.to_string()).collect();
        names.sort();
        let mut crc = crc32fast::Hasher::new();
        let mut tensors = BTreeMap::new();
        for name in names {
            let view = st.tensor(&name)?;
            crc.update(name.as_bytes());
            crc.update(view.data());
            let values: Vec<f32> = match view.dtype() {
                Dtype::F32 => view.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
                Dtype::F16 => view.data().chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
                other => bail!("tensor '{name}' has dtype {other:?}, expected F32 or F16"),
            };
            let shape: Vec<i64> = view.shape().iter().map(|&d| d as i64).collect();
            tensors.insert(name, Tensor::from_slice(&values).view(shape.as_slice()));
        }
        let expect = meta.get(KEY_CRC).context("missing checksum")?;
        if *expect != format!("{:08x}", crc.finalize()) {
            bail!("checksum mismatch: the {format} file is damaged");
        }
        let metadata = meta.into_iter().filter(|(k, _)| !k.starts_with("flashmat.")).collect();
        Ok(Self { tensors, metadata, store_half: false })
    }
}

/// Copies archived values into existing variables (same names and shapes).
pub fn restore_vars(vars: &HashMap<String, Tensor>, saved: &HashMap<String, Tensor>, what: &str) -> Result<()> {
    for (name, var) in vars {
        let src = saved.get(name).with_context(|| format!("{what}: weight '{name}' is missing"))?;
        if src.size() != var.size() {
            bail!("{what}: weight '{name}' has shape {:?}, the model expects {:?}", src.size(), var.size());
        }
        tch::no_grad(|| var.shallow_clone().copy_(&src.to_device(var.device()).to_kind(var.kind())));
    }
    if saved.len() != vars.len() {
        bail!("{what}: file holds {} weights, the model has {}", saved.len(), vars.len());
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> Archive {
        let mut a = Archive::new();
        a.insert("net.w", &Tensor::from_slice(&[1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]).view([2, 3]));
        a.insert("net.b", &Tensor::from_slice(&[-0.5f32]));
        a.set_meta("config", "{\"x\":1}");
        a
    }

    #[test]
    fn round_trip() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.safetensors");
        sample().save(&p, "test", 3).unwrap();
        let b = Archive::load(&p, "test", 3).unwrap();
        assert_eq!(b.meta("config").unwrap(), "{\"x\":1}");
        assert_eq!(b.tensor("net.w").unwrap().size(), [2, 3]);
        assert_eq!(b.tensor("net.w").unwrap().double_value(&[1, 2]), 6.0);
        assert_eq!(b.with_prefix("net.").len(), 2);
        // no temporary files left behind
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn damaged_truncated_foreign_files_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.safetensors");
        sample().save(&p, "test", 3).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        // flip one byte of tensor data (at the end of the file)
        let mut bad = bytes.clone();
        let n = bad.len();
        bad[n - 2] ^= 0x40;
        std::fs::write(&p, &bad).unwrap();
        let e = Archive::load(&p, "test", 3).err().unwrap();
        assert!(format!("{e:#}").contains("checksum"), "{e:#}");
        std::fs::write(&p, &bytes[..n - 7]).unwrap();
        let e = Archive::load(&p, "test", 3).err().unwrap();
        assert!(format!("{e:#}").contains("a.safetensors"), "{e:#}");
        std::fs::write(&p, &bytes).unwrap();
        assert!(format!("{:#}", Archive::load(&p, "other", 3).err().unwrap()).contains("'test' file"));
        assert!(format!("{:#}", Archive::load(&p, "test", 4).err().unwrap()).contains("version 3"));
        std::fs::write(&p, b"garbage").unwrap();
        assert!(Archive::load(&p, "test", 3).is_err());
        assert!(Archive::load(&dir.path().join("missing"), "test", 3).is_err());
    }

    #[test]
    fn half_storage_halves_large_tensors_and_keeps_small_ones_exact() {
        let dir = tempfile::tempdir().unwrap();
        let (full, half) = (dir.path().join("f.safetensors"), dir.path().join("h.safetensors"));
        let mut a = Archive::new();
        // 1/3 is not representable in f16: its nearest f16 is 0.333251953125 (2^-2 * 1365/1024).
        a.insert("big", &Tensor::full([HALF_MIN_NUMEL as i64], 1.0 / 3.0, (Kind::Float, Device::Cpu)));
        a.insert("small", &Tensor::from_slice(&[1.0f32 / 3.0, 1e-7]));
        a.save(&full, "test", 1).unwrap();
        a.store_half = true;
        a.save(&half, "test", 1).unwrap();
        let (nf, nh) = (std::fs::metadata(&full).unwrap().len(), std::fs::metadata(&half).unwrap().len());
        // The big tensor's 4096 bytes become 2048; headers differ by a few bytes.
        assert!((nf as i64 - nh as i64 - 2048).abs() < 16, "{nf} {nh}");
        let b = Archive::load(&half, "test", 1).unwrap();
        let big = b.tensor("big").unwrap();
        assert_eq!(big.kind(), Kind::Float);
        assert_eq!(big.double_value(&[7]), 0.333251953125);
        assert_eq!(b.tensor("small").unwrap().double_value(&[0]), (1.0f32 / 3.0) as f64);
        assert_eq!(b.tensor("small").unwrap().double_value(&[1]), 1e-7f32 as f64);
    }

    #[test]
    fn restore_checks_shapes() {
        let var = Tensor::zeros([2, 3], (Kind::Float, Device::Cpu));
        let vars: HashMap<String, Tensor> = [("w".to_string(), var.shallow_clone())].into();
        let good: HashMap<String, Tensor> = [("w".to_string(), Tensor::ones([2, 3], (Kind::Float, Device::Cpu)))].into();
        restore_vars(&vars, &good, "test").unwrap();
        assert_eq!(var.sum(Kind::Float).double_value(&[]), 6.0);
        let bad: HashMap<String, Tensor> = [("w".to_string(), Tensor::ones([3, 2], (Kind::Float, Device::Cpu)))].into();
        assert!(restore_vars(&vars, &bad, "test").is_err());
    }
}
