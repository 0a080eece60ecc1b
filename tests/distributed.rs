//! Data-parallel training (issue 51, docs/DISTRIBUTED.md) end to end: two
//! `flashmat train` processes on this machine, placed by the variables
//! torchrun sets (RANK, WORLD_SIZE, LOCAL_RANK, MASTER_ADDR, MASTER_PORT),
//! joined by libtorch's Gloo process group.

mod common;

use common::{assert_ok, s, stderr};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Output, Stdio};
use std::time::{Duration, Instant};
use tch::Tensor;

const BIN: &str = env!("CARGO_BIN_EXE_flashmat");

/// A port that was free a moment ago.
fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// `flashmat ARGS` as rank `rank` of `world` (one libtorch thread: the
/// ranks share the machine's cores).
fn rank_command(args: &[&str], rank: usize, world: usize, port: u16) -> Command {
    let mut cmd = Command::new(BIN);
    cmd.args(args)
        .env("WORLD_SIZE", world.to_string())
        .env("RANK", rank.to_string())
        .env("LOCAL_RANK", rank.to_string())
        .env("MASTER_ADDR", "127.0.0.1")
        .env("MASTER_PORT", port.to_string())
        .env("OMP_NUM_THREADS", "1")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    cmd
}

/// Runs `world` ranks of `flashmat ARGS` to the end; their outputs by rank.
fn run_ranks(args: &[&str], world: usize) -> Vec<Output> {
    let port = free_port();
    let children: Vec<Child> = (0..world).map(|r| rank_command(args, r, world, port).spawn().expect("start flashmat")).collect();
    children.into_iter().map(|c| c.wait_with_output().unwrap()).collect()
}

fn log_lines(run: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(run.join("log.jsonl")).unwrap().lines().map(|l| serde_json::from_str(l).unwrap()).collect()
}

/// The networks' variables of a checkpoint (`est/`, `renderer/`, `disc/`), by name.
fn weights(run: &Path) -> Vec<(String, Tensor)> {
    let mut v: Vec<(String, Tensor)> = Tensor::read_safetensors(run.join("checkpoint.safetensors")).unwrap().into_iter().filter(|(n, _)| !n.starts_with("opt_")).collect();
    v.sort_by(|a, b| a.0.cmp(&b.0));
    v
}

fn bundled_model() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("models/flashmat.safetensors")
}

