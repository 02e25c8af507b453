//! Lorenz–Mie scattering by a homogeneous sphere: coefficients a_n, b_n, efficiencies
//! Q_ext, Q_sca, Q_abs, Q_back, asymmetry parameter g and amplitude functions S_1(θ), S_2(θ).
//!
//! The paper (seed `000_a01c3b91f68df4b7.txt`, Sec. 3.1, Fig. 2 and Fig. 3c) compares its
//! Rayleigh model of the BFP/QPD signal with a full Mie computation; this module is the
//! plane-wave Mie tier underneath that comparison. Pure functions: no I/O, no scripting.
//!
//! # Conventions and units
//!
//! * **Size parameter** `x = 2π a n_medium / λ_vacuum = π d n_medium / λ_vacuum`
//!   (dimensionless; `a` radius, `d` diameter).
//! * **Relative index** `m = n_particle / n_medium` as a [`Complex64`] in the
//!   **Bohren–Huffman convention**: time dependence e^{−iωt}, `m = n + iκ`, with `κ = m.im ≥ 0`
//!   for an absorbing sphere (BH 1983, §2.5 and Ch. 4). Wiscombe (MIEV0) and miepython write the
//!   same physical index as `m_re − i·m_im` with `m_im ≥ 0`, i.e. their `m_im` is our `m.im`;
//!   pass `Complex64::new(m_re, m_im)`. A negative `m.im` (a gain medium, or a conjugated index
//!   from those codes) is rejected with an error that says so.
//! * **Outputs** follow BH Ch. 4 in the same e^{−iωt} convention: a_n, b_n (BH eq. 4.53/4.88),
//!   S_1, S_2 (BH eq. 4.74). Wiscombe's/miepython's complex amplitudes are the complex
//!   conjugates of ours; all efficiencies are identical in both conventions.
//! * **Efficiencies** are dimensionless (cross-section / geometric cross-section π a²);
//!   `g = ⟨cos θ⟩` is dimensionless; S_1, S_2 are dimensionless amplitude functions normalised
//!   as in BH (so that Q_ext = (4/x²) Re S(0), the optical theorem, BH eq. 4.76).
//!
//! # Numerics (see `docs/mie.md`)
//!
//! * D_n(mx) by downward recurrence from Lentz's continued fraction (Lentz 1976; Wiscombe 1980);
//!   ψ_n(x) upward only while n ≤ x and from continued-fraction ratios above; χ_n(x) upward.
//! * Coefficients as a_n = A/(A − iB) with A = (D_n/m + n/x)ψ_n − ψ_{n−1},
//!   B = (D_n/m + n/x)χ_n − χ_{n−1} (BH eq. 4.88), so that for real m, Re a_n = |a_n|² to
//!   rounding and Q_abs is formed directly from −Im(A B*) without cancellation.
//! * Term count: [`default_terms`] (Wiscombe 1980's rule plus a measured margin, documented there).
//! * Small particles, x·max(1, |m|) ≤ [`X_SMALL`]: ascending-series branch in the spirit of
//!   Wiscombe's small-particle limit, to full double precision (module `small`).
//! * Complex divisions use Smith's algorithm (no NaN for tiny or huge divisors).

mod bessel;
mod small;

pub use num_complex::Complex64;
use num_complex::Complex64 as C64;

use bessel::{cdiv, crecip};

/// Switch point of the small-particle (ascending-series) branch: it is used when
/// `x · max(1, |m|) ≤ X_SMALL`. Wiscombe (1979, 1980) switches at |m| x = 0.1 as well; there his
/// truncated closed forms are good to ~1e-6, ours to full double precision.
pub const X_SMALL: f64 = 0.1;

/// Largest accepted size parameter. Wiscombe's term-count rule is validated to x = 20 000; the
/// recurrences work beyond, with relative accuracy degrading roughly like 1e-16·x.
pub const X_MAX: f64 = 1.0e6;

/// Largest accepted |m|·x (the continued fraction for D_n(mx) needs ~|m x|/2 steps when
/// |m x| exceeds the term count).
pub const MX_MAX: f64 = 2.0e7;

/// Largest accepted |m| (the small-particle branch forms powers up to m^18).
pub const M_MAX: f64 = 1.0e6;

