//! Direct vs Winograd F(4x4, 3x3) for the stride-1 3x3 conv shapes of the
//! paper-size M_est (and the small ones the default policy leaves direct),
//! best of 3 after a warm-up, in this process:
//!
//! ```sh
//! OMP_WAIT_POLICY=PASSIVE cargo run --release --example winograd
//! ```
//! (`flashmat` sets OMP_WAIT_POLICY=PASSIVE itself; without it libtorch's
//! threads spin after each GEMM and slow the tile transforms down.)
//! The whole M_est, Winograd against direct, is in `flashmat bench infer`.

use flashmat::model::winograd::Winograd3x3;
use std::time::Instant;
use tch::{Device, Kind, Tensor};

fn best_of_3(mut f: impl FnMut()) -> f64 {
    f();
    (0..3)
        .map(|_| {
            let t = Instant::now();
            f();
            t.elapsed().as_secs_f64()
        })
        .fold(f64::MAX, f64::min)
}

fn main() {
    let _no_grad = tch::no_grad_guard();
    println!("threads: {}", tch::get_num_threads());
    println!("| C -> P @ side | direct ms | Winograd ms | speed-up | max error / max output |");
    println!("|---|---|---|---|---|");
    // (C, P, side): paper M_est at 256x256 (merged HA convs are 2.5 P wide),
    // then compact-size layers.
    for (c, p, side) in [(64, 160, 256), (64, 64, 256), (128, 128, 128), (256, 256, 64), (512, 512, 32), (16, 40, 256), (32, 32, 128), (64, 64, 64), (16, 16, 64)] {
        let xp = Tensor::randn([1, c, side + 2, side + 2], (Kind::Float, Device::Cpu));
        let w = Tensor::randn([p, c, 3, 3], (Kind::Float, Device::Cpu)) / (3.0 * (c as f64).sqrt());
        let wino = Winograd3x3::new(&w, None);
        let direct = || xp.conv2d(&w, None::<&Tensor>, [1, 1], [0, 0], [1, 1], 1);
        let t_direct = best_of_3(|| drop(direct()));
        let t_wino = best_of_3(|| drop(wino.forward(&xp)));
        let reference = direct();
        let err = (wino.forward(&xp) - &reference).abs().max().double_value(&[]) / reference.abs().max().double_value(&[]);
        println!("| {c} -> {p} @ {side} | {:.2} | {:.2} | {:.2}x | {err:.1e} |", t_direct * 1e3, t_wino * 1e3, t_direct / t_wino);
    }
}
