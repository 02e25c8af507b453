//! With `Optics { beam: Beam::Vector, .. }` every scatterer is
//! rendered in the aplanatic vector focus, and the scene picks the Mie tier for beads outside
//! the point dipole's domain (unless it pins a tier by naming `mie` / `finite_size`).

use bfpscope::instrument::sim::scene::*;
use bfpscope::instrument::sim::*;
use bfpscope::optics::mie::Complex64;
use bfpscope::optics::mie_beam::{Amplitudes, Apodization, MieBeam, MieBeamSpec, Waist};
use bfpscope::optics::params::{Beam, Optics};
use bfpscope::optics::template::TemplateSpec;

fn bead(x: f64, y: f64, d: f64) -> Bead {
    Bead {
        pos: [x, y, 0.0],
        d_nm: d,
        n: 1.572,
    }
}

fn vector() -> Optics {
    Optics {
        beam: Beam::Vector,
        ..Optics::default()
    }
}

fn direct(d: f64, amplitudes: Amplitudes) -> MieBeam {
    MieBeam::new(
        &vector(),
        d,
        Complex64::new(1.572, 0.0),
        MieBeamSpec {
            amplitudes,
            waist: Waist::Filling(f64::INFINITY),
            apodization: Apodization::Aplanatic,
            ..MieBeamSpec::default()
        },
    )
    .unwrap()
}

/// A 110 nm bead in a scene with no effects, vector beam: the render equals the direct
/// vector-dipole response (validated against the independent model in tests/vector_beam.rs)
/// at the pixels, not the paraxial one; the Sy/Sx slope ratio is the real focus's 1.65.
#[test]
fn vector_scene_renders_point_dipoles_in_the_aplanatic_focus() {
    let mut s = Scene::default();
    s.add_bead(bead(0.0, 0.0, 110.0)).unwrap();
    let r = Renderer::checked(&vector(), &s, TemplateSpec::default()).unwrap();
    assert!(r.notes.is_empty(), "{:?}", r.notes);
    let st = r.stages();
    let mie = st
        .iter()
        .find(|s| s.name == "vector_beam")
        .expect("vector beam stage");
    assert!(
        mie.detail.contains("aplanatic vector beam"),
        "{}",
        mie.detail
    );
    let dip = direct(110.0, Amplitudes::Dipole);
    let mut rng = rand::rng();
    let peak = dip.response(0.27, 0.0, 0.0).unwrap()[0];
    for p in [[0.1, 0.0], [0.27, 0.05], [-0.2, 0.3], [0.45, -0.4]] {
        let v = r.render_point([p[0], p[1], 0.0], 1, &mut rng).0;
        // the renderer's image convention (tests/sim.rs): pixel p shows response(p − bead)
        let d = dip.response(p[0], p[1], 0.0).unwrap();
        for c in 0..2 {
            assert!(
                (v[c] - d[c]).abs() < 1e-3 * peak,
                "{p:?} ch {c}: {} vs {}",
                v[c],
                d[c]
            );
        }
    }
    let h = 0.005;
    let slope = |c: usize, e: [f64; 2]| {
        let a = r
            .render_point([e[0] * h, e[1] * h, 0.0], 1, &mut rand::rng())
            .0[c];
        let b = r
            .render_point([-e[0] * h, -e[1] * h, 0.0], 1, &mut rand::rng())
            .0[c];
        (a - b) / (2.0 * h)
    };
    let ratio = slope(1, [0.0, 1.0]) / slope(0, [1.0, 0.0]);
    assert!((ratio - 1.653).abs() < 0.01, "Sy/Sx slope ratio {ratio}");
}