/// Largest accepted explicit term count.
pub const N_TERMS_MAX: usize = 2_000_000;

/// Efficiencies of a homogeneous sphere under plane-wave illumination (all dimensionless).
///
/// `qext = qsca + qabs` to rounding; `qabs` is computed directly (not as a difference) and is
/// exactly 0 for a real index; `qback` is the radar backscattering efficiency
/// (1/x²)|Σ(2n+1)(−1)^n (a_n − b_n)|² (BH §4.6); `g = ⟨cos θ⟩` (BH eq. 4.79, g = 0 when nothing
/// scatters); `n_terms` is the number of multipoles summed.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MieResult {
    pub qext: f64,
    pub qsca: f64,
    pub qabs: f64,
    pub qback: f64,
    pub g: f64,
    pub n_terms: usize,
}

/// Errors of the Mie tier. Messages name the argument, its value and the allowed range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MieError {
    /// An argument is non-finite or outside its allowed range.
    #[error("mie: argument `{name}` = {value} is out of range; allowed: {allowed}")]
    InvalidArgument {
        name: &'static str,
        value: String,
        allowed: String,
    },
    /// The continued fraction for the log-derivative did not converge (not expected to
    /// happen inside the accepted ranges; reported instead of returning garbage).
    #[error(
        "mie: Lentz continued fraction for D_n(z) did not converge (z = {z}, order {order}, {iterations} iterations)"
    )]
    NoConvergence {
        z: String,
        order: usize,
        iterations: usize,
    },
}

fn invalid(
    name: &'static str,
    value: impl std::fmt::Display,
    allowed: impl Into<String>,
) -> MieError {
    MieError::InvalidArgument {
        name,
        value: value.to_string(),
        allowed: allowed.into(),
    }
}

fn fmt_c(m: C64) -> String {
    if m.im < 0.0 || (m.im == 0.0 && m.im.is_sign_negative()) {
        format!("{} - {}i", m.re, -m.im)
    } else {
        format!("{} + {}i", m.re, m.im)
    }
}

fn check_x(x: f64) -> Result<(), MieError> {
    if !x.is_finite() || x <= 0.0 || x > X_MAX {
        return Err(invalid(
            "x",
            x,
            format!("finite size parameter, 0 < x ≤ {X_MAX:e}"),
        ));
    }
    Ok(())
}

fn check_m(x: f64, m: C64) -> Result<(), MieError> {
    if !m.re.is_finite() || !m.im.is_finite() {
        return Err(invalid("m", fmt_c(m), "finite complex relative index"));
    }
    if m.im < 0.0 {
        return Err(invalid(
            "m",
            fmt_c(m),
            "Im m ≥ 0 (Bohren–Huffman convention m = n + iκ, κ ≥ 0 absorbs; an index written \
             n − iκ as in Wiscombe/miepython must be passed as n + iκ)",
        ));
    }
    if m.re < 0.0 {
        return Err(invalid("m", fmt_c(m), "Re m ≥ 0"));
    }
    if m.re == 0.0 && m.im == 0.0 {
        return Err(invalid(
            "m",
            fmt_c(m),
            "m ≠ 0 (perfect conductors are not supported)",
        ));
    }
    if m.norm() > M_MAX {
        return Err(invalid("m", fmt_c(m), format!("|m| ≤ {M_MAX:e}")));
    }
    let mx = m.norm() * x;
    if mx > MX_MAX {
        return Err(invalid(
            "m",
            fmt_c(m),
            format!("|m|·x ≤ {MX_MAX:e} (here |m|·x = {mx:e})"),
        ));
    }
    Ok(())
}

fn check_terms(n_terms: Option<usize>) -> Result<(), MieError> {
    if let Some(n) = n_terms {
        if n == 0 || n > N_TERMS_MAX {
            return Err(invalid(
                "n_terms",
                n,
                format!("1 ≤ n_terms ≤ {N_TERMS_MAX} (or None for the default rule)"),
            ));
        }
    }
    Ok(())
}

