//! The vector beam's speed targets: building one vector-beam template plane (all three signals on the
//! template grid, from which the renderer takes the x/y derivatives by its stencil), and the
//! 128×128 render of 10 beads + a 10 µm filament in the vector beam vs the paraxial beam (the
//! `render` bench's scene), once the templates exist.
//! Run: `RAYON_NUM_THREADS=1 cargo bench --features bench --bench vector_beam` (one core).

use bfpscope::instrument::sim::render_xy;
use bfpscope::instrument::sim::scene::*;
use bfpscope::instrument::sim::Renderer;
use bfpscope::optics::mie_template::{MieTemplate, MieTemplateSpec};
use bfpscope::optics::params::{Beam, Optics};
use bfpscope::optics::template::TemplateSpec;
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
    let vector = Optics {
        beam: Beam::Vector,
        ..Optics::default()
    };
    let mut g = c.benchmark_group("vector beam template");
    g.sample_size(10);
    let spec = MieTemplateSpec {
        grid: TemplateSpec::default(),
        detector: Default::default(),
        scattered_intensity: false,
    };
    // the simulator's point dipole: exact dipole amplitudes, factorised evaluation; the
    // template's construction (its reach: the focal field's radii) apart from the plane
    g.bench_function("point dipole template, construction", |b| {
        b.iter(|| MieTemplate::point_dipole(&vector, spec).unwrap())
    });
    let dipole = MieTemplate::point_dipole(&vector, spec).unwrap();
    g.bench_function("one plane at z = 0 (point dipole, default grid)", |b| {
        b.iter(|| dipole.plane_uncached(0).unwrap())
    });
    // the same plane through the full pair matrix of a 1 nm Lorenz–Mie sphere (before)
    let sphere = MieTemplate::new(&vector, 1.0, 1.5, spec).unwrap();
    g.bench_function("one plane at z = 0 (1 nm Mie sphere, pair matrix)", |b| {
        b.iter(|| sphere.plane_uncached(0).unwrap())
    });
    g.finish();
    let xs: Vec<f64> = (0..128).map(|i| -6.0 + 12.0 * i as f64 / 127.0).collect();
    let mut g = c.benchmark_group("render 128x128, 10 beads + 10 µm filament");
    g.sample_size(20);
    let paraxial = Optics {
        beam: Beam::Paraxial,
        ..Optics::default()
    };
    for (name, o) in [("paraxial", paraxial), ("vector", vector.clone())] {
        let r = Renderer::checked(&o, &scene(), TemplateSpec::default()).unwrap();
        let _ = render_xy(&r, &xs, &xs, 0.0, 1); // templates built once
        g.bench_function(name, |b| b.iter(|| render_xy(&r, &xs, &xs, 0.0, 1)));
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
