//! Physics core against independent truth: closed forms, symmetries, limits.

use bfpscope::optics::params::Optics;
use bfpscope::optics::rayleigh::*;

fn ideal() -> DetectorModel {
    DetectorModel::default()
}

/// Dawson's integral against direct numerical integration of e^{t²} (Simpson, fine grid).
#[test]
fn dawson_matches_quadrature() {
    for &x in &[0.05, 0.19, 0.21, 0.5, 0.9241, 1.5, 3.0, 6.0, -1.2] {
        let n = 20000;
        let h = x / n as f64;
        let mut s = 0.0;
        for i in 0..=n {
            let t = i as f64 * h;
            let w = if i == 0 || i == n {
                1.0
            } else if i % 2 == 1 {
                4.0
            } else {
                2.0
            };
            s += w * (t * t - x * x).exp();
        }
        let num = s * h / 3.0;
        assert!(
            (dawson(x) - num).abs() < 1e-12 * num.abs().max(1e-3),
            "x={x}: {} vs {num}",
            dawson(x)
        );
    }
    // maximum of Dawson's function: F(0.9241388730) = 0.5410442246
    assert!((dawson(0.924_138_873) - 0.541_044_224_6).abs() < 1e-10);
}

/// Paraxial, full-collection limit: for a wide beam the far-field cone 2/(k w0) lies deep inside
/// the detection cone and θ ≈ sinθ, so the numerical response must approach the Gittes–Schmidt
/// closed form along y = 0 at z = 0, with an error shrinking like the paraxial parameter
/// (2/(k w0))².
fn paraxial_error(w0_nm: f64) -> f64 {
    let optics = Optics {
        w0_nm,
        na: 1.2,
        n_theta: 96,
        n_phi: 32,
        ..Optics::default()
    };
    let det = Detection::new(&optics, &ideal()).unwrap();
    let (k, w0) = (optics.k_per_um(), optics.w0_um());
    let peak = gittes_schmidt_sx(k, 1.0, w0, 0.924 * w0).abs();
    let mut worst: f64 = 0.0;
    for &xr in &[0.03, 0.17, 0.33, 0.66, 0.924, 1.33, 2.0, -0.8] {
        let x = xr * w0;
        let (s, _, _) = det.response_unit(x, 0.0, 0.0);
        worst = worst.max((s[0] - gittes_schmidt_sx(k, 1.0, w0, x)).abs() / peak);
        // Sz vanishes at z = 0 (dipole field in quadrature with the beam)
        assert!(s[2].abs() < 1e-9 * peak, "Sz at z=0: {}", s[2]);
    }
    // slope at the origin: (16/√π) k α / w0³
    let (_, dx, _) = det.response_unit(0.0, 0.0, 0.0);
    let slope = 16.0 / std::f64::consts::PI.sqrt() * k / w0.powi(3);
    worst.max((dx[0] / slope - 1.0).abs())
}

#[test]
fn paraxial_limit_matches_gittes_schmidt_closed_form() {
    let e3 = paraxial_error(3000.0);
    let e8 = paraxial_error(8000.0);
    eprintln!("paraxial errors: {e3:.3e} (3 µm) {e8:.3e} (8 µm)");
    assert!(e8 < 6e-4, "w0 = 8 µm: worst relative error {e8:.2e}");
    // (8/3)² ≈ 7.1: the error is the paraxial correction, not quadrature noise
    assert!(
        e3 / e8 > 4.0 && e3 / e8 < 10.0,
        "errors {e3:.2e} (3 µm), {e8:.2e} (8 µm)"
    );
}

#[test]
fn symmetries_of_sx_and_sy() {
    let optics = Optics::default();
    for model in [
        ideal(),
        DetectorModel {
            polarization: true,
            misalignment: None,
        },
    ] {
        let det = Detection::new(&optics, &model).unwrap();
        for &(x, y, z) in &[(0.13, 0.21, 0.0), (0.4, -0.07, 0.3), (-0.25, 0.5, -0.6)] {
            let (a, _, _) = det.response_unit(x, y, z);
            let (b, _, _) = det.response_unit(-x, y, z);
            let (c, _, _) = det.response_unit(x, -y, z);
            let tol = 1e-12 * a[0].abs().max(a[1].abs()).max(1e-30) + 1e-18;
            // Sx odd in x, even in y; Sy the reverse; Sz even in both
            assert!((a[0] + b[0]).abs() < tol && (a[0] - c[0]).abs() < tol);
            assert!((a[1] - b[1]).abs() < tol && (a[1] + c[1]).abs() < tol);
            assert!((a[2] - b[2]).abs() < tol && (a[2] - c[2]).abs() < tol);
        }
    }
}

