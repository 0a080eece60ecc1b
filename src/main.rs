use clap::Parser;

/// The command line: parses options and calls into the library; nothing
/// in the library depends on it.
mod cli;

/// libtorch's OpenMP threads busy-wait after each parallel region by
/// default (300,000 spins), which starves the rayon threads that generate
/// and render training data (measured: 4.4 -> 23 materials/s in `bench
/// data`); PASSIVE alone (no spinning) puts them to sleep after every
/// region instead, and the training step's many small ops then paid a
/// futex wake-up each (a fifth of its samples in the kernel's scheduler,
/// step 1.6 s against 0.87 s with a short spin; `reports/training-speed.md`).
/// So: passive, after `SPIN_COUNT` polls (a fraction of a millisecond;
/// libgomp pauses between polls). Both are read when the library loads,
/// before `main`, so set the missing ones and re-execute once; a variable
/// the user set is kept.
fn ensure_passive_openmp() {
    use std::os::unix::process::CommandExt;
    let missing = openmp_settings_to_add(std::env::var_os("OMP_WAIT_POLICY").as_deref(), std::env::var_os("GOMP_SPINCOUNT").as_deref());
    if missing.is_empty() {
        return;
    }
    if let Ok(exe) = std::env::current_exe() {
        let settings: Vec<String> = missing.iter().map(|(name, value)| format!("{name}={value}")).collect();
        let err = std::process::Command::new(exe).args(std::env::args_os().skip(1)).envs(missing).exec();
        eprintln!("warning: could not re-execute with {}: {err}", settings.join(" "));
    }
}

/// libgomp's polls before a passive worker sleeps (5,000 to 100,000
/// measured alike; 2,000 too few).
const SPIN_COUNT: &str = "10000";

/// The OpenMP variables `ensure_passive_openmp` adds, given the ones set:
/// the policy when unset; the spin count when unset and the policy is (or
/// becomes) passive, so an ACTIVE or spin count of the user's stays theirs.
fn openmp_settings_to_add(policy: Option<&std::ffi::OsStr>, spincount: Option<&std::ffi::OsStr>) -> Vec<(&'static str, &'static str)> {
    let mut add = Vec::new();
    if policy.is_none() {
        add.push(("OMP_WAIT_POLICY", "PASSIVE"));
    }
    let passive = policy.is_none_or(|p| p.eq_ignore_ascii_case("passive"));
    if spincount.is_none() && passive {
        add.push(("GOMP_SPINCOUNT", SPIN_COUNT));
    }
    add
}

/// glibc serves every allocation above its mmap threshold (at most 32 MiB)
/// with a fresh mapping, unmapped again on free, so each large activation
/// of M_est (a 64-channel 256x256 layer is 16 MiB, a 16-channel 768x768
/// one 36 MiB) costs page faults and the kernel zeroing its pages, in every
/// layer of every forward. Keeping freed memory in the heap for reuse
/// (no mmap, no trimming) made the compact M_est at 768x768 2.1x faster
/// and the paper's at 256x256 1.2x; a 1024x1024 `estimate` took half the
/// time (`reports/inference-speed.md`). The heap fragments, so the whole
/// forward's peak grows (1.1x at 1024x1024, up to 1.5x at 1536x1024; the
/// memory plan allows for it: `infer::tiles::WHOLE_HEAP_SLACK`). Freed
/// memory is returned at exit.
/// FLASHMAT_MALLOC_DEFAULTS=1 keeps glibc's defaults (for A/B timings).
fn keep_freed_memory() {
    if std::env::var_os("FLASHMAT_MALLOC_DEFAULTS").is_some() {
        return;
    }
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: mallopt only changes allocator parameters; called before the
    // program starts other threads of its own.
    unsafe {
        libc::mallopt(libc::M_MMAP_MAX, 0);
        libc::mallopt(libc::M_TRIM_THRESHOLD, -1);
    }
}

/// The command's [`cli::memory_hint`], for the panic hook (set once the
/// options are parsed).
static MEMORY_HINT: std::sync::OnceLock<&'static str> = std::sync::OnceLock::new();

