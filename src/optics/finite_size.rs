//! Finite-size Rayleigh response (suppl. S6): a large sphere as many small dipoles.
//!
//! Derivation (docs/physics.md): with no multiple scattering, a sphere of polarisability
//! α = r³ CM is the sum of volume elements dV, each of polarisability α dV/V, each driven by the
//! focal field at its own position (amplitude *and* phase) and radiating with its own
//! propagation phase. That is exactly the point response evaluated at the element's position,
//! so the sphere's response is the volume average of the point response:
//!   S_fs(x) = (α/V) ∫_sphere S_unit(x + δ) d³δ.
//! The supplement's "scaled proportionally to the magnitude of the electric field" is contained
//! in S_unit (which carries E_G(x + δ)); scaling by |E| again would double count.
//!
//! The volume integral uses a product Gauss rule: Gauss–Legendre in r (weight r²) and in cosβ,
//! uniform in azimuth; `n_r` is the accuracy knob (n_r × n_r × 2n_r points).

use super::quad::gauss_legendre;
use super::rayleigh::Detection;

/// Default radial order of the sphere rule: the knee in docs/accuracy.md (8e-6 relative error of
/// the 500 nm bead's sensitivity against n_r = 14).
pub const DEFAULT_N_R: usize = 4;

/// Quadrature points (offset µm, weight) over a sphere of diameter `d_um`; weights sum to 1.
pub fn sphere_points(d_um: f64, n_r: usize) -> Vec<([f64; 3], f64)> {
    let n_r = n_r.max(1);
    let r_max = 0.5 * d_um;
    if r_max <= 0.0 {
        return vec![([0.0; 3], 1.0)];
    }
    let (rs, wr) = gauss_legendre(n_r, 0.0, r_max);
    let (mus, wmu) = gauss_legendre(n_r, -1.0, 1.0);
    let n_az = 2 * n_r;
    let v = 4.0 / 3.0 * std::f64::consts::PI * r_max.powi(3);
    let mut pts = Vec::with_capacity(n_r * n_r * n_az);
    for (&r, &w1) in rs.iter().zip(&wr) {
        for (&mu, &w2) in mus.iter().zip(&wmu) {
            let s = (1.0 - mu * mu).max(0.0).sqrt();
            for a in 0..n_az {
                let ph = (a as f64 + 0.5) * 2.0 * std::f64::consts::PI / n_az as f64;
                let w = w1 * r * r * w2 * (2.0 * std::f64::consts::PI / n_az as f64) / v;
                pts.push(([r * s * ph.cos(), r * s * ph.sin(), r * mu], w));
            }
        }
    }
    pts
}

/// Volume-averaged per-unit-α response and its x, y derivatives at displacement (x, y, z) µm.
pub fn response_unit_finite(
    det: &Detection,
    d_nm: f64,
    n_r: usize,
    x: f64,
    y: f64,
    z: f64,
) -> ([f64; 3], [f64; 3], [f64; 3]) {
    let mut s = [0.0; 3];
    let mut dx = [0.0; 3];
    let mut dy = [0.0; 3];
    for (o, w) in sphere_points(d_nm * 1e-3, n_r) {
        let (a, b, c) = det.response_unit(x + o[0], y + o[1], z + o[2]);
        for k in 0..3 {
            s[k] += w * a[k];
            dx[k] += w * b[k];
            dy[k] += w * c[k];
        }
    }
    (s, dx, dy)
}

/// Maximise `f(z)` over the axial displacement z ∈ [−1, 1] µm: a 0.05 µm scan, then golden
/// section (30 steps) on the best bracket. Returns (max, z). Shared by every model's
/// "sensitivity at the best focus" (Rayleigh, finite-size, Mie).
pub fn best_focus(f: impl Fn(f64) -> f64) -> (f64, f64) {
    let (mut best_z, mut best) = (0.0, f(0.0));
    for i in -20..=20 {
        let z = i as f64 * 0.05;
        let v = f(z);
        if v > best {
            best = v;
            best_z = z;
        }
    }
    let (mut a, mut b) = (best_z - 0.05, best_z + 0.05);
    let g = 0.5 * (5f64.sqrt() - 1.0);
    let mut c = b - g * (b - a);
    let mut d = a + g * (b - a);
    let (mut fc, mut fd) = (f(c), f(d));
    for _ in 0..30 {
        if fc > fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = f(c);
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = f(d);
        }
    }
    let z = 0.5 * (a + b);
    (f(z), z)
}

/// Maximum Sx sensitivity ∂Sx/∂x per unit α (µm⁻⁴) at the best focus, and that focus z (µm):
/// the sensitivity at x = y = 0 maximised over the axial displacement (the paper optimises the
/// height before every scan, suppl. S5). `d_nm = None` is the point dipole.
pub fn max_sensitivity_unit(det: &Detection, d_nm: Option<f64>, n_r: usize) -> (f64, f64) {
    let f = |z: f64| match d_nm {
        None => det.response_unit(0.0, 0.0, z).1[0],
        Some(d) => response_unit_finite(det, d, n_r, 0.0, 0.0, z).1[0],
    };
    best_focus(f)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optics::{params::Optics, rayleigh::DetectorModel};

    #[test]
    fn sphere_rule_integrates_volume_moments() {
        let pts = sphere_points(0.4, 6);
        let w: f64 = pts.iter().map(|p| p.1).sum();
        assert!((w - 1.0).abs() < 1e-12);
        // <r²> over a uniform ball of radius R = 3R²/5
        let r2: f64 = pts
            .iter()
            .map(|(o, w)| w * (o[0] * o[0] + o[1] * o[1] + o[2] * o[2]))
            .sum();
        assert!((r2 - 0.6 * 0.04).abs() < 1e-12);
        let z2: f64 = pts.iter().map(|(o, w)| w * o[2] * o[2]).sum();
        assert!((z2 - 0.2 * 0.04).abs() < 1e-12);
    }

    #[test]
    fn small_sphere_reduces_to_point_dipole() {
        let det = Detection::new(&Optics::default(), &DetectorModel::default()).unwrap();
        let p = det.response_unit(0.2, 0.1, 0.05).0;
        let f = response_unit_finite(&det, 10.0, 4, 0.2, 0.1, 0.05).0;
        for c in 0..2 {
            assert!(
                (f[c] / p[c] - 1.0).abs() < 1e-3,
                "{c}: {} vs {}",
                f[c],
                p[c]
            );
        }
    }
}
