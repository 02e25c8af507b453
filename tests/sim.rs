//! The simulated instrument: pipeline built from the scene's effects only, additivity,
//! reproducible randomness, virtual clock.

use bfpscope::instrument::sim::scene::*;
use bfpscope::instrument::sim::*;
use bfpscope::optics::params::{Beam, Optics};
use bfpscope::optics::template::TemplateSpec;

/// The paper's paraxial beam: these tests exercise the render pipeline stage by stage with the
/// Rayleigh template (the default vector beam has its own tests: tests/vector_scene.rs).
fn paraxial() -> Optics {
    Optics {
        beam: Beam::Paraxial,
        ..Optics::default()
    }
}

fn bead(x: f64, y: f64, d: f64) -> Bead {
    Bead {
        pos: [x, y, 0.0],
        d_nm: d,
        n: 1.572,
    }
}

fn axis(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| lo + (hi - lo) * i as f64 / (n - 1) as f64)
        .collect()
}

fn renderer(scene: &Scene) -> Renderer {
    Renderer::checked(&paraxial(), scene, TemplateSpec::default()).unwrap()
}

#[test]
fn ideal_scene_builds_superposition_alone_and_each_effect_adds_its_own_stage() {
    let mut s = Scene::default();
    s.add_bead(bead(0.0, 0.0, 110.0)).unwrap();
    assert_eq!(renderer(&s).stage_names(), vec!["superposition"]);
    for name in EFFECT_NAMES.iter() {
        let mut e = s.clone();
        e.effects.enable(name).unwrap();
        assert_eq!(
            renderer(&e).stage_names(),
            vec!["superposition".to_string(), name.to_string()],
            "effect {name}"
        );
    }
    let mut all = s.clone();
    for name in EFFECT_NAMES.iter() {
        all.effects.enable(name).unwrap();
    }
    assert_eq!(renderer(&all).stage_names().len(), EFFECT_NAMES.len() + 1);
    let err = s.effects.clone().enable("fog").unwrap_err().to_string();
    assert!(
        err.contains("fog") && err.contains("detector_noise"),
        "{err}"
    );
}

#[test]
fn images_are_sums_of_single_bead_images() {
    let xs = axis(-1.5, 1.5, 41);
    let ys = axis(-1.2, 1.2, 33);
    let mut a = Scene::default();
    a.add_bead(bead(-0.2, 0.1, 110.0)).unwrap();
    let mut b = Scene::default();
    b.add_bead(bead(0.25, -0.15, 170.0)).unwrap();
    let mut ab = a.clone();
    ab.add_bead(bead(0.25, -0.15, 170.0)).unwrap();
    let (ia, ib, iab) = (
        render_xy(&renderer(&a), &xs, &ys, 0.0, 1),
        render_xy(&renderer(&b), &xs, &ys, 0.0, 1),
        render_xy(&renderer(&ab), &xs, &ys, 0.0, 1),
    );
    let scale = iab.sx.data.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    for ((p, q), r) in ia
        .sx
        .data
        .iter()
        .zip(ib.sx.data.iter())
        .zip(iab.sx.data.iter())
    {
        assert!((p + q - r).abs() < 1e-12 * scale);
    }
}

#[test]
fn grid_renderer_equals_point_renderer_and_bead_is_not_mirrored() {
    let mut s = Scene::default();
    s.add_bead(bead(0.3, -0.2, 110.0)).unwrap();
    let r = renderer(&s);
    let xs = axis(-0.5, 1.1, 33);
    let ys = axis(-1.0, 0.6, 33);
    let img = render_xy(&r, &xs, &ys, 0.0, 1);
    let mut rng = rand::rng();
    for &(iy, ix) in &[(16usize, 16usize), (3, 29), (20, 10)] {
        let (v, _) = r.render_point([xs[ix], ys[iy], 0.0], 1, &mut rng);
        assert!((v[0] - img.sx.data[[iy, ix]]).abs() < 1e-15);
    }
    // Sx crosses zero at the bead with a positive slope: ∂Sx/∂x > 0 at x = 0.3
    let iy = ys.iter().position(|&y| (y + 0.2).abs() < 1e-9).unwrap();
    let ix = xs.iter().position(|&x| (x - 0.3).abs() < 1e-9).unwrap();
    assert!(img.sx.data[[iy, ix]].abs() < 1e-12);
    assert!(img.sx.data[[iy, ix + 1]] > 0.0 && img.sx.data[[iy, ix - 1]] < 0.0);
}

