use super::*;
use crate::data::procedural::{generate_family, Family};
use crate::data::samples::{make_batch, SampleConfig};
use crate::model::Model;
use rand::SeedableRng;
use rand_pcg::Pcg64;
use tch::Kind;

// Parameter counts of the U-Net layouts, layer by layer (see the M_est
// module docs): an HA layer C -> P has gate, feat, incep.a (9CP each),
// incep.b (9 P/2 P) and incep.c (9 C P/2) weights; BatchNorm 2 per channel.
fn ha(c: i64, p: i64) -> i64 {
    27 * c * p + 9 * p * (p / 2) + 9 * c * (p / 2)
}
fn res(c: i64, p: i64, stride: i64) -> i64 {
    ha(c, p) + ha(p, p) + 4 * p + if c != p || stride != 1 { c * p + 2 * p } else { 0 }
}
fn up(c: i64, p: i64) -> i64 {
    16 * c * p + 2 * p + 9 * p * p + 2 * p + 4 * c * p + 2 * p
}
/// The U-Net with `e` extra input channels at each decoder stage and a
/// `head`-channel output.
fn unet_params(w: i64, e: i64, head: i64) -> i64 {
    let enc = res(w, w, 1) + res(w, w, 1) + res(w, 2 * w, 2) + res(2 * w, 2 * w, 1) + res(2 * w, 4 * w, 2) + res(4 * w, 4 * w, 1)
        + res(4 * w, 8 * w, 2)
        + res(8 * w, 8 * w, 1);
    let dec = up(8 * w + e, 8 * w) + res(8 * w, 8 * w, 1) + up(12 * w + e, 4 * w) + res(4 * w, 4 * w, 1) + up(6 * w + e, 2 * w)
        + res(2 * w, 2 * w, 1)
        + res(3 * w + e, w, 1)
        + res(w, w, 1);
    49 * 4 * w + enc + dec + 49 * w * head
}

#[test]
fn layout_formula_reproduces_the_published_m_est_counts() {
    // M_est also holds 18 W unused compatibility parameters (m_est docs).
    for (w, n) in [(8, 1_338_176), (16, 5_294_336), (64, 84_008_960)] {
        assert_eq!(unet_params(w, 0, 64) + 18 * w, n, "W = {w}");
    }
    // The paper-size baselines (docs/TRAINING.md): analytic = M_est with a
    // 9-channel head; relight-unet with E = 32 and the 297-594-594-32 MLP.
    assert_eq!(unet_params(64, 0, 9) + 18 * 64, 83_836_480);
    assert_eq!(unet_params(64, 32, 3) + 297 * 594 + 594 * 594 + 594 * 32, 85_004_774);
}

#[test]
fn compact_parameter_counts() {
    for (method, n) in [(TrainMethod::Analytic, 5_251_216), (TrainMethod::RelightUnet, 5_464_720)] {
        assert_eq!(Baseline::new(method, &ModelConfig::compact(), Device::Cpu).unwrap().param_count(), n, "{method}");
    }
}

fn tiny_batch(k: usize) -> crate::data::samples::TrainingBatch {
    let m = generate_family(Family::Tiles, 3, 32);
    let n = generate_family(Family::Stone, 4, 32);
    let sample = SampleConfig { outputs_per_material: k, ..Default::default() };
    make_batch(&[m, n], &sample, &mut Pcg64::seed_from_u64(1), Device::Cpu).unwrap()
}

#[test]
fn analytic_tiny_parameter_count_and_shapes() {
    tch::manual_seed(0);
    let cfg = ModelConfig::tiny();
    let b = Baseline::new(TrainMethod::Analytic, &cfg, Device::Cpu).unwrap();
    // M_est at W = 8 with a 9-channel head instead of 64 channels.
    assert_eq!(b.param_count(), 1_316_616);
    assert_eq!(b.param_count(), unet_params(8, 0, 9) + 18 * 8);
    let vars = b.vs.variables();
    assert_eq!(vars["net.head.weight"].size(), [9, 8, 7, 7]);
    assert_eq!(vars["net.stem.weight"].size(), [8, 4, 7, 7]);
    assert_eq!(vars["net.dec3.up.tconv.weight"].size(), [96, 32, 4, 4]);
    assert!(vars.keys().all(|k| k.starts_with("net.")));
    assert!(b.model_id().starts_with("analytic/tiny-"), "{}", b.model_id());

    let batch = tiny_batch(3);
    let BaselineNet::Analytic(a) = &b.net else { panic!() };
    let maps = a.maps_t(&batch.est_input, true).unwrap();
    assert_eq!(maps.size(), [2, 10, 32, 32]);
    let ch = |c: i64, n: i64| maps.narrow(1, c, n);
    for (c, n, lo, hi) in [(0, 3, 0.0, 1.0), (3, 3, 0.0, 1.0), (6, 1, 0.02, 1.0)] {
        assert!(ch(c, n).min().double_value(&[]) >= lo && ch(c, n).max().double_value(&[]) <= hi, "channels {c}..{}", c + n);
    }
    let norm = ch(7, 3).square().sum_dim_intlist([1i64].as_slice(), false, Kind::Float).sqrt();
    assert!((norm - 1.0).abs().max().double_value(&[]) < 1e-5);
    assert!(ch(9, 1).min().double_value(&[]) > 0.0);
    let log = b.forward_t(&batch.est_input, &batch.out_wi, &batch.out_wo, true).unwrap();
    assert_eq!(log.size(), [2, 3, 3, 32, 32]);
    // The log renders are the GGX renderer's of the maps.
    let expect = crate::spaces::to_log(&crate::svbrdf::render::render_directions(&maps, &batch.out_wi, &batch.out_wo));
    assert!((log - expect).abs().max().double_value(&[]) < 1e-5);
}

