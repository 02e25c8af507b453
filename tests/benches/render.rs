//! Render benchmarks: a 128×128 XY scan of 10 beads + a 10 µm filament,
//! and the template precompute, each next to the kept reference implementation (the code before
//! the speed work) so one run gives before and after on the same machine. Run:
//! `cargo bench --features bench --bench render`; numbers and the floor estimate in docs/performance.md
//! ("Rendering"). `cargo run --release --example render_timing` breaks the times down.
//!
//! Measured 2026-11-25 on the 2-core AMD EPYC build machine (shared, load ≈ 5, so rayon's
//! second core was mostly busy), criterion medians:
//!
//! | bench | before (reference) | after | target |
//! |---|---|---|---|
//! | render 128×128 (ideal) | 10.2 ms | 2.57 ms | ≤ 2 ms |
//! | one plane at z = 0 | 11.1 ms | 0.53 ms | ≤ 3 ms |
//! | renderer for the scene (memo warm) | (3 planes ≈ 25 ms) | 1.60 ms | ≤ 10 ms |
//! | renderer, cold domain check | — | 128 ms | not met (2 Mie responses) |
//!
//! Best-of runs (`render_timing`) on the same machine: render 6.7 → 1.7 ms, plane 5.5 → 0.34 ms.

use bfpscope::instrument::sim::domain::{DomainCheck, DomainMemo};
use bfpscope::instrument::sim::render_xy;
use bfpscope::instrument::sim::scene::*;
use bfpscope::instrument::sim::Renderer;
use bfpscope::optics::grid::Interp;
use bfpscope::optics::rayleigh::{Detection, DetectorModel};
use bfpscope::optics::template::{plane_grid, plane_grid_reference, TemplateSpec};
use bfpscope::optics::ValidOptics;
use criterion::{criterion_group, criterion_main, Criterion};

fn scene() -> Scene {
    let mut s = Scene::default();
    for i in 0..10 {
        let a = i as f64 * 0.628;
        s.add_bead(Bead {
            pos: [4.0 * a.cos(), 4.0 * a.sin(), 0.0],
            d_nm: 110.0 + 10.0 * i as f64,
            n: 1.572,
        })
        .unwrap();
    }
    s.add_filament(Filament {
        points: vec![[-3.0, -5.0], [3.0, 3.0]],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm: 60.0 },
        n: 1.414,
        spacing_nm: 50.0,
    })
    .unwrap();
    s
}

fn bench(c: &mut Criterion) {
    let optics = ValidOptics::default();
    let r = Renderer::checked(&optics, &scene(), TemplateSpec::default()).unwrap();
    let xs: Vec<f64> = (0..128).map(|i| -6.0 + 12.0 * i as f64 / 127.0).collect();
    let _ = render_xy(&r, &xs, &xs, 0.0, 1); // build the template plane once
    let nsc = r.scatterers.len();
    let support = r.template.planes_for(0.0)[0].0.extent().0;
    let frac = ((support.1 - support.0) / 12.0).powi(2).min(1.0);
    eprintln!(
        "render: {nsc} scatterers × 16384 pixels = {} scatterer-pixel pairs, ~{:.0} inside the template support; template memory {:.1} MB",
        nsc * 16384,
        nsc as f64 * 16384.0 * frac,
        r.template.bytes() as f64 / 1e6
    );
    c.bench_function("render 128x128, 10 beads + 10 µm filament (ideal)", |b| {
        b.iter(|| render_xy(&r, &xs, &xs, 0.0, 1))
    });
    c.bench_function(
        "render 128x128, reference path (before the speed work)",
        |b| b.iter(|| r.render_grid_reference(&xs, &xs, 0.0)),
    );
    let det = Detection::new(&optics, &DetectorModel::default()).unwrap();
    let mut g = c.benchmark_group("template precompute");
    g.sample_size(10);
    g.bench_function("one plane at z = 0 (h = 20 nm, cubic)", |b| {
        b.iter(|| plane_grid(&det, 0.0, 0.02, Interp::Cubic))
    });
    g.bench_function(
        "one plane at z = 0, reference (before the speed work)",
        |b| b.iter(|| plane_grid_reference(&det, 0.0, 0.02, Interp::Cubic)),
    );
    // `checked` runs the domain check through the process-wide memo: warm after the first
    // build, as for every `simulate` of a scene seen before
    g.bench_function("renderer for the scene (planes for z = 0)", |b| {
        b.iter(|| {
            let r = Renderer::checked(&optics, &scene(), TemplateSpec::default()).unwrap();
            r.template.prepare(0.0, 0.0);
            r
        })
    });
    // cold: a fresh memo, so the 200 nm bead's domain check runs the Mie tier (two responses)
    g.bench_function("renderer for the scene, cold domain check", |b| {
        b.iter(|| {
            let s = scene();
            let d = DomainCheck::run(&optics, &s, &mut DomainMemo::default());
            let r = Renderer::new(&optics, &s, TemplateSpec::default(), &d).unwrap();
            r.template.prepare(0.0, 0.0);
            r
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