#[test]
fn random_effects_are_seeded_and_reproducible() {
    let mut s = Scene {
        seed: 7,
        ..Default::default()
    };
    s.add_bead(bead(0.0, 0.0, 110.0)).unwrap();
    s.effects.enable("detector_noise").unwrap();
    s.effects.enable("pointing_noise").unwrap();
    let xs = axis(-0.5, 0.5, 9);
    let a = render_xy(&renderer(&s), &xs, &xs, 0.0, 100);
    let b = render_xy(&renderer(&s), &xs, &xs, 0.0, 100);
    assert_eq!(a.sx.data, b.sx.data);
    s.seed = 8;
    let c = render_xy(&renderer(&s), &xs, &xs, 0.0, 100);
    assert_ne!(a.sx.data, c.sx.data);
}

#[test]
fn detector_noise_shrinks_as_one_over_root_n() {
    let mut s = Scene {
        seed: 1,
        ..Default::default()
    };
    s.effects.enable("detector_noise").unwrap();
    let xs = axis(-1.0, 1.0, 40);
    let std = |n| {
        let img = render_xy(&renderer(&s), &xs, &xs, 0.0, n);
        let v: Vec<f64> = img.sx.data.iter().copied().collect();
        let m = v.iter().sum::<f64>() / v.len() as f64;
        (v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (v.len() - 1) as f64).sqrt()
    };
    let (s1, s100) = (std(1), std(100));
    assert!((s1 / PAPER_DETECTOR_SIGMA_SAMPLE - 1.0).abs() < 0.1, "{s1}");
    assert!((s1 / s100 - 10.0).abs() < 1.0, "{s1} {s100}");
}

#[test]
fn misalignment_gain_scales_sy_exactly_and_offset_breaks_antisymmetry() {
    // The default misalignment (gain_y 0.8, offset 0.15, 2°) was chosen to look like the paper's
    // ~30 % weaker Sy, so asserting that ratio would test the tuning. What the model must do:
    // (1) a gain alone scales Sy by exactly that gain and leaves Sx alone; (2) a rotation alone
    // keeps a round bead's peak |Sy| = peak |Sx| (the response is symmetric under rotation);
    // (3) an offset breaks the antisymmetry Sy(x, −y) = −Sy(x, y).
    use bfpscope::optics::rayleigh::Misalignment;
    let xs = axis(-1.0, 1.0, 81);
    let amax = |a: &ndarray::Array2<f64>| a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    let with = |m: Option<Misalignment>| {
        let mut s = Scene::default();
        s.add_bead(bead(0.0, 0.0, 110.0)).unwrap();
        s.effects.misalignment = m;
        render_xy(&renderer(&s), &xs, &xs, 0.0, 1)
    };
    let ideal = with(None);
    assert!((amax(&ideal.sy.data) / amax(&ideal.sx.data) - 1.0).abs() < 1e-6);
    let only = |offset_y: f64, rotation_deg: f64, gain_y: f64| Misalignment {
        offset_x: 0.0,
        offset_y,
        rotation_deg,
        gain_y,
    };
    // (to rounding: the misaligned path sums the detection nodes in another order)
    let gain = with(Some(only(0.0, 0.0, 0.37)));
    for (g, i) in gain.sy.data.iter().zip(ideal.sy.data.iter()) {
        assert!(
            (g - 0.37 * i).abs() <= 1e-10 * amax(&ideal.sy.data),
            "{g} vs {i}"
        );
    }
    for (g, i) in gain.sx.data.iter().zip(ideal.sx.data.iter()) {
        assert!(
            (g - i).abs() <= 1e-10 * amax(&ideal.sx.data),
            "Sx {g} vs {i}, rel {}",
            (g - i) / amax(&ideal.sx.data)
        );
    }
    let rot = with(Some(only(0.0, 10.0, 1.0)));
    let r = amax(&rot.sy.data) / amax(&rot.sx.data);
    assert!((r - 1.0).abs() < 1e-3, "rotation alone: Sy/Sx peak {r}");
    let mis = with(Some(Misalignment::default()));
    let n = xs.len();
    let asym: f64 = (0..n)
        .map(|i| (mis.sy.data[[n - 1 - 20, i]] + mis.sy.data[[20, i]]).abs())
        .sum::<f64>();
    assert!(asym > 1e-3 * amax(&mis.sy.data), "{asym}");
}

