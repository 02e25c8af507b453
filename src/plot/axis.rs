//! A plotters coordinate for one axis, linear or logarithmic, with our own tick choice and
//! labels (plotters' own log axis gives no ticks at all on ranges narrower than a decade).

use crate::data::image::fmt_sig;
use plotters::coord::ranged1d::{
    KeyPointHint, KeyPointWeight, NoDefaultFormatting, Ranged, ValueFormatter,
};
use std::ops::Range;

#[derive(Debug, Clone)]
pub struct AxisCoord {
    lo: f64,
    hi: f64,
    log: bool,
    ticks: Vec<f64>,
    minor: Vec<f64>,
    /// How tick labels are written.
    style: LabelStyle,
}

#[derive(Debug, Clone, Copy)]
enum LabelStyle {
    /// Fixed decimals.
    Fixed(usize),
    /// Exponent form with this many mantissa decimals.
    Sci(usize),
    /// `10ⁿ` for decades.
    Power,
    /// `%g`-like with 4 significant digits.
    General,
}

impl AxisCoord {
    /// Linear axis over `[lo, hi]` (lo < hi, finite) with about `n` ticks.
    pub fn linear(lo: f64, hi: f64, n: usize) -> AxisCoord {
        let (ticks, step) = nice_ticks(lo, hi, n);
        let minor = nice_ticks(lo, hi, n * 5).0;
        let maxabs = lo.abs().max(hi.abs());
        let e_max = maxabs.log10().floor() as i32;
        let e_step = step.log10().floor() as i32;
        let style = if !(1e-3..1e5).contains(&maxabs) {
            LabelStyle::Sci((e_max - e_step).max(0) as usize)
        } else {
            LabelStyle::Fixed((-e_step).max(0) as usize)
        };
        AxisCoord {
            lo,
            hi,
            log: false,
            ticks,
            minor,
            style,
        }
    }

    /// Logarithmic (base 10) axis over `[lo, hi]` (0 < lo < hi, finite).
    pub fn log(lo: f64, hi: f64) -> AxisCoord {
        let (l0, l1) = (lo.log10(), hi.log10());
        let first = l0.ceil() as i32;
        let last = l1.floor() as i32;
        let decades: Vec<i32> = (first..=last).collect();
        let mut minor = Vec::new();
        for k in (l0.floor() as i32)..=(l1.ceil() as i32) {
            for m in 1..10 {
                let v = f64::from(m) * 10f64.powi(k);
                if v >= lo && v <= hi {
                    minor.push(v);
                }
            }
        }
        if decades.len() >= 2 {
            let every = decades.len().div_ceil(8).max(1);
            let ticks: Vec<f64> = decades
                .iter()
                .filter(|k| ((**k - first) as usize).is_multiple_of(every))
                .map(|&k| 10f64.powi(k))
                .collect();
            let plain = ticks.iter().all(|&t| (1e-3..=1e4).contains(&t));
            if every > 1 {
                minor = decades.iter().map(|&k| 10f64.powi(k)).collect();
            }
            let style = if plain {
                LabelStyle::General
            } else {
                LabelStyle::Power
            };
            return AxisCoord {
                lo,
                hi,
                log: true,
                ticks,
                minor,
                style,
            };
        }
        // Less than two decades: 1-2-5 ticks, else plain nice ticks.
        let mut ticks: Vec<f64> = Vec::new();
        for k in (l0.floor() as i32)..=(l1.ceil() as i32) {
            for m in [1.0, 2.0, 5.0] {
                let v = m * 10f64.powi(k);
                if v >= lo * (1.0 - 1e-12) && v <= hi * (1.0 + 1e-12) {
                    ticks.push(v);
                }
            }
        }
        if ticks.len() < 3 {
            // finer and finer nice ticks until there are at least four
            for n in 5..=12 {
                ticks = nice_ticks(lo, hi, n).0;
                if ticks.len() >= 4 {
                    break;
                }
            }
        }
        AxisCoord {
            lo,
            hi,
            log: true,
            ticks,
            minor,
            style: LabelStyle::General,
        }
    }

    /// Position of `v` along the axis as a fraction of its length (0 at `lo`, 1 at `hi`).
    pub fn fraction(&self, v: f64) -> f64 {
        if self.log {
            if v <= 0.0 {
                return -10.0;
            }
            (v.log10() - self.lo.log10()) / (self.hi.log10() - self.lo.log10())
        } else {
            (v - self.lo) / (self.hi - self.lo)
        }
    }