#[test]
fn zero_contrast_gives_exactly_zero_and_negative_contrast_flips_sign() {
    let o = Optics::default();
    let r = response(&o, &ideal(), [0.2, 0.1, 0.05], 110.0, o.n_medium).unwrap();
    assert_eq!((r.sx, r.sy, r.sz), (0.0, 0.0, 0.0));
    let up = response(&o, &ideal(), [0.2, 0.1, 0.05], 110.0, 1.45).unwrap();
    let down = response(&o, &ideal(), [0.2, 0.1, 0.05], 110.0, 1.25).unwrap();
    assert!(up.sx > 0.0 && down.sx < 0.0, "{up:?} {down:?}");
    let ratio = down.sx / up.sx;
    let expect = clausius_mossotti(1.25, o.n_medium) / clausius_mossotti(1.45, o.n_medium);
    assert!((ratio - expect).abs() < 1e-12);
}

#[test]
fn response_scales_as_d_cubed() {
    let o = Optics::default();
    let a = response(&o, &ideal(), [0.15, 0.0, 0.0], 20.0, 1.572).unwrap();
    let b = response(&o, &ideal(), [0.15, 0.0, 0.0], 40.0, 1.572).unwrap();
    assert!((b.sx / a.sx - 8.0).abs() < 1e-12);
}

#[test]
fn finite_and_continuous_through_focus_axis_and_far_away() {
    let o = Optics::default();
    let det = Detection::new(&o, &ideal()).unwrap();
    let at = |x, y, z| det.response_unit(x, y, z).0;
    let a = at(0.1, 0.05, 0.0);
    for dz in [1e-12, -1e-12, 1e-9] {
        let b = at(0.1, 0.05, dz);
        for c in 0..3 {
            assert!(b[c].is_finite());
            assert!((a[c] - b[c]).abs() < 1e-6 * a[0].abs(), "jump at z={dz}");
        }
    }
    let on_axis = at(0.0, 0.0, 0.5);
    assert!(on_axis[0].abs() < 1e-12 * on_axis[2].abs());
    assert!(on_axis[2].is_finite() && on_axis[2] != 0.0);
    for far in [at(5.0, 0.0, 0.0), at(0.0, 0.0, 50.0), at(1e3, 1e3, 1e3)] {
        assert!(far.iter().all(|v| v.is_finite()), "{far:?}");
    }
    assert!(at(5.0, 0.0, 0.0)[0].abs() < 1e-30);
}

mod templates {
    use bfpscope::optics::grid::Interp;
    use bfpscope::optics::params::Optics;
    use bfpscope::optics::rayleigh::{Detection, DetectorModel};
    use bfpscope::optics::template::*;
    use std::sync::Arc;

    fn det() -> Arc<Detection> {
        Arc::new(
            Detection::new(
                &Optics::default(),
                &DetectorModel {
                    polarization: true,
                    misalignment: None,
                },
            )
            .unwrap(),
        )
    }

    /// The separable matrix-product plane equals direct evaluation at the nodes.
    #[test]
    fn plane_nodes_equal_direct_evaluation() {
        let d = det();
        for z in [0.0, 0.35, -0.8] {
            let g = plane_grid(&d, z, 0.05, Interp::Cubic);
            let peak = d.response_unit(0.23, 0.0, z).0[0].abs();
            for &(i, j) in &[
                (0usize, 0usize),
                (g.nu / 2 + 3, g.nv / 2 - 7),
                (g.nu - 5, g.nv / 2 + 1),
            ] {
                let (x, y) = (g.u0 + i as f64 * g.h, g.v0 + j as f64 * g.h);
                let direct = d.response_unit(x, y, z).0;
                let node = g.data[j * g.nu + i];
                for c in 0..3 {
                    assert!(
                        (direct[c] - node[c]).abs() < 1e-10 * peak,
                        "z={z} ({x},{y}) c={c}: {} vs {}",
                        direct[c],
                        node[c]
                    );
                }
            }
        }
    }