#[test]
fn filament_along_y_is_invisible_in_sy_and_shows_in_sx() {
    let mut s = Scene::default();
    s.add_filament(Filament {
        points: vec![[0.0, -6.0], [0.0, 6.0]],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm: 50.0 },
        n: 1.414,
        spacing_nm: 50.0,
    })
    .unwrap();
    let xs = axis(-1.0, 1.0, 41);
    let ys = axis(-1.0, 1.0, 21);
    let img = render_xy(&renderer(&s), &xs, &ys, 0.0, 1);
    let amax = |a: &ndarray::Array2<f64>| a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(amax(&img.sx.data) > 0.0);
    assert!(
        amax(&img.sy.data) < 1e-3 * amax(&img.sx.data),
        "Sy {}",
        amax(&img.sy.data)
    );
}

#[test]
fn sim_instrument_refuses_moves_beyond_travel_and_counts_virtual_time() {
    let mut s = Scene::default();
    s.add_bead(bead(0.0, 0.0, 110.0)).unwrap();
    let core = SimCore::new(&paraxial(), &s, SimConfig::default()).unwrap();
    let mut inst = core.instrument(0.01);
    inst.move_settle([0.05, 0.0, 0.0]).unwrap();
    let r = inst.qpd.read(10_000).unwrap();
    assert!(r.sx > 0.0);
    let t = inst.clock.now();
    assert!((t - (0.002 + 0.01 + 0.1)).abs() < 1e-9, "{t}");
    let e = inst
        .stage
        .move_to([0.0, 0.0, 40.0])
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("out of limits") && e.contains("sim stage"),
        "{e}"
    );
    assert_eq!(inst.stage.position().unwrap(), [0.05, 0.0, 0.0]);
}

#[test]
fn zero_length_and_one_bead_filaments_are_finite() {
    let mut s = Scene::default();
    s.add_filament(Filament {
        points: vec![[0.0, 0.0]],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm: 50.0 },
        n: 1.414,
        spacing_nm: 50.0,
    })
    .unwrap();
    s.add_filament(Filament {
        points: vec![[0.5, 0.0], [0.5, 0.05]],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm: 50.0 },
        n: 1.414,
        spacing_nm: 50.0,
    })
    .unwrap();
    assert_eq!(s.scatterers(1.333).len(), 1);
    let xs = axis(-1.0, 1.0, 11);
    let img = render_xy(&renderer(&s), &xs, &xs, 0.0, 1);
    assert!(img.sx.data.iter().all(|v| v.is_finite()));
    let e = Scene::default()
        .add_filament(Filament {
            points: vec![],
            z: 0.0,
            profile: DiameterProfile::Constant { d_nm: 50.0 },
            n: 1.414,
            spacing_nm: 50.0,
        })
        .unwrap_err();
    assert_eq!(
        e.to_string(),
        "add_filament: points is empty; give at least one [x, y] vertex"
    );
}