#[test]
fn analytic_decoding() {
    use super::analytic::{KD_AT_ZERO, KS_AT_ZERO, ROUGHNESS_AT_ZERO};
    // A zero head decodes to the plain dielectric kd 0.25, ks 0.04,
    // roughness 0.3 and the flat normal; head values shift the sigmoids'
    // arguments; slopes (x, y) give normalize(x, y, 1).
    assert_eq!((KD_AT_ZERO, KS_AT_ZERO, ROUGHNESS_AT_ZERO), (0.25, 0.04, 0.3));
    let raw = Tensor::zeros([1, 9, 1, 3], (Kind::Float, Device::Cpu));
    let px = |x: i64| raw.narrow(3, x, 1);
    let _ = px(1).narrow(1, 7, 2).fill_(1.0);
    let _ = px(1).narrow(1, 0, 1).fill_(2.0);
    let _ = px(2).narrow(1, 6, 1).fill_(-40.0);
    let _ = px(2).narrow(1, 3, 3).fill_(40.0);
    let _ = px(2).narrow(1, 7, 1).fill_(-1e4);
    let m = AnalyticNet::decode(&raw).unwrap();
    assert_eq!(m.size(), [1, 10, 1, 3]);
    let v = |c: i64, x: i64| m.double_value(&[0, c, 0, x]);
    let close = |a: f64, b: f64| (a - b).abs() < 1e-6;
    assert!(close(v(0, 0), 0.25) && close(v(2, 0), 0.25) && close(v(3, 0), 0.04) && close(v(5, 0), 0.04), "{m}");
    assert!(close(v(6, 0), 0.3));
    assert!(v(7, 0).abs() < 1e-7 && v(8, 0).abs() < 1e-7 && close(v(9, 0), 1.0));
    // sigmoid(2 + logit(0.25)) = 0.25 e^2 / (0.75 + 0.25 e^2)
    let e2 = 2f64.exp();
    assert!(close(v(0, 1), 0.25 * e2 / (0.75 + 0.25 * e2)));
    let s = 1.0 / 3f64.sqrt();
    assert!(close(v(7, 1), s) && close(v(8, 1), s) && close(v(9, 1), s));
    // Ranges at the extremes: roughness floor 0.02, ks up to 1, normal
    // nearly horizontal but z > 0 and unit length.
    assert!(close(v(6, 2), 0.02) && close(v(3, 2), 1.0));
    assert!(close(v(7, 2), -1.0) && v(9, 2) > 0.0 && close(v(7, 2).powi(2) + v(8, 2).powi(2) + v(9, 2).powi(2), 1.0));
    assert!(AnalyticNet::decode(&Tensor::zeros([1, 10, 1, 1], (Kind::Float, Device::Cpu))).is_err());
}