/// Set by the panic hook when the panic was libtorch running out of memory:
/// an ordinary error (exit 1), not a bug.
static OUT_OF_MEMORY: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// The one line of an out-of-memory error, if `message` is one.
fn out_of_memory_line(message: &str) -> Option<String> {
    let hint = MEMORY_HINT.get().copied().unwrap_or("lower --size");
    flashmat::limits::out_of_memory(message).map(|oom| format!("{oom}: {hint}"))
}

/// An error as one line: its chain of contexts, where a libtorch
/// out-of-memory (whose message carries a C++ backtrace) ends the line
/// with what to lower instead.
fn error_line(e: &anyhow::Error) -> String {
    flashmat::limits::error_line(e, MEMORY_HINT.get().copied().unwrap_or("lower --size")).0
}

fn main() {
    ensure_passive_openmp();
    keep_freed_memory();
    // A bug must still end in one line, not a backtrace; libtorch running
    // out of memory (tch's methods panic on its errors) is no bug: one line
    // saying what to lower. Outputs are written atomically and checkpoints
    // replaced by rename, so what was written before stays whole.
    std::panic::set_hook(Box::new(|info| {
        let msg = info
            .payload()
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| info.payload().downcast_ref::<&str>().map(|s| s.to_string()))
            .unwrap_or_default();
        if let Some(line) = out_of_memory_line(&msg) {
            // Only the first of several threads' panics is reported.
            if !OUT_OF_MEMORY.swap(true, std::sync::atomic::Ordering::SeqCst) {
                eprintln!("error: {line}");
            }
            return;
        }
        let first = msg.lines().next().unwrap_or("").to_string();
        eprintln!("error: internal error: {first}");
    }));
    let cli = match cli::Cli::try_parse() {
        Ok(cli) => cli,
        // --help and --version (exit 0), and a bare `flashmat` (its help, exit 2): clap's own text.
        Err(e) if !e.use_stderr() || e.kind() == clap::error::ErrorKind::DisplayHelpOnMissingArgumentOrSubcommand => e.exit(),
        Err(e) => {
            eprintln!("error: {}", argument_error_line(&e, &std::env::args().collect::<Vec<_>>()));
            std::process::exit(2);
        }
    };
    let _ = MEMORY_HINT.set(cli::memory_hint(&cli.command));
    match std::panic::catch_unwind(|| cli::run(cli)) {
        Ok(Ok(())) => {}
        Ok(Err(e)) => {
            eprintln!("error: {}", error_line(&e));
            std::process::exit(1);
        }
        Err(_) if OUT_OF_MEMORY.load(std::sync::atomic::Ordering::SeqCst) => std::process::exit(1),
        Err(_) => std::process::exit(2),
    }
}

/// A refused command line (`args`, the program first) as one line: clap's
/// error, then its tip if it has one (the usage block and "For more
/// information" left out: `--help` says it).
fn argument_error_line(e: &clap::Error, args: &[String]) -> String {
    let text = e.render().to_string();
    // Paragraphs: the error (with what it lists, indented), tips, the usage, the pointer to --help.
    let paragraphs: Vec<String> = text.split("\n\n").map(|p| p.lines().map(str::trim).filter(|l| !l.is_empty()).collect::<Vec<_>>().join(" ")).filter(|p| !p.is_empty()).collect();
    let first = paragraphs.first().map_or("the command line was refused", |p| p.trim_start_matches("error:").trim());
    // clap takes a negative number for an option's value as an unknown
    // option and tips '-- -8', which no option of ours reads: say what it is.
    let negative = |v: &str| v.strip_prefix('-').is_some_and(|rest| rest.starts_with(|c: char| c.is_ascii_digit() || c == '.'));
    if let Some(value) = e.get(clap::error::ContextKind::InvalidArg).map(|v| v.to_string()).filter(|v| negative(v)) {
        // clap names '-1' of '-1G' (a cluster of short options): the argument as given.
        let at = args.iter().position(|a| a.starts_with(&value));
        let given = at.map_or(value.clone(), |i| args[i].clone());
        let option = at.and_then(|i| args[..i].last()).filter(|a| a.starts_with('-')).map_or("the option before it".to_string(), |a| a.clone());
        return format!("{option} {given}: {option} takes no negative numbers (--help lists the options)");
    }
    let tips: Vec<&str> = paragraphs.iter().filter_map(|p| p.strip_prefix("tip:")).map(str::trim).collect();
    if tips.is_empty() {
        format!("{first} (--help lists the options)")
    } else {
        format!("{first} ({}; --help lists the options)", tips.join("; "))
    }
}

