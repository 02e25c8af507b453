//! What the live view costs a scan (the target: within 2 % of the timing without it) and what it
//! holds in memory after 100 scans. Prints a table; not a criterion bench because the peer (the
//! same scan without a view) must be measured in the same run, interleaved, on a noisy machine.
//!
//! `cargo bench --features bench --bench view`
//!
//! - `none`: a 128 × 128 scan on the simulator, no view;
//! - `view, no reader`: the view open, no page connected (what the engine's hand-over costs);
//! - `view, 1 reader`: the view open and one browser-like client reading the event stream;
//! - `view, stalled reader`: one client that connects and never reads (a frozen tab), so its
//!   socket fills up and its sender blocks.
//!
//! Runs alternate between the set-ups (the order rotating every round); the table gives the median wall time of each and
//! its ratio to `none`.
//!
//! Memory: process RSS growth over 100 and 300 scans of 32 × 32 with the view open and a
//! reader, against the same without a view. The bench tunes the allocator as the binary does
//! (`bfpscope::tune_allocator`); `BFPSCOPE_DEFAULT_MALLOC=1` shows glibc's default, where the
//! heap grows by ~0.2 MB per scan. `BFPSCOPE_VIEW_BENCH_MEMORY_ONLY=1` skips the timing,
//! `BFPSCOPE_VIEW_BENCH_MORE=N` runs N scans after the first 100 (default 200).

use bfpscope::script::view::start_view;
use bfpscope::script::{Settings, Workbench};
use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::Instant;

const ROUNDS: usize = 21;
const SCAN: &str = "scan_xy(#{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 128, ny: 128, dwell: 0.0005});";

fn workbench(tag: &str) -> Workbench {
    let dir =
        std::env::temp_dir().join(format!("bfpscope-bench-view-{}-{tag}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let (s, _) = Settings::captured(dir);
    let mut w = Workbench::new(s);
    let _ = w
        .eval_line(
            "let s = scene(); s.add_bead(#{x: 0.0, y: 0.0, d_nm: 110.0, n: 1.572}); \
             connect(#{backend: \"sim\", scene: s});",
        )
        .unwrap();
    w
}

/// Open the event stream of `url`; `read`: keep reading it in a thread (a live tab).
fn client(url: &str, read: bool) -> TcpStream {
    let rest = url.trim_start_matches("http://");
    let (addr, query) = rest.split_once('/').unwrap();
    let mut s = TcpStream::connect(addr).unwrap();
    let q = query.trim_start_matches('?');
    write!(
        s,
        "GET /events?{q} HTTP/1.1\r\nHost: {addr}\r\nAccept: text/event-stream\r\n\r\n"
    )
    .unwrap();
    if read {
        let mut r = s.try_clone().unwrap();
        std::thread::spawn(move || {
            let mut buf = [0u8; 65536];
            while matches!(r.read(&mut buf), Ok(n) if n > 0) {}
        });
    } else {
        // a frozen tab: the smallest receive buffer, never read
        let _ = s.set_nonblocking(false);
    }
    s
}

fn time(w: &mut Workbench) -> f64 {
    let t0 = Instant::now();
    let _ = w.eval_line(SCAN).unwrap();
    t0.elapsed().as_secs_f64()
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

fn rss_kib() -> u64 {
    status_field("VmRSS:")
}

fn status_field(name: &str) -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with(name))
                .and_then(|l| l.split_whitespace().nth(1).and_then(|n| n.parse().ok()))
        })
        .unwrap_or(0)
}

fn main() {
    if std::env::args().any(|a| a == "--list") {
        return; // `cargo test --benches` asks for the list of benchmarks
    }
    if std::env::var_os("BFPSCOPE_DEFAULT_MALLOC").is_none() {
        bfpscope::tune_allocator(); // as the binary does
    }
    if std::env::var_os("BFPSCOPE_VIEW_BENCH_MEMORY_ONLY").is_none() {
        timing();
    }
    memory();
}

fn timing() {
    let mut plain = workbench("none");
    let mut live = workbench("live");
    let url = start_view(&live.ctx, "127.0.0.1", 0).unwrap();
    let _reader = client(&url, true);
    let mut quiet = workbench("quiet");
    start_view(&quiet.ctx, "127.0.0.1", 0).unwrap();
    let mut stalled = workbench("stalled");
    let url2 = start_view(&stalled.ctx, "127.0.0.1", 0).unwrap();
    let _frozen = client(&url2, false);

    // warm up (render caches, page cache)
    for w in [&mut plain, &mut quiet, &mut live, &mut stalled] {
        time(w);
    }
    // the order rotates every round, so no set-up always runs first (cache, frequency)
    let mut t: [Vec<f64>; 4] = Default::default();
    for round in 0..ROUNDS {
        for k in 0..4 {
            let i = (round + k) % 4;
            let w = match i {
                0 => &mut plain,
                1 => &mut quiet,
                2 => &mut live,
                _ => &mut stalled,
            };
            t[i].push(time(w));
        }
    }
    let [a, d, b, c] = t;
    let (ma, mb, mc, md) = (median(a), median(b), median(c), median(d));
    println!("128 × 128 scan on the simulator, median of {ROUNDS} interleaved runs");
    println!("| set-up | wall ms | ratio to no view |");
    println!("|---|---|---|");
    println!("| no view | {:.2} | 1.000 |", ma * 1e3);
    println!("| view, no reader | {:.2} | {:.3} |", md * 1e3, md / ma);
    println!("| view, 1 reader | {:.2} | {:.3} |", mb * 1e3, mb / ma);
    println!(
        "| view, stalled reader | {:.2} | {:.3} |",
        mc * 1e3,
        mc / ma
    );
}

fn memory() {
    // memory after 100 scans, with the view open and without (the peer)
    let small = "scan_xy(#{x: [-1.0, 1.0], y: [-1.0, 1.0], nx: 32, ny: 32, dwell: 0.0005});";
    let mut p = workbench("memory-peer");
    let rss0 = rss_kib();
    for _ in 0..100 {
        let _ = p.eval_line(small).unwrap();
    }
    let peer = rss_kib() as i64 - rss0 as i64;
    drop(p);
    let mut m = workbench("memory");
    let url3 = start_view(&m.ctx, "127.0.0.1", 0).unwrap();
    let hub = m.ctx.view_hub().unwrap();
    let _r = client(&url3, true);
    let rss0 = rss_kib();
    for _ in 0..100 {
        let _ = m.eval_line(small).unwrap();
    }
    let with = rss_kib() as i64 - rss0 as i64;
    let held100 = hub.held_bytes();
    // and more (200, or $BFPSCOPE_VIEW_BENCH_MORE): bounded, or growing with the number of scans?
    let more: usize = std::env::var("BFPSCOPE_VIEW_BENCH_MORE")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(200);
    for _ in 0..more {
        let _ = m.eval_line(small).unwrap();
    }
    let with300 = rss_kib() as i64 - rss0 as i64;
    println!();
    println!(
        "after 100 scans of 32 × 32: the view holds {held100} bytes (the last scan's points, 100 list rows; \
         {} bytes after {}); process RSS grew {with} KiB with the view ({with300} KiB after {}), {peer} KiB \
         over 100 scans without",
        hub.held_bytes(),
        100 + more,
        100 + more
    );
}