#[test]
fn relight_unet_tiny_parameter_count_and_shapes() {
    tch::manual_seed(0);
    let cfg = ModelConfig::tiny();
    let b = Baseline::new(TrainMethod::RelightUnet, &cfg, Device::Cpu).unwrap();
    // Encoder and decoder of M_est widened by E = enc_out = 8 code channels
    // at each decoder stage, a 3-channel head, and the direction MLP
    // 297 -> 32 -> 32 -> 8.
    let mlp = 297 * 32 + 32 * 32 + 32 * 8;
    assert_eq!(b.param_count(), 1_344_904);
    assert_eq!(b.param_count(), unet_params(8, 8, 3) + mlp);
    let vars = b.vs.variables();
    assert_eq!(vars["net.dirs.0.weight"].size(), [32, 297]);
    assert_eq!(vars["net.dirs.2.weight"].size(), [8, 32]);
    assert_eq!(vars["net.dec4.up.tconv.weight"].size(), [72, 64, 4, 4]);
    assert_eq!(vars["net.dec3.up.tconv.weight"].size(), [104, 32, 4, 4]);
    assert_eq!(vars["net.dec2.up.tconv.weight"].size(), [56, 16, 4, 4]);
    assert_eq!(vars["net.dec1.0.ha1.gate.weight"].size(), [8, 32, 3, 3]);
    assert_eq!(vars["net.head.weight"].size(), [3, 8, 7, 7]);
    assert!(b.model_id().starts_with("relight-unet/tiny-"));

    let batch = tiny_batch(3);
    let log = b.forward_t(&batch.est_input, &batch.out_wi, &batch.out_wo, true).unwrap();
    assert_eq!(log.size(), [2, 3, 3, 32, 32]);
    // Eval mode: the K configurations of a photo decode independently (the
    // shared encoder features are repeated per configuration), and the
    // output depends on the light and view.
    let BaselineNet::Relight(r) = &b.net else { panic!() };
    tch::no_grad(|| {
        let all = r.forward_t(&batch.est_input, &batch.out_wi, &batch.out_wo, false).unwrap();
        let enc = r.encode_t(&batch.est_input, false).unwrap();
        for i in 0..3 {
            let one = r.decode_t(&enc, &batch.out_wi.narrow(1, i, 1), &batch.out_wo.narrow(1, i, 1), false).unwrap();
            let d = (one.squeeze_dim(1) - all.select(1, i)).abs().max().double_value(&[]);
            assert!(d < 1e-4, "configuration {i}: {d}");
        }
        let spread = (all.select(1, 0) - all.select(1, 1)).abs().mean(Kind::Float).double_value(&[]);
        assert!(spread > 1e-4, "{spread}");
    });
    // Mismatched direction maps are refused.
    assert!(b.forward_t(&batch.est_input, &batch.out_wi.narrow(3, 0, 16), &batch.out_wo.narrow(3, 0, 16), false).is_err());
}

#[test]
fn model_files_record_the_method_and_refuse_the_wrong_loader() {
    let dir = tempfile::tempdir().unwrap();
    tch::manual_seed(2);
    let cfg = ModelConfig::tiny();
    let info = ModelInfo { ldr_input: true, steps: 7 };
    let batch = tiny_batch(2);
    for method in [TrainMethod::Analytic, TrainMethod::RelightUnet] {
        let b = Baseline::new(method, &cfg, Device::Cpu).unwrap();
        let path = dir.path().join(format!("{method}.safetensors"));
        b.save(&path, &info, false).unwrap();
        assert_eq!(file_method(&path).unwrap(), method);
        let (again, info2) = Baseline::load(&path, Device::Cpu).unwrap();
        assert_eq!(info2, info);
        assert_eq!(again.method, method);
        let x = tch::no_grad(|| b.forward_t(&batch.est_input, &batch.out_wi, &batch.out_wo, false).unwrap());
        let y = tch::no_grad(|| again.forward_t(&batch.est_input, &batch.out_wi, &batch.out_wo, false).unwrap());
        assert!(x.equal(&y), "{method}: reloaded network differs");
        // The flashmat loader names the method instead of failing on weights.
        let e = format!("{:#}", Model::load(&path, Device::Cpu).unwrap_err());
        assert!(e.contains(method.name()) && e.contains("baseline"), "{e}");
        // A damaged file is refused.
        let mut bytes = std::fs::read(&path).unwrap();
        let n = bytes.len();
        bytes[n - 3] ^= 0x20;
        let bad = dir.path().join("bad.safetensors");
        std::fs::write(&bad, &bytes).unwrap();
        assert!(format!("{:#}", Baseline::load(&bad, Device::Cpu).unwrap_err()).contains("checksum"));
    }
    // flashmat model files record their method too, and are refused here.
    let fm = dir.path().join("flashmat.safetensors");
    Model::new(&cfg, Device::Cpu).unwrap().save(&fm, &info, false).unwrap();
    assert_eq!(file_method(&fm).unwrap(), TrainMethod::Flashmat);
    assert!(format!("{:#}", Baseline::load(&fm, Device::Cpu).unwrap_err()).contains("flashmat model"));
    assert!(Model::load(&fm, Device::Cpu).is_ok());
    // Not a model file at all.
    let junk = dir.path().join("junk.safetensors");
    std::fs::write(&junk, b"hello").unwrap();
    assert!(file_method(&junk).is_err());
    assert!(Baseline::new(TrainMethod::Flashmat, &cfg, Device::Cpu).is_err());
    assert_eq!(TrainMethod::from_name("relight-unet").unwrap(), TrainMethod::RelightUnet);
    assert!(TrainMethod::from_name("matfusion").is_err());
}