/// The `mie` effect: exactly its own stage; beads become Mie spheres (one template per distinct
/// (d, n)); filaments and aggregates become point dipoles in the same angular-spectrum beam (one
/// shared dipole template), so no scatterer is left in the paraxial Rayleigh beam.
#[test]
fn mie_effect_builds_its_own_stage_and_renders_beads_as_mie_and_the_rest_in_the_same_beam() {
    let mut s = Scene::default();
    s.add_bead(bead(0.0, 0.0, 500.0)).unwrap();
    s.add_bead(bead(2.0, 0.0, 500.0)).unwrap();
    s.add_bead(bead(-2.0, 1.0, 110.0)).unwrap();
    s.add_filament(Filament {
        points: vec![[0.0, -3.0], [0.0, -2.0]],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm: 50.0 },
        n: 1.414,
        spacing_nm: 50.0,
    })
    .unwrap();
    s.add_aggregates(Aggregates {
        count: 3,
        d_nm: [40.0, 60.0],
        n: 1.5,
        region: [[3.0, 4.0], [3.0, 4.0]],
        z: 0.0,
        seed: 2,
    })
    .unwrap();
    s.effects.enable("mie").unwrap();
    assert_eq!(s.effects.names(), vec!["mie"]);
    let r = renderer(&s);
    assert_eq!(r.stage_names(), vec!["superposition", "mie"]);
    assert_eq!(
        r.mie.len(),
        3,
        "two distinct (d, n): 500 and 110 nm, and the dipole limit"
    );
    let dip = |m: &Option<usize>| *m == Some(2);
    assert_eq!(
        r.mie_of.iter().filter(|m| matches!(m, Some(0 | 1))).count(),
        3
    );
    // the filament's and the aggregates' scatterers are dipoles in the Mie tier's beam
    assert!(r.scatterers.len() > 3 + 3 + 10);
    for (sc, m) in r.scatterers.iter().zip(&r.mie_of) {
        assert_eq!(!dip(m), sc.object < 3, "object {}", sc.object);
        assert!(m.is_some());
    }
    // with finite_size too, Mie beads are not decomposed into dipoles
    let mut f = s.clone();
    f.effects.enable("finite_size").unwrap();
    let rf = renderer(&f);
    assert_eq!(
        rf.stage_names(),
        vec!["superposition", "finite_size", "mie"]
    );
    assert_eq!(
        rf.mie_of
            .iter()
            .filter(|m| matches!(m, Some(0 | 1)))
            .count(),
        3
    );
    // min_d_nm makes small beads dipoles (in the same beam)
    let mut g = s.clone();
    g.effects.mie = Some(MieEffect {
        min_d_nm: 200.0,
        scattered_intensity: false,
    });
    let rg = renderer(&g);
    assert_eq!(rg.mie.len(), 2, "the 500 nm sphere and the dipole limit");
    assert_eq!(rg.mie_of.iter().filter(|m| **m == Some(0)).count(), 2);
}

/// In a `mie` scene a bead below min_d_nm is a point dipole in the Mie tier's beam: its image is
/// the Mie sphere's up to the sphere's own size correction (+0.4 % in the maximum sensitivity at
/// 110 nm, docs/paper-figures.md), not the paraxial Rayleigh render, whose peak at the paper's
/// optics is about 1.2× larger (a different beam). Before session 3 such beads stayed paraxial
/// Rayleigh and a scene mixed two instruments.
#[test]
fn mie_scene_keeps_small_beads_in_the_same_beam() {
    let mut s = Scene::default();
    s.add_bead(bead(0.0, 0.0, 110.0)).unwrap();
    let ray = s.clone();
    s.effects.enable("mie").unwrap();
    let mut dip = s.clone();
    dip.effects.mie = Some(MieEffect {
        min_d_nm: 200.0,
        scattered_intensity: false,
    });
    let xs = axis(-1.0, 1.0, 41);
    let peak = |sc: &Scene| {
        let img = render_xy(&renderer(sc), &xs, &xs, 0.0, 1);
        img.sx.data.iter().fold(0.0f64, |m, v| m.max(v.abs()))
    };
    let (pm, pd, pr) = (peak(&s), peak(&dip), peak(&ray));
    eprintln!(
        "Sx peak: Mie sphere {pm:.5e}, dipole in the Mie beam {pd:.5e}, paraxial Rayleigh {pr:.5e}"
    );
    // measured: Mie/dipole 1.0055, Rayleigh/dipole 1.243
    assert!((pm / pd - 1.0).abs() < 0.01, "{}", pm / pd);
    assert!(pr / pd > 1.1, "{}", pr / pd);
}