/// Wiscombe's (1980, Appl. Opt. 19, 1505, Eq. 20; MIEV0 `NTRM`) term-count rule, exactly:
///
/// * N = ⌊x + 4 x^{1/3} + 1⌋      for x ≤ 8,
/// * N = ⌊x + 4.05 x^{1/3} + 2⌋   for 8 < x < 4200,
/// * N = ⌊x + 4 x^{1/3} + 2⌋      for x ≥ 4200,
///
/// and at least 1. `x` dimensionless size parameter.
pub fn wiscombe_terms(x: f64) -> usize {
    let c = x.cbrt();
    let n = if x <= 8.0 {
        x + 4.0 * c + 1.0
    } else if x < 4200.0 {
        x + 4.05 * c + 2.0
    } else {
        x + 4.0 * c + 2.0
    };
    (n.floor() as usize).max(1)
}

/// Terms summed by default for a sphere of size parameter `x` and relative index `m`.
///
/// * Small-particle branch (x·max(1,|m|) ≤ [`X_SMALL`]): the smallest N ≥ 2 with
///   z^{2N−2}/(5·3·7·5·…·(2N+1)(2N−1)) < 1e-18, z = x·max(1,|m|) (estimated ratio of the next
///   multipole to the dipole), at most 8.
/// * Otherwise N = [`wiscombe_terms`]`(x) + ⌈2 x^{1/3}⌉ + 1`. Wiscombe designed his rule for
///   ~1e-6–1e-8 accuracy; measured against 60-digit references and against N + 400 (see
///   `docs/mie.md`), it leaves relative errors up to ~2e-10 in Q_ext and up to ~2e-5 in Q_back
///   (x = 5000, m = 1.2). The margin ⌈2 x^{1/3}⌉ + 1 brings Q_ext, Q_sca, Q_abs and g to
///   ≲ 1e-13 and Q_back to ≲ 1e-10 over 0.1 < x ≤ 10⁴ for the tested indices, at a cost of
///   ≤ 2 % extra terms for x ≥ 1000. Use [`mie_q_terms`] with `Some(wiscombe_terms(x))` for
///   Wiscombe's count exactly.
pub fn default_terms(x: f64, m: C64) -> usize {
    let z = x * m.norm().max(1.0);
    if z <= X_SMALL {
        small::default_terms(z)
    } else {
        wiscombe_terms(x) + (2.0 * x.cbrt()).ceil() as usize + 1
    }
}

/// Internal coefficient set: a_n = scale·a[n−1], b_n = scale·b[n−1];
/// absorb[n−1] = (Re a_n − |a_n|² + Re b_n − |b_n|²)/scale. `scale_x` = scale/x and
/// `scale_x2` = scale/x² are kept separately so that tiny spheres (scale = x³ underflowing)
/// still get Q_ext = O(x) right.
struct Coeffs {
    scale: f64,
    scale_x: f64,
    scale_x2: f64,
    a: Vec<C64>,
    b: Vec<C64>,
    absorb: Vec<f64>,
}

/// Above this |χ_n(x)| the remaining coefficients are ≲ ψ_n/χ_n < 1e-250 and set to zero, so
/// that a large explicit term count cannot overflow.
const CHI_MAX: f64 = 1e250;

/// a_n (or b_n) = A/(A − iB) with A = dd ψ_n − ψ_{n−1}, B = dd χ_n − χ_{n−1} (BH eq. 4.88 with
/// ξ_n = ψ_n − iχ_n), plus Re c − |c|² = −Im(A B*)/|A − iB|² (no cancellation for weak
/// absorption: both products carry Im m explicitly).
#[inline]
fn coefficient(
    dd: C64,
    psi_n: f64,
    psi_nm1: f64,
    chi_n: f64,
    chi_nm1: f64,
    want_absorb: bool,
) -> (C64, f64) {
    let (a, b) = if dd.re.abs() + dd.im.abs() < 1e150 {
        (
            C64::new(dd.re * psi_n - psi_nm1, dd.im * psi_n),
            C64::new(dd.re * chi_n - chi_nm1, dd.im * chi_n),
        )
    } else {
        // at a pole of D_n (measure zero for real m) the limit dd → ∞ gives ψ_n/ξ_n
        (C64::new(psi_n, 0.0), C64::new(chi_n, 0.0))
    };
    let den = C64::new(a.re + b.im, a.im - b.re); // A − iB
    let n2 = den.re * den.re + den.im * den.im;
    if n2 > 1e-290 && n2 < 1e290 {
        // common case: one real division serves the coefficient and its absorption term
        let inv = 1.0 / n2;
        let c = C64::new(
            (a.re * den.re + a.im * den.im) * inv,
            (a.im * den.re - a.re * den.im) * inv,
        );
        let absorb = if want_absorb {
            -(a.im * b.re - a.re * b.im) * inv
        } else {
            0.0
        };
        return (c, absorb);
    }
    let s = den.re.abs().max(den.im.abs());
    if s == 0.0 || !s.is_finite() {
        return (C64::new(0.0, 0.0), 0.0);
    }
    let c = cdiv(a, den);
    if !want_absorb {
        return (c, 0.0);
    }
    // scale by 1/s so that |den|² cannot overflow
    let si = 1.0 / s;
    let (ar, ai, br, bi) = (a.re * si, a.im * si, b.re * si, b.im * si);
    let (dr, di) = (den.re * si, den.im * si);
    let absorb = -(ai * br - ar * bi) / (dr * dr + di * di);
    (c, absorb)
}

