use super::*;

/// The mode is process-wide: a test that sets it puts the default back.
fn with_mode<T>(p: Precision, f: impl FnOnce() -> T) -> T {
    set(p).unwrap();
    let out = f();
    set(Precision::default()).unwrap();
    out
}

#[test]
fn names_round_trip_and_others_are_refused() {
    for p in [Precision::F32, Precision::Tf32, Precision::Bf16] {
        assert_eq!(p.to_string().parse::<Precision>().unwrap(), p);
    }
    let e = "fp8".parse::<Precision>().unwrap_err().to_string();
    assert!(e.contains("f32, tf32 or bf16") && e.contains("fp8"), "{e}");
}

/// Under bf16 a matmul inside `forward` runs in bf16 (its result rounded
/// to bf16's 8-bit mantissa), nested regions keep the outer one on, and
/// leaving the outermost turns autocast off again; in f32 nothing changes.
#[test]
fn bf16_forward_runs_matmuls_in_bf16_and_ends_with_the_region() {
    let a = Tensor::from_slice(&[1.0f32 + 1.0 / 512.0, 3.0]).view([1, 2]);
    let b = Tensor::from_slice(&[1.0f32, 0.0]).view([2, 1]);
    with_mode(Precision::Bf16, || {
        let (inner, outer) = forward(Device::Cpu, || {
            let inner = forward(Device::Cpu, || a.matmul(&b));
            (inner, a.matmul(&b))
        });
        assert_eq!((inner.kind(), outer.kind()), (Kind::BFloat16, Kind::BFloat16));
        // 1 + 2^-9 is not a bf16 number: the product rounds to 1.
        assert_eq!(to_f32(outer).double_value(&[0, 0]), 1.0);
        let after = a.matmul(&b);
        assert_eq!(after.kind(), Kind::Float);
        assert_eq!(after.double_value(&[0, 0]), 1.0 + 1.0 / 512.0);
    });
    with_mode(Precision::F32, || {
        let y = forward(Device::Cpu, || a.matmul(&b));
        assert_eq!((y.kind(), y.double_value(&[0, 0])), (Kind::Float, 1.0 + 1.0 / 512.0));
        assert_eq!(current(), Precision::F32);
    });
}
