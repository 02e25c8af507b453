//! Physics core against independent truth: closed forms, symmetries, limits (issue 2).

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
            let w = if i == 0 || i == n { 1.0 } else if i % 2 == 1 { 4.0 } else { 2.0 };
            s += w * (t * t - x * x).exp();
        }
        let num = s * h / 3.0;
        assert!((dawson(x) - num).abs() < 1e-12 * num.abs().max(1e-3), "x={x}: {} vs {num}", dawson(x));
    }
    // maximum of Dawson's function: F(0.9241388730) = 0.5410442246
    assert!((dawson(0.924_138_873) - 0.541_044_224_6).abs() < 1e-10);
}

/// Paraxial, full-collection limit: for a wide beam the far-field cone 2/(k w0) lies deep inside
/// the detection cone and θ ≈ sinθ, so the numerical response must approach the Gittes–Schmidt
/// closed form along y = 0 at z = 0, with an error shrinking like the paraxial parameter
/// (2/(k w0))².
fn paraxial_error(w0_nm: f64) -> f64 {
    let optics = Optics { w0_nm, na: 1.2, n_theta: 96, n_phi: 32, ..Optics::default() };
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
    assert!(e3 / e8 > 4.0 && e3 / e8 < 10.0, "errors {e3:.2e} (3 µm), {e8:.2e} (8 µm)");
}

#[test]
fn symmetries_of_sx_and_sy() {
    let optics = Optics::default();
    for model in [ideal(), DetectorModel { polarization: true, misalignment: None }] {
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