    pub fn label(&self, v: f64) -> String {
        match self.style {
            LabelStyle::Fixed(d) => {
                let s = format!("{:.*}", d, v);
                // avoid "-0.00"
                if s.trim_start_matches('-')
                    .chars()
                    .all(|c| c == '0' || c == '.')
                {
                    s.trim_start_matches('-').to_string()
                } else {
                    s
                }
            }
            LabelStyle::Sci(d) => {
                if v == 0.0 {
                    "0".into()
                } else {
                    format!("{:.*e}", d, v)
                }
            }
            LabelStyle::Power => {
                let k = v.log10().round() as i32;
                format!("10{}", superscript(k))
            }
            LabelStyle::General => fmt_sig(v, 4),
        }
    }
}

fn superscript(k: i32) -> String {
    k.to_string()
        .chars()
        .map(|c| match c {
            '-' => '⁻',
            '0' => '⁰',
            '1' => '¹',
            '2' => '²',
            '3' => '³',
            '4' => '⁴',
            '5' => '⁵',
            '6' => '⁶',
            '7' => '⁷',
            '8' => '⁸',
            '9' => '⁹',
            c => c,
        })
        .collect()
}

/// About `n` ticks at multiples of 1, 2 or 5 × 10^k inside `[lo, hi]`; also returns the step.
pub fn nice_ticks(lo: f64, hi: f64, n: usize) -> (Vec<f64>, f64) {
    let span = hi - lo;
    if span.is_nan() || span <= 0.0 || !span.is_finite() {
        return (vec![lo], 1.0);
    }
    let raw = span / n.max(1) as f64;
    let mag = 10f64.powf(raw.log10().floor());
    let norm = raw / mag;
    // the 1-2-5 multiplier nearest to the raw step (on a log scale)
    let mult = [1.0f64, 2.0, 5.0, 10.0]
        .into_iter()
        .min_by(|a, b| (a / norm).ln().abs().total_cmp(&(b / norm).ln().abs()))
        .unwrap_or(1.0);
    let step = mult * mag;
    let first = (lo / step - 1e-9).ceil() as i64;
    let last = (hi / step + 1e-9).floor() as i64;
    let ticks = (first..=last)
        .map(|k| {
            let v = k as f64 * step;
            if v.abs() < step * 1e-9 {
                0.0
            } else {
                v
            }
        })
        .collect();
    (ticks, step)
}

impl Ranged for AxisCoord {
    type FormatOption = NoDefaultFormatting;
    type ValueType = f64;

    fn map(&self, value: &f64, limit: (i32, i32)) -> i32 {
        let t = self.fraction(*value);
        let t = if t.is_finite() {
            t.clamp(-10.0, 10.0)
        } else {
            -10.0
        };
        limit.0 + (t * f64::from(limit.1 - limit.0)).round() as i32
    }

    fn key_points<Hint: KeyPointHint>(&self, hint: Hint) -> Vec<f64> {
        match hint.weight() {
            KeyPointWeight::Bold => self.ticks.clone(),
            KeyPointWeight::Any => self.minor.clone(),
        }
    }

    fn range(&self) -> Range<f64> {
        self.lo..self.hi
    }
}

impl ValueFormatter<f64> for AxisCoord {
    fn format_ext(&self, value: &f64) -> String {
        self.label(*value)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nice_linear_ticks() {
        let (t, s) = nice_ticks(-1.02, 1.02, 6);
        assert_eq!(s, 0.5);
        assert_eq!(t, vec![-1.0, -0.5, 0.0, 0.5, 1.0]);
        let a = AxisCoord::linear(-1.02, 1.02, 6);
        assert_eq!(a.label(-0.5), "-0.5");
        assert_eq!(a.label(0.0), "0.0");
        let a = AxisCoord::linear(0.0, 3e-4, 5);
        assert_eq!(a.label(1e-4), "1.0e-4");
        assert_eq!(a.label(1.5e-4), "1.5e-4");
    }

    #[test]
    fn log_ticks_wide_and_narrow() {
        let a = AxisCoord::log(0.5, 2000.0);
        assert_eq!(a.ticks, vec![1.0, 10.0, 100.0, 1000.0]);
        assert_eq!(a.label(100.0), "100");
        let a = AxisCoord::log(1e-9, 1e-3);
        assert_eq!(a.label(1e-6), "10⁻⁶");
        // less than one decade still gets ticks
        let a = AxisCoord::log(2.5, 8.0);
        assert!(a.ticks.len() >= 3, "{:?}", a.ticks);
        assert!(a.ticks.iter().all(|&t| (2.5..=8.0).contains(&t)));
    }
}