    /// Interpolation error of the default template (h = 20 nm cubic, hz = 50 nm), relative to
    /// the peak |Sx|, at random points: stated in docs/physics.md.
    #[test]
    fn default_template_interpolation_error_is_below_1e_3() {
        let d = det();
        let t = ModelTemplate::new(d.clone(), TemplateSpec::default()).unwrap();
        let peak = (0..100)
            .map(|i| d.response_unit(i as f64 * 0.01, 0.0, 0.0).0[0].abs())
            .fold(0.0, f64::max);
        let mut worst: f64 = 0.0;
        for k in 0..300 {
            let x = -1.0 + 2.0 * (k as f64 * 0.618_033_988_7).fract();
            let y = -1.0 + 2.0 * (k as f64 * 0.414_213_562_3).fract();
            let z = -0.3 + 0.6 * (k as f64 * 0.732_050_807_5).fract();
            let a = t.eval(x, y, z);
            let b = d.response_unit(x, y, z).0;
            for c in 0..3 {
                worst = worst.max((a[c] - b[c]).abs() / peak);
            }
        }
        eprintln!(
            "default template: worst interpolation error {worst:.2e} of peak; {} planes, {} bytes",
            t.n_planes(),
            t.bytes()
        );
        assert!(worst < 1e-3, "{worst}");
        let lin = ModelTemplate::new(
            d.clone(),
            TemplateSpec {
                interp: Interp::Linear,
                ..TemplateSpec::default()
            },
        )
        .unwrap();
        let (x, y, z) = (0.31, -0.17, 0.12);
        let e_lin = (lin.eval(x, y, z)[0] - d.response_unit(x, y, z).0[0]).abs();
        let e_cub = (t.eval(x, y, z)[0] - d.response_unit(x, y, z).0[0]).abs();
        assert!(e_cub < e_lin, "cubic {e_cub:.2e} vs linear {e_lin:.2e}");
    }
}

/// The misaligned-QPD rule (polar coordinates about the QPD cross) with zero offset, zero
/// rotation and unit gain must agree with the ideal rule: two different quadratures of one
/// integral.
#[test]
fn misaligned_rule_with_zero_misalignment_equals_ideal_rule() {
    let o = Optics {
        n_theta: 32,
        n_phi: 16,
        ..Optics::default()
    };
    let ideal = Detection::new(&o, &DetectorModel::default()).unwrap();
    let zero = Misalignment {
        offset_x: 0.0,
        offset_y: 0.0,
        rotation_deg: 0.0,
        gain_y: 1.0,
    };
    let mis = Detection::new(
        &o,
        &DetectorModel {
            polarization: false,
            misalignment: Some(zero),
        },
    )
    .unwrap();
    let peak = ideal.response_unit(0.24, 0.0, 0.0).0[0].abs();
    for &(x, y, z) in &[(0.1, 0.2, 0.0), (0.5, -0.3, 0.4), (-0.7, 0.1, -0.2)] {
        let (a, b) = (ideal.response_unit(x, y, z).0, mis.response_unit(x, y, z).0);
        for c in 0..3 {
            assert!(
                (a[c] - b[c]).abs() < 1e-8 * peak,
                "({x},{y},{z}) c={c}: {} vs {}",
                a[c],
                b[c]
            );
        }
    }
    let bad = Misalignment {
        offset_x: 0.9,
        offset_y: 0.5,
        ..zero
    };
    // |offset| = 1.03 of the cone radius: the cross is outside the beam, refused by name
    let e = match Detection::new(
        &o,
        &DetectorModel {
            polarization: false,
            misalignment: Some(bad),
        },
    ) {
        Ok(_) => panic!("an offset outside the beam must be refused"),
        Err(e) => e.to_string(),
    };
    assert!(
        e.starts_with("misalignment offset (0.9, 0.5) puts the QPD cross outside the beam: |offset| must be < 0.95"),
        "{e}"
    );
}

/// The plane builder with separable phase tables and one Gaussian per node agrees
/// with the kept reference builder (two `sin_cos` and an `exp` per node pair) to 1e-12 of the plane's
/// peak signal, at focus and off focus (curvature and Gouy phase), for the ideal, the
/// polarised and the misaligned detector.
#[test]
fn fast_plane_matches_the_reference_plane() {
    use bfpscope::optics::grid::Interp;
    use bfpscope::optics::template::{plane_grid, plane_grid_reference};
    let o = Optics::default();
    let models = [
        ideal(),
        DetectorModel {
            polarization: true,
            misalignment: None,
        },
        DetectorModel {
            polarization: true,
            misalignment: Some(Misalignment::default()),
        },
    ];
    for m in &models {
        let det = Detection::new(&o, m).unwrap();
        for z in [0.0, 0.35, -1.2] {
            let a = plane_grid(&det, z, 0.02, Interp::Cubic);
            let b = plane_grid_reference(&det, z, 0.02, Interp::Cubic);
            assert_eq!((a.nu, a.nv, a.u0, a.h), (b.nu, b.nv, b.u0, b.h));
            // scale: the plane's largest signal (Sz vanishes at the focus by symmetry)
            let peak = b
                .data
                .iter()
                .fold(0.0f64, |p, v| p.max(v[0].abs()).max(v[1].abs()));
            assert!(peak > 1e-3, "{m:?} z = {z}: peak {peak}");
            for c in 0..3 {
                let err = a
                    .data
                    .iter()
                    .zip(&b.data)
                    .fold(0.0f64, |e, (x, y)| e.max((x[c] - y[c]).abs()));
                assert!(
                    err <= 1e-12 * peak,
                    "{m:?} z = {z} c = {c}: {err:e} of {peak:e}"
                );
            }
        }
    }
}
