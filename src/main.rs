use clap::Parser;

/// The command line: parses options and calls into the library; nothing
/// in the library depends on it.
mod cli;

/// libtorch's OpenMP threads busy-wait after each parallel region by
/// default, which starves the rayon threads that generate and render
/// training data (measured: 4.4 -> 23 materials/s in `bench data`). The
/// policy is read when the library loads, before `main`, so set it and
/// re-execute once.
fn ensure_passive_openmp() {
    use std::os::unix::process::CommandExt;
    if std::env::var_os("OMP_WAIT_POLICY").is_some() {
        return;
    }
    if let Ok(exe) = std::env::current_exe() {
        let err = std::process::Command::new(exe).args(std::env::args_os().skip(1)).env("OMP_WAIT_POLICY", "PASSIVE").exec();
        eprintln!("warning: could not re-execute with OMP_WAIT_POLICY=PASSIVE: {err}");
    }
}

fn main() {
    ensure_passive_openmp();
    // A bug must still end in one line, not a backtrace.
    std::panic::set_hook(Box::new(|info| {
        let msg = info
            .payload()
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| info.payload().downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_default();
        let first = msg.lines().next().unwrap_or("").to_string();
        eprintln!("error: internal error: {first}");
    }));
    let cli = cli::Cli::parse();
    match std::panic::catch_unwind(|| cli::run(cli)) {
        Ok(Ok(())) => {}
        Ok(Err(e)) => {
            eprintln!("error: {e:#}");
            std::process::exit(1);
        }
        Err(_) => std::process::exit(2),
    }
}
