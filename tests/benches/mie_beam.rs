//! Focused-beam Mie response: cost of one (Sx, Sy, Sz) point, with and without the
//! analytic gradient and the |E_s|² term, vs the incident plane-wave grid; and the per-sphere
//! pair-matrix build. 500 nm polystyrene bead, default optics (512 detection nodes).
//! Run: `cargo bench --features bench --bench mie_beam`.

use bfpscope::optics::mie::Complex64 as C64;
use bfpscope::optics::mie_beam::{MieBeam, MieBeamSpec};
use bfpscope::optics::params::Optics;
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let o = Optics::default();
    let n = C64::new(1.572, 0.0);
    let mut g = c.benchmark_group("mie_beam_point");
    g.sample_size(20);
    for &(nt, np) in &[(8usize, 4usize), (10, 5), (12, 6), (16, 8), (24, 12)] {
        let spec = MieBeamSpec {
            n_theta_in: nt,
            n_phi_in: np,
            ..MieBeamSpec::default()
        };
        let m = MieBeam::new(&o, 500.0, n, spec).unwrap();
        let j = 4 * nt * np;
        g.bench_with_input(BenchmarkId::new("response", j), &m, |b, m| {
            b.iter(|| m.response(black_box(0.31), black_box(-0.12), 0.05).unwrap())
        });
        g.bench_with_input(BenchmarkId::new("response_grad", j), &m, |b, m| {
            b.iter(|| {
                m.response_grad(black_box(0.31), black_box(-0.12), 0.05)
                    .unwrap()
            })
        });
    }
    let full = MieBeam::new(
        &o,
        500.0,
        n,
        MieBeamSpec {
            scattered_intensity: true,
            ..MieBeamSpec::default()
        },
    )
    .unwrap();
    g.bench_function("response_with_scattered_intensity/288", |b| {
        b.iter(|| {
            full.response(black_box(0.31), black_box(-0.12), 0.05)
                .unwrap()
        })
    });
    g.finish();
    let mut g = c.benchmark_group("mie_beam_build");
    g.sample_size(10);
    for d in [110.0, 500.0, 1000.0] {
        g.bench_with_input(BenchmarkId::new("default_grid", d as u32), &d, |b, &d| {
            b.iter(|| MieBeam::new(&o, black_box(d), n, MieBeamSpec::default()).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
