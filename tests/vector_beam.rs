//! The vectorial focus of an aplanatic objective (Richards & Wolf 1959; Novotny &
//! Hecht, *Principles of Nano-Optics*, 2nd ed., §3.6, eq. 3.66), validated against an
//! INDEPENDENT vectorial dipole model written here, which shares no code with the renderer:
//!
//! * focal field by the Bessel-integral form of Richards–Wolf (Novotny & Hecht eq. 3.66),
//!   J₀, J₁, J₂ from their integral representation (periodic trapezoid), θ by composite
//!   Simpson — the renderer instead sums discrete plane waves (`mie_beam::AngularSpectrum`);
//! * beam far field −2πi k √cosθ f_w ê(θ, φ) (stationary phase of the angular spectrum,
//!   Mandel & Wolf §3.3, aplanatic factor), power 8π³k² ∫₀^Θ cosθ sinθ dθ = 4π³k² sin²Θ in closed form (uniform
//!   filling);
//! * dipole far field k² α [E − r̂(r̂·E)] e^{−ik r̂·x} (α = a³ (m²−1)/(m²+2), Gaussian units);
//! * S_c = (2/P) ∫_cone s_c Re(E_s·E_b*) dΩ by Simpson in θ and in φ per quadrant.
//!
//! The renderer side is `MieBeam` with dipole amplitudes in the aplanatic, uniformly filled
//! NA 1.2 beam (the real instrument), detected through a condenser of NA 1.2.
//! Numbers: docs/physics.md §10.

use bfpscope::optics::finite_size::sphere_points;
use bfpscope::optics::mie::Complex64 as C64;
use bfpscope::optics::mie_beam::{
    filling_to_spectral_um, Amplitudes, Apodization, MieBeam, MieBeamSpec, Waist,
};
use bfpscope::optics::params::Optics;
use std::f64::consts::PI;

const D_REF: f64 = 110.0;
const N_PS: f64 = 1.572;

fn real_spec(amplitudes: Amplitudes) -> MieBeamSpec {
    MieBeamSpec {
        amplitudes,
        waist: Waist::Filling(f64::INFINITY),
        apodization: Apodization::Aplanatic,
        ..MieBeamSpec::default()
    }
}

// ---------------------------------------------------------------- independent reference model

/// J_n(x) = (1/π) ∫₀^π cos(nτ − x sinτ) dτ; the integrand extends to a smooth 2π-periodic
/// function, so the trapezoid rule on [0, 2π] converges exponentially (128 points: < 1e-14
/// for x ≤ 30).
fn bessel_j(n: i32, x: f64) -> f64 {
    let m = 128;
    let h = 2.0 * PI / m as f64;
    (0..m)
        .map(|i| {
            let t = i as f64 * h;
            (n as f64 * t - x * t.sin()).cos()
        })
        .sum::<f64>()
        / m as f64
}

/// Composite Simpson weights on [a, b] with an even number of intervals `m`.
fn simpson(a: f64, b: f64, m: usize) -> Vec<(f64, f64)> {
    let h = (b - a) / m as f64;
    (0..=m)
        .map(|i| {
            let w = if i == 0 || i == m {
                1.0
            } else if i % 2 == 1 {
                4.0
            } else {
                2.0
            };
            (a + i as f64 * h, w * h / 3.0)
        })
        .collect()
}

struct Reference {
    k: f64,
    alpha: f64,
    theta_max: f64,
    power: f64,
    /// θ nodes for the focal-field integrals: (θ, weight)
    th_focal: Vec<(f64, f64)>,
    /// detection nodes: (u, v, c, dΩ weight, sign x, sign y)
    det: Vec<[f64; 6]>,
}

impl Reference {
    fn new(wavelength_nm: f64, n_medium: f64, na: f64, d_nm: f64, n_p: f64) -> Self {
        let k = 2.0 * PI * n_medium / (wavelength_nm * 1e-3);
        let m2 = (n_p / n_medium).powi(2);
        let alpha = (0.5e-3 * d_nm).powi(3) * (m2 - 1.0) / (m2 + 2.0);
        let theta_max = (na / n_medium).asin();
        let power = 4.0 * PI.powi(3) * k * k * theta_max.sin().powi(2);
        let th_focal = simpson(0.0, theta_max, 200);
        let mut det = Vec::new();
        for (t, wt) in simpson(0.0, theta_max, 80) {
            for q in 0..4 {
                let lo = q as f64 * PI / 2.0;
                for (p, wp) in simpson(lo, lo + PI / 2.0, 48) {
                    let (st, ct) = t.sin_cos();
                    let (sx, sy) = ([1.0, -1.0, -1.0, 1.0][q], [1.0, 1.0, -1.0, -1.0][q]);
                    det.push([st * p.cos(), st * p.sin(), ct, wt * wp * st, sx, sy]);
                }
            }
        }
        Self {
            k,
            alpha,
            theta_max,
            power,
            th_focal,
            det,
        }
    }

