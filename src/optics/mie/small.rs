//! Small-particle branch: Lorenz–Mie coefficients from the ascending series of the
//! Riccati–Bessel functions, with the factor (m² − 1) taken out analytically.
//!
//! Wiscombe (1979, NCAR/TN-140+STR, "small-particle limit"; 1980, Appl. Opt. 19, 1505) switches
//! to closed-form series for a_1, a_2, b_1 when |m|x < 0.1, because the general recurrences lose
//! digits there. His truncated forms are accurate to roughly x⁴ (~1e-6 at the switch point); here
//! the same idea is carried to full double precision: every function is summed from its power
//! series until the terms drop below 1e-17, and as many multipoles are kept as contribute.
//!
//! With ψ_n(z) = z^{n+1}/(2n+1)!! · S(z²), ψ_n'(z) = z^n/(2n+1)!! · T(z²),
//! χ_n(x) = (2n−1)!!/x^n · U(x²), χ_n'(x) = (2n−1)!!/x^{n+1} · V(x²) (Abramowitz & Stegun
//! 10.1.2–10.1.3), BH eq. 4.53 becomes a_n = t_n/(t_n − i), b_n = u_n/(u_n − i) with
//!
//! t_n = x^{2n+1}/((2n+1)!!(2n−1)!!) · [m² S(m²x²) T(x²) − S(x²) T(m²x²)] / [m² S(m²x²) V(x²) − U(x²) T(m²x²)],
//! u_n = x^{2n+1}/((2n+1)!!(2n−1)!!) · [S(m²x²) T(x²) − S(x²) T(m²x²)] / [S(m²x²) V(x²) − U(x²) T(m²x²)].
//!
//! The numerator brackets vanish at m = 1; written as Σ_jk s_j t_k x^{2(j+k)} (m^{2p} − m^{2q})
//! each difference of powers is (m² − 1)·(±m^{2 min(p,q)})·(1 + m² + … ), so the coefficients keep
//! full relative precision even for m → 1 (Rayleigh–Gans spheres). Leading terms reproduce the
//! classical small-sphere results (BH eq. 5.4–5.5): a_1 ≈ −(2i/3)x³(m²−1)/(m²+2),
//! b_1 ≈ −(i/45)x⁵(m²−1), a_2 ≈ −(i/15)x⁵(m²−1)/(2m²+3).
//!
//! Coefficients are returned divided by x³ (â_n = a_n/x³) so that efficiencies can be formed
//! without x² underflowing for absurdly small spheres.

use super::bessel::cdiv;
use num_complex::Complex64 as C64;

/// Number of power-series terms (each of S, T, U, V) summed; at |m x| ≤ 0.1 the k-th term is
/// below (0.005)^k/(k!·5^k), i.e. < 1e-19 from k = 6 on. Eight keeps a margin.
const N_SERIES: usize = 8;

/// Highest multipole evaluated by default in this branch (x ≤ 0.1: a_n ∝ x^{2n+1}/((2n+1)!!)²,
/// so n = 6 is ≲ 1e-25 relative to a_1).
const N_DEFAULT_MAX: usize = 8;

/// Coefficients of the small-particle branch, scaled: a_n = x³·ahat[n-1], b_n = x³·bhat[n-1].
/// `absorb[n-1]` is (Re a_n − |a_n|² + Re b_n − |b_n|²)/x³ computed without cancellation.
pub(crate) struct SmallCoeffs {
    pub ahat: Vec<C64>,
    pub bhat: Vec<C64>,
    pub absorb_hat: Vec<f64>,
}

/// Series coefficients of S, T (ψ side, order n) and U, V (χ side).
fn series(
    n: usize,
) -> (
    [f64; N_SERIES],
    [f64; N_SERIES],
    [f64; N_SERIES],
    [f64; N_SERIES],
) {
    let nf = n as f64;
    let mut s = [0.0; N_SERIES];
    let mut t = [0.0; N_SERIES];
    let mut u = [0.0; N_SERIES];
    let mut v = [0.0; N_SERIES];
    s[0] = 1.0;
    u[0] = 1.0;
    for k in 1..N_SERIES {
        let kf = k as f64;
        // ψ: s_k = s_{k−1} · (−1/2) / (k (2n+2k+1))
        s[k] = s[k - 1] * (-0.5) / (kf * (2.0 * nf + 2.0 * kf + 1.0));
        // χ: u_k = u_{k−1} · (−1/2) / (k (2k−2n−1))
        u[k] = u[k - 1] * (-0.5) / (kf * (2.0 * kf - 2.0 * nf - 1.0));
    }
    for k in 0..N_SERIES {
        let kf = k as f64;
        t[k] = s[k] * (nf + 1.0 + 2.0 * kf);
        v[k] = u[k] * (2.0 * kf - nf);
    }
    (s, t, u, v)
}