/// Real-index version of [`coefficient`]: A, B real, a_n = A/(A − iB) = t/(t − i) with
/// t = A/B (or 1/(1 − iu), u = B/A), two real divisions and no overflow.
#[inline]
fn coefficient_real(dd: f64, psi_n: f64, psi_nm1: f64, chi_n: f64, chi_nm1: f64) -> C64 {
    let (a, b) = if dd.abs() < 1e150 {
        (dd * psi_n - psi_nm1, dd * chi_n - chi_nm1)
    } else {
        (psi_n, chi_n) // pole of D_n: limit ψ_n/ξ_n
    };
    if b.abs() >= a.abs() {
        if b == 0.0 {
            return C64::new(0.0, 0.0);
        }
        let t = a / b;
        let d = 1.0 / (1.0 + t * t);
        C64::new(t * t * d, t * d)
    } else {
        let u = b / a;
        let d = 1.0 / (1.0 + u * u);
        C64::new(d, u * d)
    }
}

/// The order loop of the general-size coefficients, n = 1 … `n_terms`: runs the upward
/// recurrence of χ_n(x) (χ_0 = cos x, χ_1 = cos x / x + sin x, χ_{n+1} = (2n + 1)/x·χ_n −
/// χ_{n−1}) and hands `sink` what `order(n, n/x, χ_n, χ_{n−1})` makes of each order: zeros
/// from the first |χ_n| > CHI_MAX on.
fn stream_orders(
    x: f64,
    n_terms: usize,
    mut sink: impl FnMut(C64, C64, f64),
    mut order: impl FnMut(usize, f64, f64, f64) -> (C64, C64, f64),
) {
    let xinv = 1.0 / x;
    let (sx, cx) = x.sin_cos();
    let mut chi_nm1 = cx; // χ_0
    let mut chi_n = cx * xinv + sx; // χ_1
    let zero = C64::new(0.0, 0.0);
    for n in 1..=n_terms {
        if chi_n.abs() > CHI_MAX {
            sink(zero, zero, 0.0);
            continue;
        }
        let (an, bn, third) = order(n, n as f64 * xinv, chi_n, chi_nm1);
        sink(an, bn, third);
        let chi_np1 = (2 * n + 1) as f64 * xinv * chi_n - chi_nm1;
        chi_nm1 = chi_n;
        chi_n = chi_np1;
    }
}

/// Streams the general-size coefficients for a real relative index, in real arithmetic (same
/// equations as [`stream_complex`]; about three times cheaper): calls `sink(a_n, b_n, 0)` for
/// n = 1 … `n_terms` in order (zeros once |χ_n| > CHI_MAX).
fn stream_real(
    x: f64,
    m: f64,
    n_terms: usize,
    sink: impl FnMut(C64, C64, f64),
) -> Result<(), MieError> {
    let z = m * x;
    let nc = |e: bessel::CfNoConvergence, zz: f64| MieError::NoConvergence {
        z: zz.to_string(),
        order: n_terms,
        iterations: e.iterations,
    };
    SCRATCH.with(|sc| {
        let mut sc = sc.borrow_mut();
        let (d, psi, ratios) = sc.real_parts();
        bessel::log_derivatives_real_into(z, n_terms, d).map_err(|e| nc(e, z))?;
        bessel::riccati_psi_into(x, n_terms, psi, ratios).map_err(|e| nc(e, x))?;
        let minv = 1.0 / m;
        stream_orders(x, n_terms, sink, |n, nx, chi_n, chi_nm1| {
            let dn = d[n - 1];
            let an = coefficient_real(dn * minv + nx, psi[n], psi[n - 1], chi_n, chi_nm1);
            let bn = coefficient_real(dn * m + nx, psi[n], psi[n - 1], chi_n, chi_nm1);
            (an, bn, 0.0)
        });
        Ok(())
    })
}