/// A small bead rendered by the `mie` stage equals the Rayleigh render (with the vector-dipole
/// `polarization` effect, as the Mie tier is vectorial) in a wide, weakly focused beam, where
/// the paraxial Gaussian of the Rayleigh tier and the angular-spectrum beam of the Mie tier are
/// the same beam (to the paraxial correction ∝ 1/(k w0)², docs/physics.md §9).
#[test]
fn mie_render_of_a_small_bead_agrees_with_the_rayleigh_render() {
    let o = Optics {
        w0_nm: 1000.0,
        na: 1.0,
        ..paraxial()
    };
    let mut s = Scene::default();
    s.add_bead(bead(0.1, -0.05, 30.0)).unwrap();
    let mut ray = s.clone();
    ray.effects.enable("polarization").unwrap();
    s.effects.enable("mie").unwrap();
    let rm = Renderer::checked(&o, &s, TemplateSpec::default()).unwrap();
    let rr = Renderer::checked(&o, &ray, TemplateSpec::default()).unwrap();
    let xs = axis(-2.0, 2.0, 41);
    let (im, ir) = (
        render_xy(&rm, &xs, &xs, 0.0, 1),
        render_xy(&rr, &xs, &xs, 0.0, 1),
    );
    let amax = |a: &ndarray::Array2<f64>| a.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    // all channels relative to the Sx peak (the Rayleigh tier's Sz vanishes in the focal plane;
    // the Mie sphere's is its extinction, −C_ext I/P, 3.5e-4 of the Sx peak here)
    let peak = amax(&ir.sx.data);
    let mut worst = [0.0; 3];
    for (c, (a, b)) in [(&im.sx, &ir.sx), (&im.sy, &ir.sy), (&im.sz, &ir.sz)]
        .into_iter()
        .enumerate()
    {
        assert!(amax(&a.data) > 0.0);
        worst[c] = a
            .data
            .iter()
            .zip(b.data.iter())
            .fold(0.0f64, |m, (p, q)| m.max((p - q).abs()))
            / peak;
    }
    // measured 2.4e-2 (Sx), 2.3e-2 (Sy), 3.5e-4 (Sz): the paraxial correction at k·w0 = 7.9
    eprintln!("worst |Mie − Rayleigh| / peak Sx: {worst:?}");
    assert!(worst.iter().all(|&w| w < 0.03), "{worst:?}");
    assert!(worst[2] < 1e-3, "{worst:?}");
    // the Mie stage's time is recorded
    assert!(rm.stages()[1].seconds > 0.0);
}

/// A 500 nm bead renders finitely with the Mie stage, the image equals the direct focused-beam
/// Mie response at its pixels, and its slope at the bead is below the point-dipole Rayleigh
/// value (the finite size, paper Fig. 3c).
#[test]
fn mie_render_of_a_500_nm_bead_is_finite_and_matches_the_direct_response() {
    use bfpscope::optics::mie::Complex64;
    use bfpscope::optics::mie_beam::{MieBeam, MieBeamSpec};
    let o = paraxial();
    let mut s = Scene::default();
    s.add_bead(bead(0.2, 0.1, 500.0)).unwrap();
    let ray = renderer(&s);
    s.effects.enable("mie").unwrap();
    let r = renderer(&s);
    let xs = axis(-1.0, 1.4, 25);
    let img = render_xy(&r, &xs, &xs, 0.0, 1);
    for ch in [&img.sx, &img.sy, &img.sz] {
        assert!(ch.data.iter().all(|v| v.is_finite()));
    }
    let direct = MieBeam::new(
        &o,
        500.0,
        Complex64::new(1.572, 0.0),
        MieBeamSpec::default(),
    )
    .unwrap();
    let peak = img.sx.data.iter().fold(0.0f64, |m, v| m.max(v.abs()));
    assert!(peak > 0.0);
    for &(ix, iy) in &[(12usize, 11usize), (15, 14), (5, 20), (20, 3)] {
        let d = direct.response(xs[ix] - 0.2, xs[iy] - 0.1, 0.0).unwrap();
        let v = [
            img.sx.data[[iy, ix]],
            img.sy.data[[iy, ix]],
            img.sz.data[[iy, ix]],
        ];
        for c in 0..3 {
            assert!(
                (v[c] - d[c]).abs() < 2e-4 * peak,
                "pixel ({ix}, {iy}) ch {c}: {} vs {}",
                v[c],
                d[c]
            );
        }
    }
    // slope at the bead along x vs the Rayleigh point dipole
    let mut rng = rand::rng();
    let h = 0.01;
    let slope = |rr: &Renderer, rng: &mut rand::rngs::ThreadRng| {
        (rr.render_point([0.2 + h, 0.1, 0.0], 1, rng).0[0]
            - rr.render_point([0.2 - h, 0.1, 0.0], 1, rng).0[0])
            / (2.0 * h)
    };
    let (sm, sr) = (slope(&r, &mut rng), slope(&ray, &mut rng));
    assert!(sm > 0.0 && sm < 0.8 * sr, "Mie slope {sm} vs Rayleigh {sr}");
}