/// Replace an exactly vanishing denominator (an exact resonance, measure zero) by the
/// smallest normal number so that the result stays finite.
#[inline]
fn nonzero(c: C64) -> C64 {
    if c.re == 0.0 && c.im == 0.0 {
        C64::new(f64::MIN_POSITIVE, 0.0)
    } else {
        c
    }
}

/// Σ_k c_k w^k (Horner).
fn poly_c(c: &[f64], w: C64) -> C64 {
    c.iter()
        .rev()
        .fold(C64::new(0.0, 0.0), |acc, &ck| acc * w + ck)
}
fn poly_r(c: &[f64], w: f64) -> f64 {
    c.iter().rev().fold(0.0, |acc, &ck| acc * w + ck)
}

/// (m^{2p} − m^{2q})/(m² − 1) from precomputed powers `mp[i] = m^{2i}` and geometric sums
/// `geo[r] = 1 + m² + … + m^{2(r−1)}`.
#[inline]
fn power_diff_over(mp: &[C64], geo: &[C64], p: usize, q: usize) -> C64 {
    use std::cmp::Ordering::*;
    match p.cmp(&q) {
        Equal => C64::new(0.0, 0.0),
        Greater => mp[q] * geo[p - q],
        Less => -(mp[p] * geo[q - p]),
    }
}

/// Multipoles needed in this branch for relative truncation ≲ 1e-17 (at least 2).
pub(crate) fn default_terms(x: f64) -> usize {
    // |a_n/a_1| ~ x^{2n−2} · 3/((2n+1)!! (2n−1)!!)
    let mut n = 1;
    let mut ratio = 1.0;
    while n < N_DEFAULT_MAX {
        let nn = (n + 1) as f64;
        ratio *= x * x / ((2.0 * nn + 1.0) * (2.0 * nn - 1.0));
        n += 1;
        if ratio < 1e-18 && n >= 2 {
            break;
        }
    }
    n
}

