//! The `detector_range` effect: a detector and digitiser of finite range, so that scripted
//! tests meet clipped and dark inputs as a real bench gives them.
//!
//! The digitiser's inputs see `power · Sx`, `power · Sy` (the differences scale with the beam
//! power reaching the detector) and the sum `sum_scale · power · (1 + Sz)` (Sz is the relative
//! change of the total, so the sum sits at `sum_scale` with the full beam and no sample). Every
//! input spans ±`range`: a sample beyond it reads the rail. A read of n samples with per-sample
//! standard deviation σ (the noise effects) around a mean m clips a fraction
//! P(|m + σZ| ≥ range) of its samples (Z standard normal), and averages the clipped normal:
//! E[clamp(X, −r, r)] = r·(1 − Φ(b)) − r·Φ(a) + m·(Φ(b) − Φ(a)) + σ·(φ(a) − φ(b)),
//! a = (−r − m)/σ, b = (r − m)/σ. A pixel whose sum input lies below `sum_floor` is dark.
//! Scenes without the effect skip all of this.

use super::scene::DetectorRange;
use crate::instrument::range::InputRange;

/// The digitiser's view of a reading: the means `v` (Sx, Sy, Sz, signal units) and per-sample
/// standard deviations `sd` of `n` samples, through the detector's power, sum scale and range.
/// Returns the means as read back in signal units and the clipped sample count per channel.
pub fn apply(d: &DetectorRange, v: [f64; 3], sd: [f64; 3], n: usize) -> ([f64; 3], [usize; 3]) {
    let p = d.power;
    let input = [p * v[0], p * v[1], d.sum_scale * p * (1.0 + v[2])];
    let scale = [p, p, d.sum_scale * p];
    let mut out = [0.0; 3];
    let mut clipped = [0usize; 3];
    for c in 0..3 {
        let s = (scale[c] * sd[c]).abs();
        let (mean, frac) = clipped_normal(input[c], s, d.range);
        out[c] = mean;
        clipped[c] = (frac * n as f64).round() as usize;
    }
    let sum_scale = d.sum_scale;
    out[2] = out[2] / sum_scale - 1.0;
    (out, clipped)
}

/// The pipeline stage's description.
pub fn describe(d: &DetectorRange) -> String {
    format!(
        "inputs ±{} (signal units), sum = {} · power · (1 + Sz), floor {}, power {}",
        d.range, d.sum_scale, d.sum_floor, d.power
    )
}

/// The input range the simulated QPD reports with the effect on.
pub fn input_range(d: &DetectorRange) -> InputRange {
    InputRange::new(d.range, "").with_sum(
        (d.sum_floor > 0.0).then_some(d.sum_floor),
        1.0 / d.sum_scale,
        d.sum_scale,
    )
}

/// The mean of clamp(X, −r, r) for X ~ N(m, s²) and the probability that X lies at or beyond
/// ±r. s = 0: the clamp of m, and 1 or 0.
pub fn clipped_normal(m: f64, s: f64, r: f64) -> (f64, f64) {
    if s <= 0.0 || !s.is_finite() {
        let at = m.abs() >= r;
        return (m.clamp(-r, r), if at { 1.0 } else { 0.0 });
    }
    let a = (-r - m) / s;
    let b = (r - m) / s;
    let (pa, pb) = (phi_cdf(a), phi_cdf(b));
    let upper = 1.0 - pb;
    let mean = r * upper - r * pa + m * (pb - pa) + s * (phi_pdf(a) - phi_pdf(b));
    (mean, pa + upper)
}

/// Standard normal density.
fn phi_pdf(x: f64) -> f64 {
    (-0.5 * x * x).exp() / (2.0 * std::f64::consts::PI).sqrt()
}

/// Standard normal distribution function, Φ(x) = erfc(−x/√2)/2.
fn phi_cdf(x: f64) -> f64 {
    0.5 * erfc(-x / std::f64::consts::SQRT_2)
}

/// The complementary error function by the Chebyshev fit of Numerical Recipes (2nd ed., §6.2,
/// `erfcc`): fractional error below 1.2·10⁻⁷ everywhere.
fn erfc(x: f64) -> f64 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let ans = t
        * (-z * z - 1.265_512_23
            + t * (1.000_023_68
                + t * (0.374_091_96
                    + t * (0.096_784_18
                        + t * (-0.186_288_06
                            + t * (0.278_868_07
                                + t * (-1.135_203_98
                                    + t * (1.488_515_87
                                        + t * (-0.822_152_23 + t * 0.170_872_77)))))))))
            .exp();
    if x >= 0.0 {
        ans
    } else {
        2.0 - ans
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn erfc_matches_known_values() {
        // erfc(0) = 1, erfc(1) = 0.157299207050285, erfc(−1) = 1.842700792949715
        assert!((erfc(0.0) - 1.0).abs() < 1e-7);
        assert!((erfc(1.0) - 0.157_299_207_050_285).abs() < 2e-8);
        assert!((erfc(-1.0) - 1.842_700_792_949_715).abs() < 2e-8);
        // Φ(1.959964) = 0.975
        assert!((phi_cdf(1.959_964) - 0.975).abs() < 1e-6);
    }

    #[test]
    fn the_clipped_normal_has_its_limits() {
        // far inside: the mean itself, nothing clipped
        let (m, f) = clipped_normal(0.1, 0.01, 1.0);
        assert!((m - 0.1).abs() < 1e-12 && f < 1e-12);
        // centred on the rail: half the samples clip, the mean drops by s·φ(0) = s/√(2π)
        let (m, f) = clipped_normal(1.0, 0.1, 1.0);
        assert!((f - 0.5).abs() < 1e-7, "{f}");
        assert!((m - (1.0 - 0.1 / (2.0 * std::f64::consts::PI).sqrt())).abs() < 1e-7);
        // no noise: the clamp
        assert_eq!(clipped_normal(-3.0, 0.0, 1.0), (-1.0, 1.0));
    }

    #[test]
    fn power_and_sum_scale_reach_the_inputs() {
        let d = DetectorRange {
            range: 0.2,
            sum_scale: 0.1,
            sum_floor: 0.01,
            power: 0.5,
        };
        // Sx 0.6 → input 0.3, clipped at 0.2; Sy 0.1 → 0.05; sum 0.1·0.5·1 = 0.05 → Sz −0.5
        let (v, c) = apply(&d, [0.6, 0.1, 0.0], [0.0; 3], 100);
        assert_eq!(c, [100, 0, 0]);
        assert!((v[0] - 0.2).abs() < 1e-12 && (v[1] - 0.05).abs() < 1e-12);
        assert!((v[2] + 0.5).abs() < 1e-12, "{}", v[2]);
        let r = input_range(&d);
        // the sum input 0.05 is above the floor 0.01; laser off (Sz = −1) is dark
        assert!(!r.is_dark(v[2]) && r.is_dark(-1.0));
    }
}
