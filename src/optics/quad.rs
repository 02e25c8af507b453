//! Gauss–Legendre quadrature nodes (Golub–Welsch-free Newton iteration on P_n; exact to
//! machine precision for n ≤ 1000).

/// Nodes and weights of the n-point Gauss–Legendre rule on [a, b].
pub fn gauss_legendre(n: usize, a: f64, b: f64) -> (Vec<f64>, Vec<f64>) {
    let n = n.max(1);
    let mut x = vec![0.0; n];
    let mut w = vec![0.0; n];
    let (mid, half) = (0.5 * (a + b), 0.5 * (b - a));
    for i in 0..n.div_ceil(2) {
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
        let wi = 2.0 / ((1.0 - z * z) * dp * dp);
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