    /// Focal field of the aplanatic, uniformly filled, x-polarised objective at (x, y, z) µm
    /// (Novotny & Hecht eq. 3.66 with f_w = 1, in the units of the plane-wave amplitude).
    fn field(&self, x: f64, y: f64, z: f64) -> [C64; 3] {
        let rho = x.hypot(y);
        let phi = y.atan2(x);
        let (mut i0, mut i1, mut i2) = (C64::new(0.0, 0.0), C64::new(0.0, 0.0), C64::new(0.0, 0.0));
        for &(t, w) in &self.th_focal {
            let (s, c) = t.sin_cos();
            let kr = self.k * rho * s;
            let e = C64::from_polar(w * s * c.sqrt(), self.k * z * c);
            i0 += e * (0.5 * (1.0 + c) * bessel_j(0, kr));
            i1 += e * (s * bessel_j(1, kr));
            i2 += e * (0.5 * (1.0 - c) * bessel_j(2, kr));
        }
        let f = 2.0 * PI * self.k * self.k;
        [
            (i0 + i2 * (2.0 * phi).cos()) * f,
            i2 * (2.0 * phi).sin() * f,
            C64::new(0.0, -1.0) * i1 * phi.cos() * f,
        ]
    }

    /// (Sx, Sy) of the dipole at (x, y, z) µm, normalised to the beam power.
    fn signals(&self, x: f64, y: f64, z: f64) -> [f64; 2] {
        let e0 = self.field(x, y, z);
        let mut out = [0.0; 2];
        for n in &self.det {
            let (u, v, c) = (n[0], n[1], n[2]);
            let rdot = e0[0] * u + e0[1] * v + e0[2] * c;
            let ph = C64::from_polar(
                self.k * self.k * self.alpha,
                -self.k * (u * x + v * y + c * z),
            );
            let es = [
                (e0[0] - rdot * u) * ph,
                (e0[1] - rdot * v) * ph,
                (e0[2] - rdot * c) * ph,
            ];
            // beam far field −2πi k √c ê, ê = (1 − u²/(1+c), −uv/(1+c), −u)
            let q = 1.0 / (1.0 + c);
            let eb = [1.0 - u * u * q, -u * v * q, -u];
            let amp = C64::new(0.0, -2.0 * PI * self.k * c.sqrt());
            let proj = (es[0] * eb[0] + es[1] * eb[1] + es[2] * eb[2]) * amp.conj();
            let val = 2.0 * proj.re * n[3] / self.power;
            out[0] += n[4] * val;
            out[1] += n[5] * val;
        }
        out
    }
}

// ---------------------------------------------------------------- extraction (both models)

/// Maximise f on [lo, hi]: 21-point scan then golden section.
fn maximise(f: &dyn Fn(f64) -> f64, lo: f64, hi: f64) -> (f64, f64) {
    let n = 20;
    let h = (hi - lo) / n as f64;
    let best = (0..=n)
        .map(|i| lo + i as f64 * h)
        .max_by(|a, b| f(*a).partial_cmp(&f(*b)).unwrap())
        .unwrap();
    let (mut a, mut b) = ((best - h).max(lo), (best + h).min(hi));
    let g = 0.5 * (5f64.sqrt() - 1.0);
    for _ in 0..40 {
        let c = b - g * (b - a);
        let d = a + g * (b - a);
        if f(c) > f(d) {
            b = d
        } else {
            a = c
        }
    }
    let x = 0.5 * (a + b);
    (f(x), x)
}

/// Root of f on [a, b] (sign change) by bisection.
fn bisect(f: &dyn Fn(f64) -> f64, mut a: f64, mut b: f64) -> f64 {
    let fa = f(a);
    for _ in 0..40 {
        let m = 0.5 * (a + b);
        if (f(m) > 0.0) == (fa > 0.0) {
            a = m
        } else {
            b = m
        }
    }
    0.5 * (a + b)
}

