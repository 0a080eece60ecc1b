use super::*;

fn vars(pairs: &[(&str, &str)]) -> impl Fn(&str) -> Option<String> {
    let map: std::collections::HashMap<String, String> = pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect();
    move |k| map.get(k).cloned()
}

/// A port that was free a moment ago.
pub(crate) fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

#[test]
fn reads_torchruns_environment() {
    assert_eq!(Launch::from_vars(vars(&[])).unwrap(), None);
    let l = Launch::from_vars(vars(&[("WORLD_SIZE", "8"), ("RANK", "5"), ("LOCAL_RANK", "1"), ("MASTER_ADDR", "node0"), ("MASTER_PORT", "29400"), ("TORCHELASTIC_USE_AGENT_STORE", "True"), ("TORCHELASTIC_RESTART_COUNT", "2")])).unwrap().unwrap();
    assert_eq!((l.rank, l.world, l.local_rank, l.master_addr.as_str(), l.master_port, l.agent_store, l.restart), (5, 8, 1, "node0", 29400, true, 2));
    let e = Launch::from_vars(vars(&[("WORLD_SIZE", "2"), ("RANK", "2")])).unwrap_err().to_string();
    assert!(e.contains("RANK=2 must lie below WORLD_SIZE=2"), "{e}");
    let e = Launch::from_vars(vars(&[("WORLD_SIZE", "2")])).unwrap_err().to_string();
    assert!(e.contains("RANK is not") && e.contains("torchrun"), "{e}");
    let e = Launch::from_vars(vars(&[("WORLD_SIZE", "2"), ("RANK", "0"), ("MASTER_PORT", "70000")])).unwrap_err().to_string();
    assert!(e.contains("MASTER_PORT=70000"), "{e}");
}

fn launch(rank: usize, world: usize, port: u16) -> Launch {
    Launch { rank, world, local_rank: rank, master_addr: "127.0.0.1".into(), master_port: port, agent_store: false, restart: 0 }
}

/// Two ranks of one Gloo group, one thread each: sums, averages in
/// buckets (a bucket limit of 3 floats splits the list), the flags summed,
/// broadcast from rank 1.
#[test]
fn two_gloo_ranks_sum_average_and_broadcast() {
    let port = free_port();
    let config = Config { timeout: Duration::from_secs(30), bucket_bytes: 12 };
    let results: Vec<(Vec<f64>, Vec<f32>, Vec<f32>, Vec<f32>)> = std::thread::scope(|s| {
        let handles: Vec<_> = (0..2)
            .map(|rank| {
                let config = config.clone();
                s.spawn(move || {
                    let g = Group::join(&launch(rank, 2, port), Device::Cpu, config).unwrap();
                    let r = rank as f64;
                    let sums = g.sum_f64(&[1.0 + r, 10.0 * r]).unwrap();
                    let a = Tensor::from_slice(&[1f32 + r as f32, 2.0]).view([2, 1]);
                    let b = Tensor::from_slice(&[4f32 * r as f32, 6.0, 8.0]);
                    let flags = g.average(&[a.shallow_clone(), b.shallow_clone()], &[r as f32]).unwrap();
                    let mut c = [Tensor::from_slice(&[r as f32 + 7.0])];
                    g.broadcast(&mut c, 1).unwrap();
                    g.barrier().unwrap();
                    let got: Vec<f32> = Vec::try_from(Tensor::cat(&[a.reshape([-1]), b], 0)).unwrap();
                    (sums, flags, got, Vec::try_from(&c[0]).unwrap())
                })
            })
            .collect();
        handles.into_iter().map(|h| h.join().unwrap()).collect()
    });
    for (sums, flags, got, c) in results {
        assert_eq!(sums, vec![3.0, 10.0]);
        assert_eq!(flags, vec![1.0]);
        assert_eq!(got, vec![1.5, 2.0, 2.0, 6.0, 8.0]);
        assert_eq!(c, vec![8.0]);
    }
}

/// A rank that leaves makes the other's next collective fail in one line
/// well within the timeout (Gloo sees the closed connection).
#[test]
fn a_departed_rank_fails_the_others_collective_in_one_line() {
    let port = free_port();
    let config = Config { timeout: Duration::from_secs(60), bucket_bytes: 1 << 20 };
    let started = std::time::Instant::now();
    let err = std::thread::scope(|s| {
        let leaver = s.spawn({
            let config = config.clone();
            move || {
                let g = Group::join(&launch(1, 2, port), Device::Cpu, config).unwrap();
                g.barrier().unwrap();
                drop(g);
            }
        });
        let g = Group::join(&launch(0, 2, port), Device::Cpu, config).unwrap();
        g.barrier().unwrap();
        leaver.join().unwrap();
        g.sum_f64(&[1.0]).unwrap_err().to_string()
    });
    assert!(started.elapsed() < Duration::from_secs(30), "{:?}", started.elapsed());
    assert!(err.starts_with("rank 0 of 2: all-reduce failed, another rank died") && !err.contains('\n'), "{err}");
}
