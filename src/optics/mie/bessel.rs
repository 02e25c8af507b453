//! Riccati–Bessel machinery for the Lorenz–Mie coefficients (pure numerics, no I/O).
//!
//! Conventions (Bohren & Huffman 1983, "Absorption and Scattering of Light by Small
//! Particles", Ch. 4, hereafter BH):
//!
//! * ψ_n(ρ) = ρ j_n(ρ), χ_n(ρ) = −ρ y_n(ρ), ξ_n(ρ) = ψ_n(ρ) − i χ_n(ρ) = ρ h_n^(1)(ρ);
//! * D_n(z) = ψ_n'(z) / ψ_n(z), the logarithmic derivative (BH eq. 4.88–4.89).
//!
//! Stability, following Wiscombe (1979, NCAR/TN-140+STR; 1980, Appl. Opt. 19, 1505) and
//! Lentz (1976, Appl. Opt. 15, 668):
//!
//! * D_n(mx) by **downward** recurrence D_{n−1} = n/z − 1/(D_n + n/z) (BH eq. 4.89), started at
//!   the highest order from Lentz's continued fraction for ψ_{N−1}/ψ_N — so no extra
//!   "|mx| + 15" orders are needed;
//! * ψ_n(x) (the minimal solution for n > x) by the **upward** three-term recurrence only while
//!   n ≤ x (oscillatory region, where it is stable), and above that from the ratios
//!   ψ_{n−1}/ψ_n obtained downward from the same continued fraction — so ψ_n keeps full
//!   relative precision at every order and at small x;
//! * χ_n(x) (the dominant solution) by the **upward** recurrence, which is stable for it.
//!
//! Lengths in this module are dimensionless (size parameters).

use num_complex::Complex64 as C64;

/// Replacement for an exactly vanishing denominator in the continued fraction and the
/// downward recurrence (modified Lentz method, Thompson & Barnett 1986, J. Comput. Phys. 64, 490).
const TINY: f64 = 1e-300;

/// Convergence tolerance of the continued fraction, |Δ_k − 1| ≤ CF_TOL.
const CF_TOL: f64 = 1e-15;

/// Robust complex division `a / b` (Smith 1962, Comm. ACM 5, 435).
///
/// Unlike `num_complex`'s `a / b`, which forms |b|² and therefore returns NaN/inf for
/// |b| ≲ 1e-154 or |b| ≳ 1e154, this never forms |b|², so it is exact to rounding for any
/// finite non-zero `b`. `b == 0` gives non-finite output (callers guard against it).
#[inline]
pub(crate) fn cdiv(a: C64, b: C64) -> C64 {
    if b.re.abs() >= b.im.abs() {
        let r = b.im / b.re;
        let inv = 1.0 / (b.re + b.im * r);
        C64::new((a.re + a.im * r) * inv, (a.im - a.re * r) * inv)
    } else {
        let r = b.re / b.im;
        let inv = 1.0 / (b.re * r + b.im);
        C64::new((a.re * r + a.im) * inv, (a.im * r - a.re) * inv)
    }
}

/// Robust complex reciprocal `1 / b` (Smith's method, see [`cdiv`]).
#[inline]
pub(crate) fn crecip(b: C64) -> C64 {
    cdiv(C64::new(1.0, 0.0), b)
}

/// `1 / b` with a single real division when |b|² is safely inside the normal range, else
/// Smith's method ([`cdiv`]); same result to rounding, used in the hot recurrences.
#[inline]
pub(crate) fn crecip_fast(b: C64) -> C64 {
    let n2 = b.re * b.re + b.im * b.im;
    if n2 > 1e-290 && n2 < 1e290 {
        let inv = 1.0 / n2;
        C64::new(b.re * inv, -b.im * inv)
    } else {
        crecip(b)
    }
}