/// Streams the general-size coefficients (BH eq. 4.88), n = 1 … `n_terms`:
/// `sink(a_n, b_n, Re a_n − |a_n|² + Re b_n − |b_n|²)` in order.
fn stream_complex(
    x: f64,
    m: C64,
    n_terms: usize,
    sink: impl FnMut(C64, C64, f64),
) -> Result<(), MieError> {
    if m.im == 0.0 {
        return stream_real(x, m.re, n_terms, sink);
    }
    let z = m * x;
    let nc = |e: bessel::CfNoConvergence, zz: C64| MieError::NoConvergence {
        z: fmt_c(zz),
        order: n_terms,
        iterations: e.iterations,
    };
    SCRATCH.with(|sc| {
        let mut sc = sc.borrow_mut();
        let (d, psi, ratios) = sc.complex_parts();
        bessel::log_derivatives_into(z, n_terms, d).map_err(|e| nc(e, z))?;
        bessel::riccati_psi_into(x, n_terms, psi, ratios).map_err(|e| nc(e, C64::new(x, 0.0)))?;
        let minv = crecip(m);
        let absorbing = m.im != 0.0;
        stream_orders(x, n_terms, sink, |n, nx, chi_n, chi_nm1| {
            let dn = d[n - 1];
            let (an, abs_a) = coefficient(
                dn * minv + nx,
                psi[n],
                psi[n - 1],
                chi_n,
                chi_nm1,
                absorbing,
            );
            let (bn, abs_b) =
                coefficient(dn * m + nx, psi[n], psi[n - 1], chi_n, chi_nm1, absorbing);
            (an, bn, abs_a + abs_b)
        });
        Ok(())
    })
}

/// Per-thread work buffers of the general-size path (D_n, ψ_n and the ψ ratios), reused
/// across calls so that `mie_q` allocates nothing in steady state.
#[derive(Default)]
struct Scratch {
    d_real: Vec<f64>,
    d_complex: Vec<C64>,
    psi: Vec<f64>,
    ratios: Vec<f64>,
}

impl Scratch {
    fn real_parts(&mut self) -> (&mut Vec<f64>, &mut Vec<f64>, &mut Vec<f64>) {
        (&mut self.d_real, &mut self.psi, &mut self.ratios)
    }
    fn complex_parts(&mut self) -> (&mut Vec<C64>, &mut Vec<f64>, &mut Vec<f64>) {
        (&mut self.d_complex, &mut self.psi, &mut self.ratios)
    }
}

thread_local! {
    static SCRATCH: std::cell::RefCell<Scratch> = std::cell::RefCell::new(Scratch::default());
}

/// General-size coefficients (BH eq. 4.88), n = 1 … `n_terms`, stored.
fn full_coefficients(x: f64, m: C64, n_terms: usize) -> Result<Coeffs, MieError> {
    let xinv = 1.0 / x;
    let mut out = Coeffs {
        scale: 1.0,
        scale_x: xinv,
        scale_x2: xinv * xinv,
        a: Vec::with_capacity(n_terms),
        b: Vec::with_capacity(n_terms),
        absorb: Vec::with_capacity(n_terms),
    };
    stream_complex(x, m, n_terms, |a, b, ab| {
        out.a.push(a);
        out.b.push(b);
        out.absorb.push(ab);
    })?;
    Ok(out)
}

