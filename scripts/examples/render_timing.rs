//! Where the renderer's time goes: times the stages of building a renderer for the
//! render bench's scene (10 beads + a 10 µm filament, paraxial beam), the parts of one template
//! plane, and the 128 × 128 render. Run: `cargo run --release --example render_timing`.

use bfpscope::instrument::sim::domain::{DomainCheck, DomainMemo};
use bfpscope::instrument::sim::render_xy;
use bfpscope::instrument::sim::scene::*;
use bfpscope::instrument::sim::Renderer;
use bfpscope::optics::grid::Interp;
use bfpscope::optics::params::{Beam, Optics};
use bfpscope::optics::rayleigh::{Detection, DetectorModel};
use bfpscope::optics::template::{plane_grid, plane_grid_reference, TemplateSpec, SUPPORT_W};
use bfpscope::optics::ValidOptics;
use ndarray::Array2;
use std::time::Instant;

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

/// Best (minimum) wall time of `f` over `n` runs, ms.
fn best<T>(n: usize, mut f: impl FnMut() -> T) -> f64 {
    let mut b = f64::INFINITY;
    for _ in 0..n {
        let t = Instant::now();
        std::hint::black_box(f());
        b = b.min(t.elapsed().as_secs_f64() * 1e3);
    }
    b
}

fn main() {
    // pinned to the paraxial beam the numbers in docs/performance.md were measured in (the
    // default beam is the vector focus since the one-beam work)
    let optics = ValidOptics::new(Optics {
        beam: Beam::Paraxial,
        ..Optics::default()
    })
    .unwrap();
    let sc = scene();
    println!("renderer for the scene, by stage (best of 5, ms):");
    let t_det = best(5, || {
        Detection::new(&optics, &DetectorModel::default()).unwrap()
    });
    println!("  Detection::new (cone nodes)        {t_det:8.3}");
    let t_dom = best(5, || {
        DomainCheck::run(&optics, &sc, &mut DomainMemo::default())
    });
    let dom = DomainCheck::run(&optics, &sc, &mut DomainMemo::default());
    println!(
        "  domain check ({} suspect species)   {t_dom:8.3}",
        dom.entries.len()
    );
    let t_one = best(3, || {
        bfpscope::optics::mie_beam::max_sensitivity_per_alpha(&optics, 200.0, 1.572).unwrap()
    });
    println!("    of which one Mie response M/α        {t_one:8.3}  (the check needs the bead's and the 110 nm reference's)");
    let _ = DomainCheck::run_shared(&optics, &sc);
    let t_dom_warm = best(5, || DomainCheck::run_shared(&optics, &sc));
    println!("  domain check, process memo warm    {t_dom_warm:8.3}");
    let t_sc = best(5, || sc.scatterers(optics.n_medium));
    println!("  scene.scatterers                   {t_sc:8.3}");
    let t_new = best(5, || {
        Renderer::new(&optics, &sc, TemplateSpec::default(), &dom).unwrap()
    });
    println!("  Renderer::new (no check, no plane) {t_new:8.3}");
    let t_all = best(5, || {
        let r = Renderer::new(&optics, &sc, TemplateSpec::default(), &dom).unwrap();
        r.template.prepare(0.0, 0.0);
        r
    });
    let r0 = Renderer::new(&optics, &sc, TemplateSpec::default(), &dom).unwrap();
    r0.template.prepare(0.0, 0.0);
    println!(
        "  new + planes for z = 0             {t_all:8.3}  ({} planes: cubic convolution in z builds iz = -1, 0, 1)",
        r0.template.n_planes()
    );
    let t_chk = best(5, || {
        let r = Renderer::checked(&optics, &sc, TemplateSpec::default()).unwrap();
        r.template.prepare(0.0, 0.0);
        r
    });
    println!("  checked (memo warm) + planes       {t_chk:8.3}");
    println!(
        "  cold total (fresh memo) ≈ domain check + new + planes = {:.3}",
        t_dom + t_all
    );

    let det = Detection::new(&optics, &DetectorModel::default()).unwrap();
    let t_plane = best(10, || plane_grid(&det, 0.0, 0.02, Interp::Cubic));
    let t_pref = best(10, || plane_grid_reference(&det, 0.0, 0.02, Interp::Cubic));
    println!(
        "one plane at z = 0 (h = 20 nm): {t_plane:.3} ms (reference {t_pref:.3} ms); the reference's parts:"
    );
    // the parts of plane_grid, as it computes them
    let (z, h) = (0.0, 0.02);
    let (w, inv_r, _gouy) = det.beam_at(z);
    let half = ((SUPPORT_W * w) / h).ceil() as usize;
    let n = 2 * half + 1;
    let kn = det.nodes.len();
    let k = det.k;
    let coords: Vec<f64> = (0..n).map(|i| -(half as f64) * h + i as f64 * h).collect();
    let t_exp = best(10, || {
        let mut s = 0.0;
        for _ in &det.nodes {
            for &x in &coords {
                s += (-x * x / (w * w)).exp();
            }
        }
        s
    });
    let t_sc2 = best(10, || {
        let mut s = 0.0;
        for node in &det.nodes {
            for &x in &coords {
                let (a, b) = (0.5 * k * x * x * inv_r - k * x * node.u).sin_cos();
                let (c, d) = (0.5 * k * x * x * inv_r - k * x * node.v).sin_cos();
                s += a + b + c + d;
            }
        }
        s
    });
    let a = Array2::<f64>::from_elem((n, kn), 0.5);
    let b = Array2::<f64>::from_elem((kn, 3 * n), 0.25);
    let t_mm = best(10, || a.dot(&b) + a.dot(&b));
    println!(
        "  {} exp calls {t_exp:.3}; {} sin_cos calls {t_sc2:.3}; two ({n}×{kn})·({kn}×{}) products {t_mm:.3} ({:.1} GFLOP/s)",
        n * kn,
        2 * n * kn,
        3 * n,
        4.0 * (n * kn * 3 * n) as f64 / (t_mm * 1e-3) / 1e9
    );

    let r = Renderer::checked(&optics, &sc, TemplateSpec::default()).unwrap();
    let xs: Vec<f64> = (0..128).map(|i| -6.0 + 12.0 * i as f64 / 127.0).collect();
    let _ = render_xy(&r, &xs, &xs, 0.0, 1);
    let t_r = best(20, || render_xy(&r, &xs, &xs, 0.0, 1));
    let t_g = best(20, || r.render_grid_ideal(&xs, &xs, 0.0));
    let t_gref = best(20, || r.render_grid_reference(&xs, &xs, 0.0));
    let g = r.template.planes_for(0.0)[0].0.clone();
    let ((u0, u1), _) = g.extent();
    let mut pairs = 0usize;
    for s in &r.scatterers {
        let cnt = |p: f64| xs.iter().filter(|&&x| x >= p + u0 && x <= p + u1).count();
        pairs += cnt(s.pos[0]) * cnt(s.pos[1]);
    }
    let t_eval = best(20, || {
        let mut acc = 0.0;
        for i in 0..pairs {
            let f = (i % 977) as f64 / 977.0;
            acc += g.eval(-1.0 + 2.0 * f, 0.3 - 0.5 * f)[0];
        }
        acc
    });
    println!(
        "render 128×128: render_xy {t_r:.3} ms, render_grid_ideal {t_g:.3} ms (reference, serial: {t_gref:.3} ms); {} scatterers, {pairs} scatterer-pixel pairs inside the support (reference: {:.1} ns each); {pairs} bare Grid2::eval {t_eval:.3} ms",
        r.scatterers.len(),
        t_gref * 1e6 / pairs as f64
    );
}
