//! Render benchmarks (issue 2): a 128×128 XY scan of 10 beads + a 10 µm filament, and the
//! template precompute. Run: `cargo bench --bench render`.

use bfpscope::instrument::sim::render_xy;
use bfpscope::instrument::sim::scene::*;
use bfpscope::instrument::sim::Renderer;
use bfpscope::optics::grid::Interp;
use bfpscope::optics::params::Optics;
use bfpscope::optics::rayleigh::{Detection, DetectorModel};
use bfpscope::optics::template::{plane_grid, TemplateSpec};
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
    let optics = Optics::default();
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
    let det = Detection::new(&optics, &DetectorModel::default()).unwrap();
    let mut g = c.benchmark_group("template precompute");
    g.sample_size(10);
    g.bench_function("one plane at z = 0 (h = 20 nm, cubic)", |b| {
        b.iter(|| plane_grid(&det, 0.0, 0.02, Interp::Cubic))
    });
    g.bench_function("renderer for the scene (planes for z = 0)", |b| {
        b.iter(|| {
            let r = Renderer::checked(&optics, &scene(), TemplateSpec::default()).unwrap();
            r.template.prepare(0.0, 0.0);
            r
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