/// A 500 nm bead in a scene without named effects, vector beam: rendered by the Lorenz–Mie tier
/// automatically (the note says so and names the measured error), equal to the direct Mie
/// response; pinning `finite_size` keeps the user's tier and drops the note.
#[test]
fn the_scene_picks_mie_for_a_500_nm_bead_and_the_user_can_pin_a_tier() {
    let mut s = Scene::default();
    s.add_bead(bead(0.0, 0.0, 500.0)).unwrap();
    s.add_bead(bead(1.0, 0.0, 110.0)).unwrap();
    let r = Renderer::checked(&vector(), &s, TemplateSpec::default()).unwrap();
    assert_eq!(r.notes.len(), 1, "{:?}", r.notes);
    assert!(
        r.notes[0].contains("d = 500 nm") && r.notes[0].contains("Lorenz–Mie tier"),
        "{}",
        r.notes[0]
    );
    let mie = r
        .stages()
        .into_iter()
        .find(|s| s.name == "vector_beam")
        .unwrap();
    assert!(
        mie.detail.contains("1 picked by the scene"),
        "{}",
        mie.detail
    );
    let m = direct(500.0, Amplitudes::Mie);
    let dip = direct(110.0, Amplitudes::Dipole);
    let peak = m.response(0.3, 0.0, 0.0).unwrap()[0].abs();
    for p in [[-0.2, 0.1], [0.15, -0.25]] {
        let v = r.render_point([p[0], p[1], 0.0], 1, &mut rand::rng()).0;
        let a = m.response(p[0], p[1], 0.0).unwrap();
        let b = dip.response(p[0] - 1.0, p[1], 0.0).unwrap();
        for c in 0..2 {
            assert!(
                (v[c] - a[c] - b[c]).abs() < 1e-3 * peak,
                "{p:?} ch {c}: {} vs {} + {}",
                v[c],
                a[c],
                b[c]
            );
        }
    }
    s.effects.enable("finite_size").unwrap();
    let pinned = Renderer::checked(&vector(), &s, TemplateSpec::default()).unwrap();
    assert!(pinned.notes.is_empty(), "{:?}", pinned.notes);
    let mie = pinned
        .stages()
        .into_iter()
        .find(|s| s.name == "vector_beam")
        .unwrap();
    assert!(
        mie.detail.starts_with("aplanatic vector beam"),
        "{}",
        mie.detail
    );
    assert!(mie.detail.contains("0 beads"), "{}", mie.detail);
}

/// The default instrument is the real one: `Optics::default()` is the
/// uniformly filled NA 1.2 aplanatic vector beam; a scene without effects builds the
/// superposition and the vector-beam stage only, each effect adds its own stage after them, and
/// `cross_terms` (modelled with the paraxial Gaussian only) is refused with a message that
/// says how to get it, rather than rendered in the wrong beam.
#[test]
fn default_optics_are_the_vector_beam_and_each_effect_adds_its_own_stage() {
    let o = Optics::default();
    assert_eq!(o.beam, Beam::Vector);
    assert!(o.pupil_filling.is_infinite() && o.na == 1.2 && o.wavelength_nm == 1064.0);
    let mut s = Scene::default();
    s.add_bead(bead(0.0, 0.0, 110.0)).unwrap();
    let r = Renderer::checked(&o, &s, TemplateSpec::default()).unwrap();
    assert_eq!(r.stage_names(), vec!["superposition", "vector_beam"]);
    for name in EFFECT_NAMES.iter() {
        let mut e = s.clone();
        e.effects.enable(name).unwrap();
        if *name == "cross_terms" {
            let err = Renderer::checked(&o, &e, TemplateSpec::default())
                .err()
                .expect("cross_terms refused in the vector beam")
                .to_string();
            assert!(
                err.contains("cross_terms") && err.contains("beam: \"paraxial\""),
                "{err}"
            );
            continue;
        }
        let names = Renderer::checked(&o, &e, TemplateSpec::default())
            .unwrap()
            .stage_names();
        // `mie` and `finite_size` pin a tier: the stage is then the named effect's
        let expected: Vec<String> = match *name {
            "mie" => vec!["superposition".into(), "mie".into()],
            "finite_size" => vec![
                "superposition".into(),
                "finite_size".into(),
                "vector_beam".into(),
            ],
            _ => vec![
                "superposition".into(),
                name.to_string(),
                "vector_beam".into(),
            ],
        };
        let mut got = names.clone();
        let mut want = expected.clone();
        got.sort();
        want.sort();
        assert_eq!(got, want, "effect {name}: {names:?}");
    }
}
