//! Where does the colour go? Estimates the nine matte uniform colours of
//! `flashmat eval --uniform` at 64x64 and prints the norm of each mean
//! neural code and the distances between them (issue 15,
//! `reports/curriculum.md`). With `TEACHER=FILE` (a `flashmat
//! train-teacher` file of the same preset) the table is the teacher's codes
//! of the true maps instead, each line giving M_est's distance to them.
//!
//! ```sh
//! cargo run --release --example probe_colour -- [MODEL_FILE]
//! TEACHER=models/teacher-any-ggx.safetensors cargo run --release --example probe_colour -- MODEL_FILE
//! ```

use anyhow::Result;
use flashmat::geometry::LightView;
use flashmat::infer::{estimate, load_model, PreparedPhoto};
fn main() -> Result<()> {
    let path = std::env::args().nth(1).map(std::path::PathBuf::from);
    let loaded = load_model(path.as_deref(), tch::Device::Cpu)?;
    let identity = LightView::colocated(flashmat::geometry::MODEL_FOV_DEG);
    let mut codes = vec![];
    for (set, u) in flashmat::eval::uniform::uniform_materials() {
        if set != "matte" { continue; }
        let m = flashmat::svbrdf::Svbrdf::uniform(64, 64, u.diffuse, u.specular, u.roughness);
        let truth = flashmat::svbrdf::render::render_material(&m, &[identity])?;
        let photo = PreparedPhoto::at_model_view(truth[0].clone(), loaded.info.ldr_input, "probe");
        let mat = estimate(&loaded.model, &loaded.info, &photo)?;
        let c = mat.neural_map.mean_dim(&[1i64, 2][..], false, tch::Kind::Float);
        let sd = mat.neural_map.std_dim(&[1i64, 2][..], false, false).norm().double_value(&[]);
        println!("{:10} |mean code| {:.2}  pixel spread {:.2}  diffuse {:?}", u.name, c.norm().double_value(&[]), sd, u.diffuse);
        if let Ok(tp) = std::env::var("TEACHER") {
            let t = flashmat::train::teacher::Teacher::load(std::path::Path::new(&tp), &loaded.model.config, tch::Device::Cpu, None)?;
            let maps = flashmat::data::samples::stack_maps(&[m.clone()], tch::Device::Cpu)?;
            let tc = t.encoder.forward_maps(&maps).get(0).mean_dim(&[1i64, 2][..], false, tch::Kind::Float);
            println!("{:10} teacher |code| {:.2}, M_est vs teacher {:.2}", u.name, tc.norm().double_value(&[]), (&c - &tc).norm().double_value(&[]));
            codes.push((u.name, tc));
            continue;
        }
        codes.push((u.name, c));
    }
    print!("{:10}", "");
    for (n, _) in &codes { print!("{:>9}", n); }
    println!();
    for (a, ca) in &codes {
        print!("{:10}", a);
        for (_, cb) in &codes { print!("{:9.2}", (ca - cb).norm().double_value(&[])); }
        println!();
    }
    Ok(())
}
