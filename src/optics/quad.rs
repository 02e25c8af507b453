//! Gauss–Legendre quadrature nodes (Golub–Welsch-free Newton iteration on P_n; exact to
//! machine precision for n ≤ 1000).

/// Nodes and weights of the n-point Gauss–Legendre rule on [a, b].
///
/// The rule on [−1, 1] (the Newton roots z_i and weights 2/((1 − z²)P_n'²) of its first half)
/// is computed once per n and remembered (process-wide, up to [`RULES_KEPT`] sizes): the
/// Newton iteration was ~15 % of building a vector-beam template plane. The mapping to [a, b]
/// is the same arithmetic as before, so the values are unchanged.
pub fn gauss_legendre(n: usize, a: f64, b: f64) -> (Vec<f64>, Vec<f64>) {
    let n = n.max(1);
    let rule = standard_rule(n);
    let mut x = vec![0.0; n];
    let mut w = vec![0.0; n];
    let (mid, half) = (0.5 * (a + b), 0.5 * (b - a));
    for (i, &(z, wi)) in rule.iter().enumerate() {
        x[i] = mid - half * z;
        x[n - 1 - i] = mid + half * z;
        w[i] = half * wi;
        w[n - 1 - i] = half * wi;
    }
    if n == 1 {
        x[0] = mid;
        w[0] = b - a;
    }
    (x, w)
}

/// The n-point Gauss–Legendre rule on each quadrant [q·π/2, (q+1)·π/2] of the azimuth, q = 0…3:
/// (nodes, weights) per quadrant, so that no node straddles a QPD quadrant boundary.
pub fn quadrant_gauss(n: usize) -> [(Vec<f64>, Vec<f64>); 4] {
    let quarter = std::f64::consts::FRAC_PI_2;
    std::array::from_fn(|q| gauss_legendre(n, q as f64 * quarter, (q + 1) as f64 * quarter))
}

/// Sizes of the remembered rules (the oldest is dropped beyond that).
const RULES_KEPT: usize = 64;

type Rule = std::sync::Arc<Vec<(f64, f64)>>;

static RULES: std::sync::Mutex<Vec<(usize, Rule)>> = std::sync::Mutex::new(Vec::new());

/// (z_i, 2/((1 − z_i²) P_n'(z_i)²)) for i < ⌈n/2⌉, remembered per n.
fn standard_rule(n: usize) -> Rule {
    let lock = || {
        RULES
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
    };
    if let Some((_, r)) = lock().iter().find(|(m, _)| *m == n) {
        return r.clone();
    }
    let rule: Rule = std::sync::Arc::new(
        (0..n.div_ceil(2))
            .map(|i| {
                // Tricomi initial guess, then Newton on P_n.
                let mut z = (std::f64::consts::PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
                let mut dp = 1.0;
                for _ in 0..100 {
                    let (mut p0, mut p1) = (1.0, z);
                    for k in 2..=n {
                        let p2 = ((2 * k - 1) as f64 * z * p1 - (k - 1) as f64 * p0) / k as f64;
                        p0 = p1;
                        p1 = p2;
                    }
                    let pn = if n == 1 { z } else { p1 };
                    let pn1 = if n == 1 { 1.0 } else { p0 };
                    dp = n as f64 * (z * pn - pn1) / (z * z - 1.0);
                    let dz = pn / dp;
                    z -= dz;
                    if dz.abs() < 1e-16 {
                        break;
                    }
                }
                if n == 1 {
                    z = 0.0;
                    dp = 1.0;
                }
                (z, 2.0 / ((1.0 - z * z) * dp * dp))
            })
            .collect(),
    );
    let mut kept = lock();
    if kept.len() >= RULES_KEPT {
        kept.remove(0);
    }
    kept.push((n, rule.clone()));
    rule
}

#[cfg(test)]
mod tests {
    use super::*;
    #[test]
    fn integrates_polynomials_exactly_and_smooth_functions_well() {
        for n in [1usize, 2, 5, 16, 48] {
            let (x, w) = gauss_legendre(n, -1.0, 2.0);
            let deg = 2 * n - 1;
            let num: f64 = x.iter().zip(&w).map(|(x, w)| w * x.powi(deg as i32)).sum();
            let exact =
                (2f64.powi(deg as i32 + 1) - (-1f64).powi(deg as i32 + 1)) / (deg as f64 + 1.0);
            assert!(
                (num - exact).abs() < 1e-12 * exact.abs().max(1.0),
                "n={n}: {num} vs {exact}"
            );
        }
        let (x, w) = gauss_legendre(20, 0.0, std::f64::consts::PI);
        let s: f64 = x.iter().zip(&w).map(|(x, w)| w * x.sin()).sum();
        assert!((s - 2.0).abs() < 1e-14);
    }
}