#[derive(Debug)]
struct Figures {
    sens_x: f64,
    sens_y: f64,
    z_best: f64,
    sx_peak: f64,
    x_peak: f64,
    x_zero: f64,
    overshoot: f64,
    focus_lo: f64,
    focus_hi: f64,
}

/// The figures of merit from a signal function (x, y, z) → (Sx, Sy):
/// (∂S/∂x)max over z (central difference, 2 nm), Sx peak value and position along x at the
/// best focus, first zero crossing beyond the peak, overshoot = min Sx beyond it / peak, and
/// the 2 % focus range (z where ∂Sx/∂x ≥ 0.98 of its maximum).
fn figures(s: &dyn Fn(f64, f64, f64) -> [f64; 2]) -> Figures {
    let h = 1e-3;
    let dsx = |z: f64| (s(h, 0.0, z)[0] - s(-h, 0.0, z)[0]) / (2.0 * h);
    let dsy = |z: f64| (s(0.0, h, z)[1] - s(0.0, -h, z)[1]) / (2.0 * h);
    let (sens_x, z_best) = maximise(&dsx, -0.6, 0.6);
    let (sens_y, _) = maximise(&dsy, -0.6, 0.6);
    let sx = |x: f64| s(x, 0.0, z_best)[0];
    let (sx_peak, x_peak) = maximise(&sx, 0.02, 0.8);
    let mut a = x_peak;
    while sx(a + 0.02) > 0.0 && a < 1.4 {
        a += 0.02;
    }
    let x_zero = bisect(&sx, a, a + 0.02);
    let (neg, _) = maximise(&|x| -sx(x), x_zero, 1.45);
    let g = |z: f64| dsx(z) - 0.98 * sens_x;
    let focus_lo = bisect(&g, z_best - 0.4, z_best);
    let focus_hi = bisect(&g, z_best, z_best + 0.4);
    Figures {
        sens_x,
        sens_y,
        z_best,
        sx_peak,
        x_peak,
        x_zero,
        overshoot: -neg / sx_peak,
        focus_lo,
        focus_hi,
    }
}

/// The issue asks for 2 %; the two independent quadratures agree to ~1e-6, so the test holds
/// them to 1e-4 (a beam-model error of any physical size fails it).
const TOL: f64 = 1e-4;

fn rel(a: f64, b: f64) -> f64 {
    (a / b - 1.0).abs()
}

/// The vector beam's acceptance test: a 110 nm PS bead in the real beam agrees with the independent
/// vectorial dipole model within 2 % on every figure of merit.
#[test]
fn vector_beam_matches_independent_dipole_model_for_110_nm_ps() {
    let o = Optics::default();
    let r = Reference::new(o.wavelength_nm, o.n_medium, o.na, D_REF, N_PS);
    let beam = MieBeam::new(
        &o,
        D_REF,
        C64::new(N_PS, 0.0),
        real_spec(Amplitudes::Dipole),
    )
    .unwrap();
    let fr = figures(&|x, y, z| r.signals(x, y, z));
    let fb = figures(&|x, y, z| {
        let v = beam.response(x, y, z).unwrap();
        [v[0], v[1]]
    });
    eprintln!("reference {fr:?}\nrenderer  {fb:?}");
    // the reference must describe the real instrument: x-polarised focus, Sy/Sx > 1
    assert!(fr.sens_y / fr.sens_x > 1.2, "{fr:?}");
    assert!(r.theta_max > 1.0);
    for (name, a, b) in [
        ("dSx/dx max", fb.sens_x, fr.sens_x),
        ("dSy/dy max", fb.sens_y, fr.sens_y),
        ("Sx peak", fb.sx_peak, fr.sx_peak),
        ("Sx peak position", fb.x_peak, fr.x_peak),
        ("first zero of Sx", fb.x_zero, fr.x_zero),
    ] {
        assert!(rel(a, b) < TOL, "{name}: renderer {a} vs reference {b}");
    }
    // overshoot (negative lobe beyond the zero, a fraction of the peak): within 2 % of itself
    assert!(fr.overshoot < -0.05, "{fr:?}");
    assert!(rel(fb.overshoot, fr.overshoot) < TOL, "{fb:?} vs {fr:?}");
    // focus range width and position (TOL of the width)
    let (wr, wb) = (fr.focus_hi - fr.focus_lo, fb.focus_hi - fb.focus_lo);
    assert!(rel(wb, wr) < TOL, "focus range {wb} vs {wr}");
    assert!((fb.z_best - fr.z_best).abs() < TOL * wr, "{fb:?} vs {fr:?}");
    // the real instrument's numbers (docs/physics.md §10), to 0.1 %
    for (a, b) in [
        (fr.sens_x, 0.015272),
        (fr.sens_y, 0.025252),
        (fr.sx_peak, 0.0025813),
        (fr.x_peak, 0.26919),
        (fr.x_zero, 0.62881),
        (fr.overshoot, -0.12647),
        (fr.focus_hi, 0.109874),
    ] {
        assert!(rel(a, b) < 1e-3, "{a} vs documented {b}");
    }
}