/// Coefficients a_n, b_n (scaled by x⁻³) for n = 1 … `n_terms` from the ascending series.
/// Valid (full double precision) for x·max(1, |m|) ≤ 0.1; `m` in the BH convention.
pub(crate) fn small_coefficients(x: f64, m: C64, n_terms: usize) -> SmallCoeffs {
    let x2 = x * x;
    let m2 = m * m;
    let w_m = m2 * x2; // (m x)²
                       // (m − 1)(m + 1): m − 1 is exact for m near 1 (Sterbenz), so m² − 1 keeps full precision
    let m2m1 = (m - 1.0) * (m + 1.0);
    // powers m^{2i} and geometric sums for i up to N_SERIES + 1
    let mut mp = vec![C64::new(1.0, 0.0); N_SERIES + 2];
    let mut geo = vec![C64::new(0.0, 0.0); N_SERIES + 2];
    for i in 1..mp.len() {
        mp[i] = mp[i - 1] * m2;
        geo[i] = geo[i - 1] + mp[i - 1];
    }
    // x^{2k} for the double sums
    let mut x2k = [1.0; 2 * N_SERIES];
    for k in 1..x2k.len() {
        x2k[k] = x2k[k - 1] * x2;
    }

    let mut out = SmallCoeffs {
        ahat: Vec::with_capacity(n_terms),
        bhat: Vec::with_capacity(n_terms),
        absorb_hat: Vec::with_capacity(n_terms),
    };
    // prefactor x^{2n+1}/((2n+1)!!(2n−1)!!), here divided by x³: start n = 1 → 1/3
    let mut pref_hat = 1.0 / 3.0;
    for n in 1..=n_terms {
        if n > 1 {
            let nf = n as f64;
            pref_hat *= x2 / ((2.0 * nf + 1.0) * (2.0 * nf - 1.0));
        }
        let (s, t, u, v) = series(n);
        // numerators / (m² − 1):
        //   a: Σ s_j t_k x^{2(j+k)} (m^{2(j+1)} − m^{2k})/(m²−1)
        //   b: Σ s_j t_k x^{2(j+k)} (m^{2j}     − m^{2k})/(m²−1)
        let mut num_a = C64::new(0.0, 0.0);
        let mut num_b = C64::new(0.0, 0.0);
        for j in 0..N_SERIES {
            for k in 0..N_SERIES {
                let c = s[j] * t[k] * x2k[j + k];
                if c == 0.0 {
                    continue;
                }
                num_a += power_diff_over(&mp, &geo, j + 1, k) * c;
                num_b += power_diff_over(&mp, &geo, j, k) * c;
            }
        }
        let s_m = poly_c(&s, w_m);
        let t_m = poly_c(&t, w_m);
        let u_x = poly_r(&u, x2);
        let v_x = poly_r(&v, x2);
        let den_a = nonzero(m2 * s_m * v_x - t_m * u_x);
        let den_b = nonzero(s_m * v_x - t_m * u_x);
        // t_n / x³ and u_n / x³
        let ta_hat = cdiv(m2m1 * num_a, den_a) * pref_hat;
        let tb_hat = cdiv(m2m1 * num_b, den_b) * pref_hat;
        let x3 = x2 * x;
        for (th, coeffs) in [(ta_hat, &mut out.ahat), (tb_hat, &mut out.bhat)] {
            let t_full = th * x3;
            let den = nonzero(C64::new(t_full.re, t_full.im - 1.0)); // t − i
            coeffs.push(cdiv(th, den));
        }
        // Re a − |a|² = −Im(t)/|t − i|²  (a = t/(t − i)); scaled by x⁻³
        let absorb = |th: C64| -> f64 {
            let t_full = th * x3;
            let d2 = t_full.re * t_full.re + (t_full.im - 1.0) * (t_full.im - 1.0);
            -th.im / d2
        };
        out.absorb_hat.push(absorb(ta_hat) + absorb(tb_hat));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Leading orders against BH eq. 5.4–5.5 (e^{−iωt} convention).
    #[test]
    fn leading_orders_match_bohren_huffman_5_4() {
        let m = C64::new(1.5, 0.2);
        let x = 1e-3;
        let c = small_coefficients(x, m, 3);
        let m2 = m * m;
        let i = C64::new(0.0, 1.0);
        let a1 = -i * (2.0 / 3.0) * (m2 - 1.0) / (m2 + 2.0); // / x³
        let b1 = -i * (x * x / 45.0) * (m2 - 1.0);
        let a2 = -i * (x * x / 15.0) * (m2 - 1.0) / (2.0 * m2 + 3.0);
        assert!((c.ahat[0] - a1).norm() / a1.norm() < 1e-5);
        assert!((c.bhat[0] - b1).norm() / b1.norm() < 1e-5);
        assert!((c.ahat[1] - a2).norm() / a2.norm() < 1e-5);
    }

    /// At m = 1 + δ the coefficients scale linearly in δ with no loss of relative precision.
    #[test]
    fn index_matched_limit_is_linear_in_contrast() {
        let x = 0.05;
        let (m1, m2) = (1.0 + 1e-9, 1.0 + 2e-9);
        // the contrasts actually represented (m − 1 is exact in floating point)
        let expect = ((m2 - 1.0) * (m2 + 1.0)) / ((m1 - 1.0) * (m1 + 1.0));
        let c1 = small_coefficients(x, C64::new(m1, 0.0), 3);
        let c2 = small_coefficients(x, C64::new(m2, 0.0), 3);
        for n in 0..3 {
            // a_n, b_n = (m² − 1)·(smooth in m²) + O((m² − 1)²): ratio = expect·(1 + O(1e-9))
            let r = c2.ahat[n] / c1.ahat[n];
            assert!(
                (r - expect).norm() < 1e-8,
                "a_{} ratio {r} vs {expect}",
                n + 1
            );
            let r = c2.bhat[n] / c1.bhat[n];
            assert!(
                (r - expect).norm() < 1e-8,
                "b_{} ratio {r} vs {expect}",
                n + 1
            );
        }
        let c0 = small_coefficients(x, C64::new(1.0, 0.0), 3);
        assert!(c0
            .ahat
            .iter()
            .chain(c0.bhat.iter())
            .all(|z| z.norm() == 0.0));
    }
}