/// Replace an (almost) exactly vanishing complex number by `TINY`, as in the modified Lentz
/// method; keeps the recurrences finite at the (measure-zero) poles of D_n.
#[inline]
fn guard(c: C64) -> C64 {
    if c.re.abs() + c.im.abs() < TINY {
        C64::new(TINY, 0.0)
    } else {
        c
    }
}

/// A result of the continued fractions and the recurrences they start.
pub(crate) type CfResult<T> = Result<T, CfNoConvergence>;

/// Error from the continued fraction: it did not converge within `iterations` steps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct CfNoConvergence {
    pub iterations: usize,
}

/// Iteration cap of the continued fraction for argument `z` at order `n`: the partial
/// denominators (2n+2k+1)/z only start to dominate once 2k ≳ |z|, after which convergence is
/// geometric; allow that many steps plus a generous margin.
fn cf_max_iter(abs_z: f64) -> usize {
    (abs_z.min(1e9) as usize).saturating_add(10_000)
}

/// Ratio r_n(z) = ψ_{n−1}(z)/ψ_n(z) from Lentz's continued fraction (Lentz 1976, Appl. Opt.
/// 15, 668; modified form of Thompson & Barnett 1986):
///
/// r_n = (2n+1)/z − 1/((2n+3)/z − 1/((2n+5)/z − …)),
///
/// which follows from ψ_{n+1} = (2n+1)/z ψ_n − ψ_{n−1} and converges because ψ_n is the
/// minimal solution of that recurrence as n → ∞. Then D_n(z) = r_n(z) − n/z.
/// `n ≥ 1`, `z ≠ 0`.
pub(crate) fn psi_ratio_cf(n: usize, z: C64) -> CfResult<C64> {
    let zinv = crecip(z);
    let b = |k: usize| zinv * ((2 * n + 2 * k + 1) as f64);
    let mut f = guard(b(0));
    let mut c = f;
    let mut d = C64::new(0.0, 0.0);
    let max_iter = cf_max_iter(z.norm());
    for k in 1..=max_iter {
        let bk = b(k);
        // partial numerators are all −1: D_k = b_k − D_{k−1}, C_k = b_k − 1/C_{k−1}
        d = crecip_fast(guard(bk - d));
        c = guard(bk - crecip_fast(c));
        let delta = c * d;
        f *= delta;
        if (delta - 1.0).norm_sqr() <= CF_TOL * CF_TOL {
            return Ok(f);
        }
    }
    Err(CfNoConvergence {
        iterations: max_iter,
    })
}

/// Real-argument version of [`psi_ratio_cf`]: r_n(x) = ψ_{n−1}(x)/ψ_n(x) for real x > 0.
pub(crate) fn psi_ratio_cf_real(n: usize, x: f64) -> CfResult<f64> {
    let xinv = 1.0 / x;
    let guard_r = |v: f64| if v.abs() < TINY { TINY } else { v };
    let b = |k: usize| xinv * ((2 * n + 2 * k + 1) as f64);
    let mut f = guard_r(b(0));
    let mut c = f;
    let mut d = 0.0;
    let max_iter = cf_max_iter(x);
    for k in 1..=max_iter {
        let bk = b(k);
        d = 1.0 / guard_r(bk - d);
        c = guard_r(bk - 1.0 / c);
        let delta = c * d;
        f *= delta;
        if (delta - 1.0).abs() <= CF_TOL {
            return Ok(f);
        }
    }
    Err(CfNoConvergence {
        iterations: max_iter,
    })
}

/// Logarithmic derivatives D_1(z) … D_N(z) (returned with `d[n-1] = D_n`) by downward
/// recurrence D_{n−1} = n/z − 1/(D_n + n/z) (BH eq. 4.89) started from Lentz's continued
/// fraction at n = N. Stable for every complex z (Wiscombe 1980; Kattawar & Plass 1967).
pub(crate) fn log_derivatives(z: C64, n_max: usize) -> CfResult<Vec<C64>> {
    let mut d = Vec::new();
    log_derivatives_into(z, n_max, &mut d)?;
    Ok(d)
}