/// Validated dispatch between the small-particle branch and the general recurrences.
fn coefficients_internal(x: f64, m: C64, n_terms: Option<usize>) -> Result<Coeffs, MieError> {
    check_x(x)?;
    check_m(x, m)?;
    check_terms(n_terms)?;
    let n = n_terms.unwrap_or_else(|| default_terms(x, m));
    if m == C64::new(1.0, 0.0) {
        // index-matched sphere: no scatterer at all (exactly; avoids rounding noise)
        return Ok(Coeffs {
            scale: 1.0,
            scale_x: 1.0 / x,
            scale_x2: 1.0 / (x * x),
            a: vec![C64::new(0.0, 0.0); n],
            b: vec![C64::new(0.0, 0.0); n],
            absorb: vec![0.0; n],
        });
    }
    if x * m.norm().max(1.0) <= X_SMALL {
        let c = small::small_coefficients(x, m, n);
        Ok(Coeffs {
            scale: x * x * x,
            scale_x: x * x,
            scale_x2: x,
            a: c.ahat,
            b: c.bhat,
            absorb: c.absorb_hat,
        })
    } else {
        full_coefficients(x, m, n)
    }
}

/// Lorenz–Mie coefficients a_n, b_n, n = 1 … N (`a[n-1] = a_n`), of a homogeneous sphere with
/// size parameter `x` (dimensionless, 0 < x ≤ [`X_MAX`]) and relative index `m`
/// (Bohren–Huffman convention, Im m ≥ 0 absorbs; see the module docs).
///
/// `n_terms`: `None` uses [`default_terms`]; `Some(N)` sums exactly N multipoles (the accuracy
/// knob; 1 ≤ N ≤ [`N_TERMS_MAX`]). Source: BH eq. 4.53 in the log-derivative form eq. 4.88,
/// with Wiscombe's (1980) stable recurrences; ascending series for x·max(1,|m|) ≤ [`X_SMALL`].
/// For spheres so small that a_n underflows, the coefficients are returned as 0 (efficiencies
/// are computed in a scaled form and stay accurate).
pub fn mie_coefficients(
    x: f64,
    m: C64,
    n_terms: Option<usize>,
) -> Result<(Vec<C64>, Vec<C64>), MieError> {
    let c = coefficients_internal(x, m, n_terms)?;
    let s = c.scale;
    Ok((
        c.a.into_iter().map(|v| v * s).collect(),
        c.b.into_iter().map(|v| v * s).collect(),
    ))
}

/// Running sums of the efficiency series (BH eq. 4.61, 4.62, 4.79; Q_back BH §4.6), fed one
/// order at a time, so the general-size path never stores the coefficients.
#[derive(Default)]
struct EffSums {
    n: usize,
    s_ext: f64,
    s_sca: f64,
    s_abs: f64,
    s_g: f64,
    back: C64,
    prev: (C64, C64),
}

impl EffSums {
    #[inline]
    fn push(&mut self, an: C64, bn: C64, absorb: f64) {
        self.n += 1;
        let n = self.n as f64;
        let w = 2.0 * n + 1.0;
        self.s_ext += w * (an.re + bn.re);
        self.s_sca += w * (an.norm_sqr() + bn.norm_sqr());
        self.s_abs += w * absorb;
        // (−1)^n
        let sign = if self.n % 2 == 1 { -1.0 } else { 1.0 };
        self.back += (an - bn) * (w * sign);
        // g·Q_sca = (4/x²)[Σ n(n+2)/(n+1) Re(a_n a*_{n+1} + b_n b*_{n+1})
        //                  + Σ (2n+1)/(n(n+1)) Re(a_n b*_n)]          (BH eq. 4.79)
        if self.n > 1 {
            let (pa, pb) = self.prev;
            let np = n - 1.0;
            self.s_g += np * (np + 2.0) / (np + 1.0) * ((pa * an.conj()).re + (pb * bn.conj()).re);
        }
        self.s_g += w / (n * (n + 1.0)) * (an * bn.conj()).re;
        self.prev = (an, bn);
    }

    /// Efficiencies for coefficients a_n = scale·â_n (`sx` = scale/x, `sx2` = scale/x²).
    fn finish(&self, m: C64, sx: f64, sx2: f64, n_terms: usize) -> MieResult {
        let qabs = if m.im == 0.0 {
            0.0
        } else {
            2.0 * sx2 * self.s_abs
        };
        MieResult {
            qext: 2.0 * sx2 * self.s_ext,
            qsca: 2.0 * sx * sx * self.s_sca,
            qabs,
            qback: sx * sx * self.back.norm_sqr(),
            g: if self.s_sca > 0.0 {
                2.0 * self.s_g / self.s_sca
            } else {
                0.0
            },
            n_terms,
        }
    }
}