/// The proof that it is the same training: the same global batch of 2
/// materials as 2 ranks x --batch 1 and as 1 rank x --batch 2, three steps
/// from the bundled model, every network's gradient averaged over the
/// ranks. Every logged loss agrees to float rounding at every step, and
/// every weight after the three updates to within half the learning rate
/// (1e-4: a missed or doubled gradient moves weights by that much). The
/// per-rank shares run M_est's convolutions at another batch size, whose
/// kernels round differently; nothing else differs. BatchNorm runs on its
/// running statistics (`--frozen-bn-from 0`) and the adversarial term is
/// off: on batch statistics, and with the discriminator's "another
/// material" pairs, each rank sees only its share (as PyTorch's DDP
/// without SyncBatchNorm), which the docs say.
#[test]
fn two_ranks_train_as_one_process_with_their_global_batch() {
    let dir = tempfile::tempdir().unwrap();
    let model = bundled_model();
    let run = |name: &str, batch: &str| -> Vec<String> {
        let out = dir.path().join(name);
        let a = [
            "train", "--preset", "compact-f8", "--ldr", "--warm-start", s(&model), "--crop", "32", "--outputs", "2", "--steps", "45663", "--frozen-bn-from", "0",
            "--adv-weight", "0", "--pixel-sampling", "all", "--checkpoint-every", "100000", "--preview-every", "0", "--threads", "1", "--batch", batch, "--out", s(&out),
        ];
        a.iter().map(|x| x.to_string()).collect()
    };
    let args2 = run("world2", "1");
    let outs = run_ranks(&args2.iter().map(String::as_str).collect::<Vec<_>>(), 2);
    for o in &outs {
        assert_ok(o);
    }
    assert!(stderr(&outs[0]).contains("2 ranks (Gloo) x --batch 1 = a global batch of 2 materials a step"), "{}", stderr(&outs[0]));
    // Rank 1 writes nothing and says nothing.
    assert_eq!(stderr(&outs[1]).trim(), "");
    let args1 = run("world1", "2");
    assert_ok(&run_ranks(&args1.iter().map(String::as_str).collect::<Vec<_>>(), 1)[0]);

    let (w2, w1) = (dir.path().join("world2"), dir.path().join("world1"));
    let (l2, l1) = (log_lines(&w2), log_lines(&w1));
    assert_eq!((l2.len(), l1.len()), (3, 3));
    for (a, b) in l2.iter().zip(&l1) {
        assert_eq!(a["skipped"], false);
        for key in ["l1", "lpips", "loss_est", "l1_render", "loss_render", "param_norm"] {
            let (x, y) = (a[key].as_f64().unwrap(), b[key].as_f64().unwrap());
            assert!((x - y).abs() <= 1e-5 * y.abs().max(1e-3), "step {} {key}: 2 ranks {x}, 1 rank {y}", a["step"]);
        }
    }
    let before = Tensor::read_safetensors(&model).unwrap();
    let moved = |name: &str, t: &Tensor| before.iter().find(|(n, _)| name.ends_with(n.as_str())).map(|(_, b)| (t - b).abs().max().double_value(&[]));
    let (mut worst, mut largest_move) = (0f64, 0f64);
    for ((n2, t2), (n1, t1)) in weights(&w2).iter().zip(&weights(&w1)) {
        assert_eq!(n2, n1);
        worst = worst.max((t2 - t1).abs().max().double_value(&[]));
        if n2.starts_with("est/") {
            largest_move = largest_move.max(moved(n2, t1).unwrap_or(0.0));
        }
    }
    // Adam divides each gradient by its own running magnitude, so a weight
    // whose gradient is at rounding level can move by a good part of the
    // learning rate on rounding alone (1.8e-5 on an AVX-512 machine, a few
    // 1e-6 on others); a missed or doubled rank's share flips the direction
    // of many updates, 2e-4 apart. Half the learning rate tells them apart.
    assert!(worst < 5e-5, "weights differ by {worst}");
    // The steps moved M_est's weights by the learning rate's order: the match is not that of untouched weights.
    assert!(largest_move > 1e-4, "M_est moved by {largest_move}");
}