/// Pupil filling: f0 = 1 (1/e field radius = aperture radius) maps to the Gaussian
/// spectrum exp(−sin²θ/sin²Θ) at the aperture edge = e^{−1}; f0 = ∞ is uniform.
#[test]
fn pupil_filling_definition() {
    let o = Optics::default();
    let ws = filling_to_spectral_um(&o, 1.0).unwrap();
    let st = o.na / o.n_medium;
    let edge = (-(o.k_per_um() * ws * st).powi(2) / 4.0).exp();
    assert!((edge - (-1.0f64).exp()).abs() < 1e-12);
    assert_eq!(filling_to_spectral_um(&o, f64::INFINITY).unwrap(), 0.0);
    let e = filling_to_spectral_um(&o, -1.0).unwrap_err().to_string();
    assert!(e.contains("pupil_filling") && e.contains("-1"), "{e}");
}

/// Tier consistency in one beam: a 30 nm PS sphere as exact Lorenz–Mie, as a point dipole, and
/// as a finite-size sphere (S6: volume average of point dipoles) agree within 1 % (asserted 0.5 %).
#[test]
fn tiers_agree_for_30_nm_sphere_in_the_vector_beam() {
    let o = Optics::default();
    let d = 30.0;
    let mie = MieBeam::new(&o, d, C64::new(N_PS, 0.0), real_spec(Amplitudes::Mie)).unwrap();
    let dip = MieBeam::new(&o, d, C64::new(N_PS, 0.0), real_spec(Amplitudes::Dipole)).unwrap();
    let pts = sphere_points(d * 1e-3, 3);
    let fin = |x: f64, y: f64, z: f64| {
        let mut s = [0.0; 3];
        for (off, w) in &pts {
            let v = dip.response(x + off[0], y + off[1], z + off[2]).unwrap();
            for c in 0..3 {
                s[c] += w * v[c];
            }
        }
        s
    };
    let (smax, zb) = dip.max_sensitivity_x();
    let (smie, _) = mie.max_sensitivity_x();
    assert!(rel(smie, smax) < 0.005, "{smie} vs {smax}");
    let peak = dip.response(0.3, 0.0, zb).unwrap()[0].abs();
    let mut worst = [0.0f64; 2];
    for (x, y, z) in [
        (0.1, 0.0, zb),
        (0.3, 0.2, 0.1),
        (-0.2, 0.35, -0.2),
        (0.0, 0.25, 0.0),
    ] {
        let a = dip.response(x, y, z).unwrap();
        let b = mie.response(x, y, z).unwrap();
        let f = fin(x, y, z);
        for c in 0..2 {
            assert!(
                (b[c] - a[c]).abs() < 0.005 * peak,
                "mie {c} at {x},{y},{z}: {b:?} vs {a:?}"
            );
            assert!(
                (f[c] - a[c]).abs() < 0.005 * peak,
                "fs {c} at {x},{y},{z}: {f:?} vs {a:?}"
            );
            worst[0] = worst[0].max((b[c] - a[c]).abs() / peak);
            worst[1] = worst[1].max((f[c] - a[c]).abs() / peak);
        }
    }
    // measured: sensitivity 7.3e-5, worst 5.0e-4 (Mie) and 1.7e-3 (finite size, O((ka)²)) of the
    // peak; the issue asks for 1 %, asserted at 0.5 %
    eprintln!(
        "30 nm: sensitivity Mie/dipole − 1 = {:.2e}; worst |Mie − dipole|, |finite − dipole| / peak = {:.2e}, {:.2e}",
        smie / smax - 1.0,
        worst[0],
        worst[1]
    );
}