/// [`log_derivatives`] into a reused buffer (resized to `n_max`).
pub(crate) fn log_derivatives_into(z: C64, n_max: usize, d: &mut Vec<C64>) -> CfResult<()> {
    d.clear();
    d.resize(n_max, C64::new(0.0, 0.0));
    if n_max == 0 {
        return Ok(());
    }
    let zinv = crecip(z);
    let mut r = psi_ratio_cf(n_max, z)?; // r_N = ψ_{N−1}/ψ_N = D_N + N/z
    d[n_max - 1] = r - zinv * (n_max as f64);
    // r_{n−1} = (2n−1)/z − 1/r_n  and  D_{n−1} = r_{n−1} − (n−1)/z
    for n in (2..=n_max).rev() {
        let rn1 = zinv * ((2 * n - 1) as f64) - crecip_fast(guard(r));
        d[n - 2] = rn1 - zinv * ((n - 1) as f64);
        r = rn1;
    }
    Ok(())
}

/// Real-argument version of [`log_derivatives`] (real relative index): D_1(z) … D_N(z) for
/// real z > 0, in real arithmetic (same recurrence and continued-fraction start).
/// (Written into a reused buffer, resized to `n_max`.)
pub(crate) fn log_derivatives_real_into(z: f64, n_max: usize, d: &mut Vec<f64>) -> CfResult<()> {
    d.clear();
    d.resize(n_max, 0.0);
    if n_max == 0 {
        return Ok(());
    }
    let zinv = 1.0 / z;
    let mut r = psi_ratio_cf_real(n_max, z)?;
    d[n_max - 1] = r - zinv * (n_max as f64);
    for n in (2..=n_max).rev() {
        let g = if r.abs() < TINY { TINY } else { r };
        let rn1 = zinv * ((2 * n - 1) as f64) - 1.0 / g;
        d[n - 2] = rn1 - zinv * ((n - 1) as f64);
        r = rn1;
    }
    Ok(())
}

/// Riccati–Bessel ψ_0(x) … ψ_N(x) for real x > 0 (`psi[n] = ψ_n(x)`), stable at every order:
/// upward from ψ_{−1} = cos x, ψ_0 = sin x while n ≤ ⌊x⌋ (oscillatory region; BH eq. 4.89's
/// companion three-term recurrence), above that ψ_n = ψ_{n−1}/r_n with r_n = ψ_{n−1}/ψ_n from
/// the continued fraction at n = N and the downward recurrence r_{n−1} = (2n−1)/x − 1/r_n.
/// For n > x, ψ_n has no zeros (its first zero lies beyond n + 1.8 n^{1/3}), so every r_n is
/// finite and positive and the division keeps full relative precision; ψ_n underflows
/// gracefully to 0 for very high orders.
#[cfg(test)]
pub(crate) fn riccati_psi(x: f64, n_max: usize) -> CfResult<Vec<f64>> {
    let (mut psi, mut ratios) = (Vec::new(), Vec::new());
    riccati_psi_into(x, n_max, &mut psi, &mut ratios)?;
    Ok(psi)
}