/// Efficiencies from a stored coefficient set.
fn efficiencies(m: C64, c: &Coeffs) -> MieResult {
    let mut acc = EffSums::default();
    for i in 0..c.a.len() {
        acc.push(c.a[i], c.b[i], c.absorb[i]);
    }
    acc.finish(m, c.scale_x, c.scale_x2, c.a.len())
}

/// Extinction, scattering, absorption and backscattering efficiencies and asymmetry parameter
/// of a homogeneous sphere (plane wave), with the default term count.
///
/// `x`: size parameter 2πa·n_medium/λ (dimensionless, 0 < x ≤ [`X_MAX`]); `m`: relative index
/// n_particle/n_medium, Bohren–Huffman convention (Im m ≥ 0 absorbs, Re m ≥ 0, m ≠ 0,
/// |m|x ≤ [`MX_MAX`]). Sources: BH (1983) eq. 4.61, 4.62, 4.79, §4.6; Wiscombe (1980).
///
/// ```
/// use bfpscope::optics::mie::{mie_q, Complex64};
/// // Wiscombe (1979) MIEV0 test case: m = 1.5, x = 10  →  Q_ext = 2.881999, g = 0.742913
/// let r = mie_q(10.0, Complex64::new(1.5, 0.0)).unwrap();
/// assert!((r.qext - 2.881999).abs() < 1e-6 && (r.g - 0.742913).abs() < 1e-6);
/// ```
pub fn mie_q(x: f64, m: C64) -> Result<MieResult, MieError> {
    mie_q_terms(x, m, None)
}

/// [`mie_q`] with an explicit term count (`None` = [`default_terms`]); the accuracy knob used by
/// the accuracy-vs-time report.
pub fn mie_q_terms(x: f64, m: C64, n_terms: Option<usize>) -> Result<MieResult, MieError> {
    check_x(x)?;
    check_m(x, m)?;
    check_terms(n_terms)?;
    let n = n_terms.unwrap_or_else(|| default_terms(x, m));
    if m == C64::new(1.0, 0.0) || x * m.norm().max(1.0) <= X_SMALL {
        let c = coefficients_internal(x, m, n_terms)?;
        return Ok(efficiencies(m, &c));
    }
    // general size: stream the coefficients into the sums (nothing stored)
    let mut acc = EffSums::default();
    stream_complex(x, m, n, |a, b, ab| acc.push(a, b, ab))?;
    let xinv = 1.0 / x;
    Ok(acc.finish(m, xinv, xinv * xinv, n))
}

/// Amplitude functions (S_1(θ), S_2(θ)) at the given cosines of the scattering angle
/// (BH eq. 4.74, with π_n, τ_n from the recurrences BH eq. 4.47), default term count.
///
/// S_1 is the amplitude for polarisation perpendicular to the scattering plane, S_2 parallel;
/// dimensionless, BH normalisation (Q_ext = (4/x²) Re S_1(0°)), e^{−iωt} convention (the
/// complex conjugate of Wiscombe's/miepython's). `cos_theta` values must lie in [−1, 1].
pub fn mie_s1s2(x: f64, m: C64, cos_theta: &[f64]) -> Result<Vec<(C64, C64)>, MieError> {
    mie_s1s2_terms(x, m, cos_theta, None)
}