/// Without `mie`, the simulator says when a bead is outside the point dipole's domain (> 1 % off
/// the Mie tier in the paper's normalised sensitivity, docs/accuracy.md#model_500): a 500 nm
/// polystyrene bead is +21.9 % off (the model knob's number); 170 nm polystyrene beads are not
/// even checked (0.14 %), a 200 nm one is checked and passes; a silica bead of 170 nm is off by
/// +2.0 %; a `mie` scene has nothing to say.
#[test]
fn simulator_notes_beads_outside_the_point_dipoles_domain() {
    let mut s = Scene::default();
    s.add_bead(bead(0.0, 0.0, 500.0)).unwrap();
    s.add_bead(bead(1.0, 0.0, 500.0)).unwrap();
    s.add_bead(bead(2.0, 0.0, 170.0)).unwrap();
    s.add_bead(bead(3.0, 0.0, 200.0)).unwrap();
    let r = renderer(&s);
    assert_eq!(r.notes.len(), 1, "{:?}", r.notes);
    let pct = |note: &str| -> f64 {
        note.split(" % off")
            .next()
            .and_then(|a| a.rsplit(' ').next())
            .and_then(|v| v.parse().ok())
            .unwrap()
    };
    assert!((20.0..24.0).contains(&pct(&r.notes[0])), "{}", r.notes[0]);
    assert!(r.notes[0].contains("d = 500 nm"), "{}", r.notes[0]);

    let mut silica = Scene::default();
    silica
        .add_bead(Bead {
            pos: [0.0, 0.0, 0.0],
            d_nm: 170.0,
            n: 1.45,
        })
        .unwrap();
    let rs = renderer(&silica);
    assert_eq!(rs.notes.len(), 1, "{:?}", rs.notes);
    assert!((1.5..2.5).contains(&pct(&rs.notes[0])), "{}", rs.notes[0]);

    s.effects.enable("mie").unwrap();
    assert!(renderer(&s).notes.is_empty());
}

/// The parallel, stencil-precomputing render path gives exactly (bit for bit) the
/// image of the kept reference path (serial, scatterer-major, `Grid2::eval` per pixel), for a
/// scene with beads, a filament, an object off the focal plane (z-interpolated planes), pixels
/// at the template's edges and a descending axis; and the image is not trivially zero.
#[test]
fn fast_render_is_bit_identical_to_the_reference_path() {
    let mut s = Scene::default();
    for i in 0..6 {
        let a = i as f64 * 1.1;
        s.add_bead(bead(2.5 * a.cos(), 2.5 * a.sin(), 110.0 + 15.0 * i as f64))
            .unwrap();
    }
    s.add_bead(Bead {
        pos: [0.3, -0.2, 0.137],
        d_nm: 120.0,
        n: 1.572,
    })
    .unwrap();
    s.add_filament(Filament {
        points: vec![[-2.0, -3.0], [2.0, 1.5]],
        z: 0.0,
        profile: DiameterProfile::Constant { d_nm: 60.0 },
        n: 1.414,
        spacing_nm: 50.0,
    })
    .unwrap();
    let r = renderer(&s);
    let xs = axis(-4.0, 4.0, 61);
    let ys = axis(3.5, -3.5, 47); // descending
    for z in [0.0, 0.21] {
        let fast = r.render_grid_ideal(&xs, &ys, z);
        let slow = r.render_grid_reference(&xs, &ys, z);
        for c in 0..3 {
            assert_eq!(fast[c].len(), 61 * 47);
            let peak = slow[c].iter().fold(0.0f64, |m, v| m.max(v.abs()));
            assert!(peak > 1e-4, "channel {c} at z = {z}: peak {peak}");
            for (i, (a, b)) in fast[c].iter().zip(&slow[c]).enumerate() {
                assert_eq!(
                    a.to_bits(),
                    b.to_bits(),
                    "channel {c}, z = {z}, pixel {i}: {a} vs {b}"
                );
            }
        }
    }
}