/// `riccati_psi` into reused buffers (`psi` resized to `n_max + 1`; `ratios` is scratch).
pub(crate) fn riccati_psi_into(
    x: f64,
    n_max: usize,
    psi: &mut Vec<f64>,
    ratios: &mut Vec<f64>,
) -> CfResult<()> {
    psi.clear();
    psi.resize(n_max + 1, 0.0);
    psi[0] = x.sin();
    if n_max == 0 {
        return Ok(());
    }
    let n_up = (x.floor() as usize).min(n_max);
    // upward: ψ_n = (2n−1)/x ψ_{n−1} − ψ_{n−2}
    let xinv = 1.0 / x;
    let mut prev = x.cos(); // ψ_{−1}
    for n in 1..=n_up {
        let next = ((2 * n - 1) as f64) * xinv * psi[n - 1] - prev;
        prev = psi[n - 1];
        psi[n] = next;
    }
    if n_up == n_max {
        return Ok(());
    }
    // ratios r_n for n = n_up+1 ..= N, downward from the continued fraction at N
    ratios.clear();
    ratios.resize(n_max + 1, 0.0);
    let mut r = psi_ratio_cf_real(n_max, x)?;
    ratios[n_max] = r;
    for n in ((n_up + 2)..=n_max).rev() {
        r = ((2 * n - 1) as f64) * xinv - 1.0 / r;
        ratios[n - 1] = r;
    }
    for n in (n_up + 1)..=n_max {
        psi[n] = psi[n - 1] / ratios[n];
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Closed forms: ψ_1(x) = sin x/x − cos x, D_1(z) = −1/z + 1/(1/z − cot z) (from ψ_1).
    #[test]
    fn psi_and_d1_match_closed_forms() {
        for &x in &[1e-3f64, 0.1, 0.7, 1.0, 3.3, 25.0, 300.5] {
            let psi = riccati_psi(x, 60).unwrap();
            let p1 = x.sin() / x - x.cos();
            assert!(
                ((psi[1] - p1) / p1).abs() < 1e-9_f64.max(1e-15 / (x * x)),
                "x={x}"
            );
            // ψ_2 = (3/x² − 1) sin x − 3 cos x / x
            if x > 0.5 {
                let p2 = (3.0 / (x * x) - 1.0) * x.sin() - 3.0 * x.cos() / x;
                assert!(((psi[2] - p2) / p2).abs() < 1e-12, "x={x}");
            }
        }
        for &z in &[
            C64::new(1.5, 0.0),
            C64::new(3.0, 0.04),
            C64::new(10.0, 10.0),
            C64::new(0.05, 0.02),
        ] {
            let d = log_derivatives(z, 40).unwrap();
            let cot = z.cos() / z.sin();
            let d1 = -1.0 / z + 1.0 / (1.0 / z - cot);
            assert!((d[0] - d1).norm() / d1.norm() < 1e-12, "z={z}");
        }
    }

    /// ψ_n(x) must satisfy the three-term recurrence at every order, including n > x where
    /// the upward recurrence itself would be unstable; and the Wronskian
    /// ψ_n χ_{n−1} − ψ_{n−1} χ_n = −1 (from j_n y_{n−1} − j_{n−1} y_n = 1/x², Abramowitz &
    /// Stegun 10.1.6) with χ from the upward recurrence.
    #[test]
    fn psi_recurrence_and_wronskian() {
        for &x in &[0.3f64, 2.0, 17.0, 140.0] {
            let n_max = (x + 4.05 * x.cbrt() + 2.0) as usize + 10;
            let psi = riccati_psi(x, n_max).unwrap();
            let mut chi_prev = -x.sin(); // χ_{−1}
            let mut chi = x.cos(); // χ_0
            for n in 1..n_max {
                let chi_next = ((2 * n - 1) as f64) / x * chi - chi_prev;
                chi_prev = chi;
                chi = chi_next;
                let w = psi[n] * chi_prev - psi[n - 1] * chi;
                assert!((w + 1.0).abs() < 1e-10, "x={x} n={n} W={w}");
                let lhs = psi[n + 1];
                let rhs = ((2 * n + 1) as f64) / x * psi[n] - psi[n - 1];
                assert!(
                    (lhs - rhs).abs() <= 1e-10 * lhs.abs().max(psi[n].abs()),
                    "x={x} n={n}"
                );
            }
        }
    }

    #[test]
    fn smith_division_survives_tiny_divisors() {
        let a = C64::new(1e-200, 2e-200);
        let b = C64::new(3e-170, -4e-170);
        let q = cdiv(a, b);
        let expect = C64::new(-0.2, 0.4) * 1e-30;
        assert!((q - expect).norm() / expect.norm() < 1e-15);
        // num-complex's own division loses this one (|b|² underflows)
        assert!(!(a / b).is_finite() || (a / b - expect).norm() > 1e-31);
    }
}