/// Waits for `path` to exist (a checkpoint being written).
fn wait_for(path: &Path, limit: Duration) {
    let t = Instant::now();
    while !path.exists() {
        assert!(t.elapsed() < limit, "{} did not appear", path.display());
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A rank that dies (SIGKILL: no handler runs) makes the other stop within
/// seconds with one error line and exit code 1; the checkpoint it had
/// written stays whole (it exports). Any world size resumes any
/// checkpoint: the 2-rank run resumes in one process, then in 2 ranks
/// again, its steps and log continuing, still drawing its global batch per
/// material.
#[test]
fn a_killed_rank_stops_the_other_in_one_line_and_the_run_resumes_at_any_world_size() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let args = ["train", "--preset", "tiny", "--crop", "32", "--outputs", "2", "--steps", "100000", "--checkpoint-every", "2", "--preview-every", "0", "--threads", "1", "--out", s(&run)];
    let port = free_port();
    let mut rank0 = rank_command(&args, 0, 2, port).spawn().unwrap();
    let mut rank1 = rank_command(&args, 1, 2, port).spawn().unwrap();
    wait_for(&run.join("checkpoint.safetensors"), Duration::from_secs(60));
    rank1.kill().unwrap();
    rank1.wait().unwrap();
    let killed = Instant::now();
    let out = loop {
        if rank0.try_wait().unwrap().is_some() {
            break rank0.wait_with_output().unwrap();
        }
        assert!(killed.elapsed() < Duration::from_secs(30), "rank 0 still runs 30 s after rank 1 died");
        std::thread::sleep(Duration::from_millis(50));
    };
    let err = stderr(&out);
    assert_eq!(out.status.code(), Some(1), "{err}");
    let errors: Vec<&str> = err.lines().filter(|l| l.starts_with("error: ")).collect();
    assert_eq!(errors.len(), 1, "{err}");
    assert_eq!(err.lines().last(), Some(errors[0]), "{err}");
    for needle in ["rank 0 of 2", "another rank died", "the last checkpoint is kept"] {
        assert!(errors[0].contains(needle), "'{needle}' not in: {err}");
    }
    assert!(!err.contains("panicked") && !err.contains("frame #"), "{err}");
    common::no_temp_files(&run);
    let export = dir.path().join("model.safetensors");
    assert_ok(&common::flashmat(&["export", "--run", s(&run), "-o", s(&export)]));
    // The resume starts from the checkpoint's step (the log beyond it is dropped).
    let at = flashmat::train::Trainer::resume(&run.join("checkpoint.safetensors"), tch::Device::Cpu, None).unwrap().step;
    assert!(at >= 2 && at % 2 == 0, "checkpoint at step {at}");
    let total = (at + 1).to_string();
    assert_ok(&common::flashmat(&["train", "--resume", s(&run), "--steps", &total, "--threads", "1"]));
    let total = (at + 2).to_string();
    let outs = run_ranks(&["train", "--resume", s(&run), "--steps", &total, "--threads", "1"], 2);
    for o in &outs {
        assert_ok(o);
    }
    assert!(stderr(&outs[0]).contains(&format!("at step {total} of {total}")), "{}", stderr(&outs[0]));
    let steps: Vec<u64> = log_lines(&run).iter().map(|l| l["step"].as_u64().unwrap()).collect();
    assert_eq!(steps, (1..=at + 2).collect::<Vec<_>>());
    assert!(log_lines(&run).iter().all(|l| l["skipped"] == false));
    let config = flashmat::train::Trainer::checkpoint_config(&run.join("checkpoint.safetensors")).unwrap();
    assert!(config.material_streams && config.steps == at + 2);
}

/// torchrun itself (PyTorch's launcher, beside the libtorch flashmat
/// links): its agent serves the store (`TORCHELASTIC_USE_AGENT_STORE`),
/// every rank joins as a client. Skipped, saying so, where torchrun is
/// not on PATH (scripts/env.sh puts it there).
#[test]
fn torchrun_launches_two_ranks() {
    let Some(torchrun) = std::env::var_os("PATH").and_then(|p| std::env::split_paths(&p).map(|d| d.join("torchrun")).find(|t| t.is_file())) else {
        eprintln!("skipped: no torchrun on PATH (source scripts/env.sh)");
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let out = Command::new(torchrun)
        .args(["--standalone", "--nproc-per-node", "2", "--no-python", BIN])
        .args(["train", "--preset", "tiny", "--crop", "32", "--outputs", "2", "--steps", "2", "--checkpoint-every", "100", "--preview-every", "0", "--threads", "1", "--out", s(&run)])
        .env("OMP_NUM_THREADS", "1")
        .output()
        .unwrap();
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("data-parallel training: 2 ranks (Gloo) x --batch 2 = a global batch of 4 materials a step"), "{err}");
    assert_eq!(log_lines(&run).len(), 2);
    assert!(run.join("checkpoint.safetensors").is_file());
}

/// Every rank takes rank 0's decisions: given different `--minutes`, rank
/// 0's (0: stop after the first step) stops both ranks at that step, with
/// rank 0's checkpoint, both exiting 0; rank 1's own time box (1000
/// minutes) does not keep it waiting for a step that never comes.
#[test]
fn the_time_box_is_rank_0s_and_every_rank_stops_with_it() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let port = free_port();
    let args = |minutes: &'static str| -> Vec<String> {
        ["train", "--preset", "tiny", "--crop", "32", "--outputs", "2", "--steps", "1000", "--checkpoint-every", "100", "--preview-every", "0", "--threads", "1", "--minutes", minutes, "--out", s(&run)]
            .iter()
            .map(|a| a.to_string())
            .collect()
    };
    let ranks: Vec<Child> = [("0", 0), ("1000", 1)].into_iter().map(|(m, r)| rank_command(&args(m).iter().map(String::as_str).collect::<Vec<_>>(), r, 2, port).spawn().unwrap()).collect();
    let outs: Vec<Output> = ranks.into_iter().map(|c| c.wait_with_output().unwrap()).collect();
    for o in &outs {
        assert_ok(o);
    }
    assert_eq!(log_lines(&run).len(), 1);
    let at = flashmat::train::Trainer::resume(&run.join("checkpoint.safetensors"), tch::Device::Cpu, None).unwrap().step;
    assert_eq!(at, 1);
}