#[cfg(test)]
mod tests {
    use super::{argument_error_line, error_line, openmp_settings_to_add};
    use clap::Parser;
    use std::ffi::OsStr;

    /// An out-of-memory deep in an error's chain (libtorch's message, C++
    /// backtrace and all) ends the one line with what to lower; other
    /// errors keep their chain.
    #[test]
    fn out_of_memory_errors_are_one_line() {
        let torch = "CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of 79.19 GiB of which 1.50 GiB is free.\nException raised from malloc at CUDACachingAllocator.cpp:1463 (most recent call first):\nframe #0: c10::Error::Error";
        let e = anyhow::anyhow!(torch).context("estimating p.png with model m.safetensors");
        assert_eq!(
            error_line(&e),
            "estimating p.png with model m.safetensors: out of GPU memory (tried to allocate 2.00 GiB; 1.50 GiB of the card's 79.19 GiB free): lower --size"
        );
        let e = anyhow::anyhow!("no such file").context("cannot read p.png");
        assert_eq!(error_line(&e), "cannot read p.png: no such file");
    }

    /// A refused command line is one line that names the option and the value.
    #[test]
    fn argument_errors_are_one_line() {
        let line_of = |args: &[&str]| {
            let e = crate::cli::Cli::try_parse_from(args).err().expect("refused");
            argument_error_line(&e, &args.iter().map(|a| a.to_string()).collect::<Vec<_>>())
        };
        let line = line_of(&["flashmat", "estimate", "p.png", "-o", "m.nmat", "--size", "abc"]);
        assert!(!line.contains('\n') && line.contains("'abc'") && line.contains("--size"), "{line}");
        let line = line_of(&["flashmat", "estimate", "p.png", "-o", "m.nmat", "--sise", "64"]);
        assert!(!line.contains('\n') && line.contains("--sise") && line.contains("similar argument exists: '--size'"), "{line}");
        let line = line_of(&["flashmat", "estimate", "p.png", "-o", "m.nmat", "--size", "-8"]);
        assert_eq!(line, "--size -8: --size takes no negative numbers (--help lists the options)");
        let line = line_of(&["flashmat", "estimate", "p.png", "-o", "m.nmat", "--max-memory", "-1G"]);
        assert_eq!(line, "--max-memory -1G: --max-memory takes no negative numbers (--help lists the options)");
        let line = line_of(&["flashmat", "capture", "a.jpg"]);
        assert!(!line.contains('\n') && line.contains("not provided: --output <OUTPUT>"), "{line}");
    }

    #[test]
    fn openmp_settings_add_only_what_is_missing() {
        let set = |v: &'static str| Some(OsStr::new(v));
        assert_eq!(openmp_settings_to_add(None, None), [("OMP_WAIT_POLICY", "PASSIVE"), ("GOMP_SPINCOUNT", "10000")]);
        assert_eq!(openmp_settings_to_add(set("passive"), None), [("GOMP_SPINCOUNT", "10000")]);
        assert_eq!(openmp_settings_to_add(set("PASSIVE"), set("0")), []);
        assert_eq!(openmp_settings_to_add(None, set("0")), [("OMP_WAIT_POLICY", "PASSIVE")]);
        // A user's ACTIVE keeps libgomp's own spin count for it.
        assert_eq!(openmp_settings_to_add(set("ACTIVE"), None), []);
    }
}
