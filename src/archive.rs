//! Named f32 tensors plus string metadata in one safetensors file, with a
//! format tag, a version, a CRC-32 of the tensor bytes and a CRC-32 of the
//! header (tensor names, dtypes and shapes, and the metadata), so that
//! truncated, damaged or foreign files are refused with a clear message.
//! Non-finite values are refused both ways: a diverged network is never
//! written, nor read. Used by training checkpoints, exported models and
//! `.nmat` neural materials. Writes are atomic (temporary file, then rename).

use anyhow::{bail, Context, Result};
use safetensors::tensor::{Dtype, SafeTensors, TensorView};
use std::collections::{BTreeMap, HashMap};
use std::path::Path;
use tch::{Device, Kind, Tensor};

const KEY_FORMAT: &str = "flashmat.format";
const KEY_VERSION: &str = "flashmat.version";
const KEY_CRC: &str = "flashmat.crc32";
/// CRC-32 of the header (see [`header_crc`]). Files written before it
/// existed (the bundled models among them) lack it and are read with the
/// tensor CRC alone.
const KEY_META_CRC: &str = "flashmat.meta_crc32";

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

/// Rewrites a serialized safetensors file's JSON header with its keys in
/// sorted order. `safetensors::serialize` takes the metadata as a HashMap
/// and writes it in that map's random order, so the same archive gave
/// different bytes on every save and a retrained model could not be
/// checked by its SHA-256. The tensor offsets are explicit in the header,
/// and the same keys and values in another order have the same length, so
/// the data part is untouched.
fn sort_header_keys(data: &mut [u8]) -> Result<()> {
    let len_bytes: [u8; 8] = data.get(..8).context("serialized archive shorter than its header length")?.try_into()?;
    let header_len = u64::from_le_bytes(len_bytes) as usize;
    let header = data.get_mut(8..8 + header_len).context("serialized archive shorter than its header")?;
    // serde_json's Map is a BTreeMap (no preserve_order feature): parsing sorts every object.
    let parsed: serde_json::Value = serde_json::from_slice(header).context("parsing the serialized header")?;
    let sorted = serde_json::to_vec(&parsed)?;
    anyhow::ensure!(sorted.len() <= header.len(), "sorted header longer than the original ({} > {})", sorted.len(), header.len());
    let (head, padding) = header.split_at_mut(sorted.len());
    head.copy_from_slice(&sorted);
    padding.fill(b' ');
    Ok(())
}

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
    /// Tensors holding NaN or Inf (or, stored as f16, values beyond its
    /// range) are refused and nothing is written.
    pub fn save(&self, path: &Path, format: &str, version: u32) -> Result<()> {
        let buffers: Vec<(String, Dtype, Vec<u8>, Vec<usize>)> = self
            .tensors
            .iter()
            .map(|(name, t)| {
                let numel = t.numel();
                let mut values = vec![0f32; numel];
                t.copy_data(&mut values, numel);
                if let Some(v) = values.iter().find(|v| !v.is_finite()) {
                    bail!("cannot write {}: tensor '{name}' holds a non-finite value ({v})", path.display());
                }
                let (dtype, bytes): (Dtype, Vec<u8>) = if self.store_half && numel >= HALF_MIN_NUMEL {
                    let halves: Vec<half::f16> = values.iter().map(|v| half::f16::from_f32(*v)).collect();
                    if let Some(i) = halves.iter().position(|h| !h.is_finite()) {
                        bail!("cannot write {}: tensor '{name}' holds {}, beyond the f16 range (store it as f32)", path.display(), values[i]);
                    }
                    (Dtype::F16, halves.iter().flat_map(|h| h.to_le_bytes()).collect())
                } else {
                    (Dtype::F32, values.iter().flat_map(|v| v.to_le_bytes()).collect())
                };
                Ok((name.clone(), dtype, bytes, t.size().iter().map(|&d| d as usize).collect()))
            })
            .collect::<Result<_>>()?;
        let mut crc = crc32fast::Hasher::new();
        for (name, _, bytes, _) in &buffers {
            crc.update(name.as_bytes());
            crc.update(bytes);
        }
        let mut metadata: BTreeMap<String, String> = self.metadata.clone();
        metadata.insert(KEY_FORMAT.into(), format.into());
        metadata.insert(KEY_VERSION.into(), version.to_string());
        metadata.insert(KEY_CRC.into(), format!("{:08x}", crc.finalize()));
        let layout: Vec<(&str, Dtype, &[usize])> = buffers.iter().map(|(n, d, _, s)| (n.as_str(), *d, s.as_slice())).collect();
        metadata.insert(KEY_META_CRC.into(), format!("{:08x}", header_crc(&layout, &metadata)));
        let views: Vec<(String, TensorView)> = buffers
            .iter()
            .map(|(name, dtype, bytes, shape)| Ok((name.clone(), TensorView::new(*dtype, shape.clone(), bytes)?)))
            .collect::<Result<_>>()?;
        let mut data = safetensors::tensor::serialize(views, Some(metadata.into_iter().collect())).context("serializing tensors")?;
        sort_header_keys(&mut data)?;
        crate::io::atomic_write_bytes(path, &data)
    }

    /// Reads and verifies an archive of the given format; versions other than
    /// `version` are refused. Errors name the file.
    pub fn load(path: &Path, format: &str, version: u32) -> Result<Self> {
        let data = crate::io::read_input(path).with_context(|| format!("{}: cannot read file", path.display()))?;
        Self::from_bytes(&data, format, version).with_context(|| format!("{}", path.display()))
    }

    /// [`Archive::load`] accepting any of `versions` (a format whose reader
    /// still understands older files). Errors name the file.
    pub fn load_versions(path: &Path, format: &str, versions: &[u32]) -> Result<Self> {
        let data = crate::io::read_input(path).with_context(|| format!("{}: cannot read file", path.display()))?;
        Self::from_bytes_versions(&data, format, versions).with_context(|| format!("{}", path.display()))
    }

    /// [`Archive::load`] of a file's bytes (errors do not name it).
    pub fn from_bytes(data: &[u8], format: &str, version: u32) -> Result<Self> {
        Self::from_bytes_versions(data, format, &[version])
    }

    /// [`Archive::load_versions`] of a file's bytes (errors do not name it).
    pub fn from_bytes_versions(data: &[u8], format: &str, versions: &[u32]) -> Result<Self> {
        let (_, header) = SafeTensors::read_metadata(data).map_err(|e| anyhow::anyhow!("not a valid {format} file (damaged or truncated: {e})"))?;
        let meta: BTreeMap<String, String> = header.metadata().clone().unwrap_or_default().into_iter().collect();
        match meta.get(KEY_FORMAT) {
            Some(f) if f == format => {}
            Some(f) => bail!("this is a '{f}' file, expected a '{format}' file"),
            None => bail!("not a flashmat {format} file (no format tag)"),
        }
        let found: u32 = meta.get(KEY_VERSION).and_then(|v| v.parse().ok()).context("missing format version")?;
        if !versions.contains(&found) {
            let list: Vec<String> = versions.iter().map(u32::to_string).collect();
            let list = match list.split_last() {
                Some((last, rest)) if !rest.is_empty() => format!("versions {} and {last}", rest.join(", ")),
                _ => format!("version {}", list.join("")),
            };
            bail!("{format} version {found} is not supported (this flashmat reads {list})");
        }
        // A damaged key name must not switch a check off: an unknown
        // `flashmat.` key, or any key one byte away from an integrity key
        // (a bit flip in the prefix itself), is damage.
        let integrity = [KEY_FORMAT, KEY_VERSION, KEY_CRC, KEY_META_CRC];
        let one_byte_from = |k: &str, known: &str| k.len() == known.len() && k.bytes().zip(known.bytes()).filter(|(a, b)| a != b).count() == 1;
        if let Some(k) = meta.keys().find(|k| !integrity.contains(&k.as_str()) && (k.starts_with("flashmat.") || integrity.iter().any(|known| one_byte_from(k, known)))) {
            bail!("unknown integrity field '{k}': the {format} file is damaged");
        }
        let st = SafeTensors::deserialize(data).map_err(|e| anyhow::anyhow!("damaged {format} file: {e}"))?;
        let mut names: Vec<String> = st.names().into_iter().map(|s| s.to_string()).collect();
        names.sort();
        let views: Vec<(String, TensorView)> = names.into_iter().map(|n| Ok((n.clone(), st.tensor(&n)?))).collect::<Result<_>>()?;
        if let Some(expect) = meta.get(KEY_META_CRC) {
            let layout: Vec<(&str, Dtype, &[usize])> = views.iter().map(|(n, v)| (n.as_str(), v.dtype(), v.shape())).collect();
            if *expect != format!("{:08x}", header_crc(&layout, &meta)) {
                bail!("header checksum mismatch: the {format} file is damaged");
            }
        }
        let mut crc = crc32fast::Hasher::new();
        for (name, view) in &views {
            crc.update(name.as_bytes());
            crc.update(view.data());
        }
        let expect = meta.get(KEY_CRC).context("missing checksum")?;
        if *expect != format!("{:08x}", crc.finalize()) {
            bail!("checksum mismatch: the {format} file is damaged");
        }
        let mut tensors = BTreeMap::new();
        for (name, view) in views {
            let values: Vec<f32> = match view.dtype() {
                Dtype::F32 => view.data().chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect(),
                Dtype::F16 => view.data().chunks_exact(2).map(|b| half::f16::from_le_bytes([b[0], b[1]]).to_f32()).collect(),
                other => bail!("tensor '{name}' has dtype {other:?}, expected F32 or F16"),
            };
            if let Some(v) = values.iter().find(|v| !v.is_finite()) {
                bail!("tensor '{name}' holds a non-finite value ({v}): the file was written from diverged values");
            }
            let shape: Vec<i64> = view.shape().iter().map(|&d| i64::try_from(d)).collect::<Result<_, _>>().with_context(|| format!("tensor '{name}' has an impossible shape"))?;
            let t = Tensor::from_slice(&values).f_view(shape.as_slice()).with_context(|| format!("tensor '{name}' has an impossible shape {shape:?}"))?;
            tensors.insert(name, t);
        }
        let metadata = meta.into_iter().filter(|(k, _)| !k.starts_with("flashmat.")).collect();
        Ok(Self { tensors, metadata, store_half: false })
    }
}