/// [`mie_s1s2`] with an explicit term count (`None` = [`default_terms`]).
pub fn mie_s1s2_terms(
    x: f64,
    m: C64,
    cos_theta: &[f64],
    n_terms: Option<usize>,
) -> Result<Vec<(C64, C64)>, MieError> {
    if let Some(&bad) = cos_theta
        .iter()
        .find(|mu| !mu.is_finite() || mu.abs() > 1.0)
    {
        return Err(invalid("cos_theta", bad, "finite values in [-1, 1]"));
    }
    let c = coefficients_internal(x, m, n_terms)?;
    let n_terms = c.a.len();
    // common factors (2n+1)/(n(n+1))
    let f: Vec<f64> = (1..=n_terms)
        .map(|n| {
            let n = n as f64;
            (2.0 * n + 1.0) / (n * (n + 1.0))
        })
        .collect();
    let out = cos_theta
        .iter()
        .map(|&mu| {
            let mut s1 = C64::new(0.0, 0.0);
            let mut s2 = C64::new(0.0, 0.0);
            let mut pi_nm1 = 0.0; // π_0
            let mut pi_n = 1.0; // π_1
            for (i, ((an, bn), fi)) in c.a.iter().zip(&c.b).zip(&f).enumerate() {
                let n = (i + 1) as f64;
                let tau_n = n * mu * pi_n - (n + 1.0) * pi_nm1;
                s1 += (an * pi_n + bn * tau_n) * fi;
                s2 += (an * tau_n + bn * pi_n) * fi;
                let pi_np1 = ((2.0 * n + 1.0) * mu * pi_n - (n + 1.0) * pi_nm1) / n;
                pi_nm1 = pi_n;
                pi_n = pi_np1;
            }
            (s1 * c.scale, s2 * c.scale)
        })
        .collect();
    Ok(out)
}

/// Mie efficiencies of a sphere of diameter `d_nm` (nm) and complex index `n_particle`
/// (Bohren–Huffman convention, Im ≥ 0 absorbs) in a non-absorbing medium of index `n_medium`,
/// illuminated at vacuum wavelength `wavelength_nm` (nm):
/// x = π d n_medium / λ, m = n_particle / n_medium (BH §4.4). Cross-sections follow as
/// C = Q · π d²/4 (nm²).
pub fn sphere(
    d_nm: f64,
    n_particle: C64,
    n_medium: f64,
    wavelength_nm: f64,
) -> Result<MieResult, MieError> {
    if !d_nm.is_finite() || d_nm <= 0.0 {
        return Err(invalid("d_nm", d_nm, "finite diameter in nm, d_nm > 0"));
    }
    if !n_medium.is_finite() || n_medium <= 0.0 {
        return Err(invalid(
            "n_medium",
            n_medium,
            "finite medium index, n_medium > 0",
        ));
    }
    if !wavelength_nm.is_finite() || wavelength_nm <= 0.0 {
        return Err(invalid(
            "wavelength_nm",
            wavelength_nm,
            "finite vacuum wavelength in nm, wavelength_nm > 0",
        ));
    }
    if !n_particle.re.is_finite()
        || !n_particle.im.is_finite()
        || n_particle.im < 0.0
        || n_particle.re < 0.0
        || n_particle == C64::new(0.0, 0.0)
    {
        return Err(invalid(
            "n_particle",
            fmt_c(n_particle),
            "finite, non-zero complex index with Re ≥ 0 and Im ≥ 0 (Bohren–Huffman convention, \
             Im > 0 absorbs)",
        ));
    }
    let x = std::f64::consts::PI * d_nm * n_medium / wavelength_nm;
    if x > X_MAX {
        return Err(invalid(
            "d_nm",
            d_nm,
            format!("size parameter π·d_nm·n_medium/wavelength_nm ≤ {X_MAX:e} (here {x:e})"),
        ));
    }
    mie_q(x, n_particle / n_medium)
}

/// Log-derivatives D_1(z) … D_N(z) of ψ_n (BH eq. 4.89) by downward recurrence from Lentz's
/// continued fraction — exposed for tests and for the focused-beam tier. `z ≠ 0` complex,
/// dimensionless.
pub fn log_derivatives(z: C64, n_max: usize) -> Result<Vec<C64>, MieError> {
    if !z.re.is_finite() || !z.im.is_finite() || (z.re == 0.0 && z.im == 0.0) {
        return Err(invalid("z", fmt_c(z), "finite, non-zero complex argument"));
    }
    if n_max > N_TERMS_MAX {
        return Err(invalid("n_max", n_max, format!("n_max ≤ {N_TERMS_MAX}")));
    }
    bessel::log_derivatives(z, n_max).map_err(|e| MieError::NoConvergence {
        z: fmt_c(z),
        order: n_max,
        iterations: e.iterations,
    })
}