/// CRC-32 of an archive's header: for each tensor in byte-wise name order
/// its name, dtype (`F32`, `F16`) and shape (decimal dimensions joined by
/// `,`), then each metadata entry in byte-wise key order (except
/// `flashmat.meta_crc32` itself) as key and value; every string followed
/// by a NUL byte. The tensor CRC covers names and data; this one the
/// shapes and metadata that give the data its meaning.
fn header_crc(layout: &[(&str, Dtype, &[usize])], metadata: &BTreeMap<String, String>) -> u32 {
    let mut crc = crc32fast::Hasher::new();
    let mut field = |s: &str| {
        crc.update(s.as_bytes());
        crc.update(&[0]);
    };
    let mut sorted: Vec<&(&str, Dtype, &[usize])> = layout.iter().collect();
    sorted.sort_by(|a, b| a.0.cmp(b.0));
    for (name, dtype, shape) in sorted {
        field(name);
        field(&format!("{dtype:?}"));
        field(&shape.iter().map(|d| d.to_string()).collect::<Vec<_>>().join(","));
    }
    for (k, v) in metadata.iter().filter(|(k, _)| *k != KEY_META_CRC) {
        field(k);
        field(v);
    }
    crc.finalize()
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

    /// The same archive saved twice gives the same bytes (safetensors
    /// itself writes the metadata in a HashMap's random order: with these
    /// nine keys two saves agreed about once in 9! times), the header's
    /// keys are in sorted order, and the file still reads back.
    #[test]
    fn the_same_archive_gives_the_same_bytes() {
        let dir = tempfile::tempdir().unwrap();
        let mut a = sample();
        for key in ["model_id", "method", "info", "zeta"] {
            a.set_meta(key, format!("value of {key}"));
        }
        let (p, q) = (dir.path().join("a.safetensors"), dir.path().join("b.safetensors"));
        a.save(&p, "test", 3).unwrap();
        a.save(&q, "test", 3).unwrap();
        let (bytes, again) = (std::fs::read(&p).unwrap(), std::fs::read(&q).unwrap());
        assert_eq!(bytes, again);
        let header_len = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        assert_eq!((8 + header_len) % 8, 0, "safetensors pads the header to 8 bytes");
        let header = std::str::from_utf8(&bytes[8..8 + header_len]).unwrap();
        let position = |key: &str| header.find(&format!("\"{key}\"")).unwrap();
        let keys = ["config", "flashmat.crc32", "flashmat.format", "flashmat.meta_crc32", "flashmat.version", "info", "method", "model_id", "zeta"];
        assert!(keys.windows(2).all(|w| position(w[0]) < position(w[1])), "{header}");
        assert!(position("__metadata__") < position("net.b") && position("net.b") < position("net.w"), "{header}");
        let b = Archive::load(&p, "test", 3).unwrap();
        assert_eq!(b.meta("zeta").unwrap(), "value of zeta");
        assert_eq!(b.tensor("net.w").unwrap().double_value(&[1, 2]), 6.0);
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

    /// Serialises tensors and metadata as given (no keys added): files
    /// from older writers, or crafted ones.
    fn raw_file(path: &Path, tensors: &[(&str, Vec<f32>, Vec<usize>)], metadata: &BTreeMap<String, String>) {
        let bytes: Vec<Vec<u8>> = tensors.iter().map(|(_, v, _)| v.iter().flat_map(|x| x.to_le_bytes()).collect()).collect();
        let views: Vec<(String, TensorView)> =
            tensors.iter().zip(&bytes).map(|((n, _, s), b)| (n.to_string(), TensorView::new(Dtype::F32, s.clone(), b).unwrap())).collect();
        let meta: HashMap<String, String> = metadata.clone().into_iter().collect();
        std::fs::write(path, safetensors::tensor::serialize(views, Some(meta)).unwrap()).unwrap();
    }

    /// The tensor CRC as documented (names and data, sorted by name).
    fn payload_crc(tensors: &[(&str, Vec<f32>, Vec<usize>)]) -> String {
        let mut sorted: Vec<_> = tensors.iter().collect();
        sorted.sort_by(|a, b| a.0.cmp(b.0));
        let mut crc = crc32fast::Hasher::new();
        for (n, v, _) in sorted {
            crc.update(n.as_bytes());
            v.iter().for_each(|x| crc.update(&x.to_le_bytes()));
        }
        format!("{:08x}", crc.finalize())
    }

    #[test]
    fn the_header_checksum_covers_shapes_and_metadata_and_old_files_still_load() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.safetensors");
        sample().save(&p, "test", 3).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        // Swapped dimensions: the tensor bytes (and their CRC) are unchanged.
        let at = bytes.windows(5).position(|w| w == b"[2,3]").unwrap();
        let mut swapped = bytes.clone();
        swapped[at..at + 5].copy_from_slice(b"[3,2]");
        std::fs::write(&p, &swapped).unwrap();
        let e = format!("{:#}", Archive::load(&p, "test", 3).err().unwrap());
        assert!(e.contains("header checksum mismatch"), "{e}");
        // An edited metadata value.
        // (the JSON header escapes the quotes of the stored `{"x":1}`)
        let at = bytes.windows(8).position(|w| w == br#"\"x\":1}"#).unwrap();
        let mut edited = bytes.clone();
        edited[at + 6] = b'2';
        std::fs::write(&p, &edited).unwrap();
        assert!(format!("{:#}", Archive::load(&p, "test", 3).err().unwrap()).contains("header checksum mismatch"));
        // A damaged integrity key name is not an absent one.
        let at = bytes.windows(10).position(|w| w == b"meta_crc32").unwrap();
        let mut renamed = bytes.clone();
        renamed[at] = b'n';
        std::fs::write(&p, &renamed).unwrap();
        assert!(format!("{:#}", Archive::load(&p, "test", 3).err().unwrap()).contains("unknown integrity field"));
        // Also when the flip lands in the `flashmat.` prefix ('f' ^ 4 = 'b', 'h' ^ 4 = 'l').
        let at = bytes.windows(19).position(|w| w == b"flashmat.meta_crc32").unwrap();
        for (offset, mask) in [(0, 0x04), (4, 0x04), (8, 0x01)] {
            let mut renamed = bytes.clone();
            renamed[at + offset] ^= mask;
            std::fs::write(&p, &renamed).unwrap();
            let e = format!("{:#}", Archive::load(&p, "test", 3).err().unwrap());
            assert!(e.contains("unknown integrity field"), "{offset}: {e}");
        }

        // A file written before the header checksum (the bundled models): the tensor CRC alone.
        let tensors = [("net.b", vec![-0.5f32], vec![1]), ("net.w", vec![1.0, 2.0, 3.0, 4.0, 5.0, 6.0], vec![2, 3])];
        let mut meta: BTreeMap<String, String> =
            [("flashmat.format", "test"), ("flashmat.version", "3"), ("config", "{\"x\":1}")].iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        meta.insert("flashmat.crc32".into(), payload_crc(&tensors));
        raw_file(&p, &tensors, &meta);
        let old = Archive::load(&p, "test", 3).unwrap();
        assert_eq!(old.tensor("net.w").unwrap().double_value(&[1, 2]), 6.0);
        assert_eq!(old.meta("config").unwrap(), "{\"x\":1}");
    }

    #[test]
    fn non_finite_values_are_neither_written_nor_read() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.safetensors");
        for bad in [f32::NAN, f32::INFINITY] {
            let mut a = sample();
            a.insert("net.w", &Tensor::from_slice(&[1.0f32, bad]));
            let e = format!("{:#}", a.save(&p, "test", 3).unwrap_err());
            assert!(e.contains("a.safetensors") && e.contains("'net.w'") && e.contains("non-finite"), "{e}");
            assert!(!p.exists());
        }
        // Finite in f32, infinite in f16.
        let mut a = Archive { store_half: true, ..sample() };
        a.insert("big", &Tensor::full([HALF_MIN_NUMEL as i64], 1e5, (Kind::Float, Device::Cpu)));
        let e = format!("{:#}", a.save(&p, "test", 3).unwrap_err());
        assert!(e.contains("'big'") && e.contains("f16 range"), "{e}");
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0, "nothing written, no temporary left");
        // Crafted with valid checksums (no header checksum needed): refused on reading.
        let tensors = [("net.w", vec![1.0f32, f32::INFINITY], vec![2])];
        let mut meta: BTreeMap<String, String> = [("flashmat.format", "test"), ("flashmat.version", "3")].iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
        meta.insert("flashmat.crc32".into(), payload_crc(&tensors));
        raw_file(&p, &tensors, &meta);
        let e = format!("{:#}", Archive::load(&p, "test", 3).err().unwrap());
        assert!(e.contains("a.safetensors") && e.contains("'net.w'") && e.contains("non-finite"), "{e}");
    }

    #[test]
    fn special_files_are_refused_without_blocking() {
        let dir = tempfile::tempdir().unwrap();
        let fifo = dir.path().join("pipe.safetensors");
        assert!(std::process::Command::new("mkfifo").arg(&fifo).status().unwrap().success());
        let e = format!("{:#}", Archive::load(&fifo, "test", 3).err().unwrap());
        assert!(e.contains("pipe.safetensors") && e.contains("FIFO"), "{e}");
        let e = format!("{:#}", Archive::load(Path::new("/dev/zero"), "test", 3).err().unwrap());
        assert!(e.contains("character device"), "{e}");
        assert!(format!("{:#}", Archive::load(dir.path(), "test", 3).err().unwrap()).contains("directory"));
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
