//! Soft limits, the step-size rule and the speed limit: every position a plan (or a single
//! move) would command is checked before the first move; a plan that breaks a rule is refused
//! whole, with nothing sent to the stage. The rules hold for every backend (mock, simulator,
//! serial drivers, emulators): they live here, not in the drivers.
//!
//! Config (`bfpscope.toml`), the one place these are set:
//!
//! ```toml
//! [safety]
//! soft_limits = { x = [-40.0, 40.0], y = [-40.0, 40.0], z = [-5.0, 5.0] }   # µm
//! max_step_um = 10.0       # largest pixel pitch of a scan, µm (catches nm/µm mix-ups)
//! max_speed_um_s = 500.0   # fastest a scan may move the stage, µm/s (default: no limit)
//! ```
//!
//! - **Soft limits** are intersected with the travel range the stage reports.
//! - **`max_step_um`** is the *pixel pitch*: the spacing of neighbouring points along each
//!   scanned axis. It is not a limit on single moves: the move to a scan's first point, a
//!   raster's fly-back to the start of the next row and `mv` are positioning moves and may be
//!   longer (they are bounded by the soft limits, and fly-backs by the speed limit).
//! - **`max_speed_um_s`**: a scan grants each point `settle + dwell` seconds (the settle time
//!   after the move plus the QPD's integration time); moving from one point to the next over
//!   a distance d therefore implies the speed d / (settle + dwell). Every consecutive pair of
//!   points of a plan (steps, row changes, a raster's fly-back) must stay at or below the
//!   limit. The time the controller itself needs to reach the target only makes the real
//!   speed lower, so the rule is conservative. Positioning moves (`mv`, the move to the first
//!   point, the return to the start) run at the controller's own velocity setting.
//!
//! The legacy `[limits]` table (x, y, z, max_step_um) and `[stage] max_speed_um_s` are refused
//! with a message giving the `[safety]` equivalent (`instrument::config`).

use super::plan::{Axis, Plan, Point};
use crate::instrument::Pos;
use serde::{Deserialize, Serialize};

/// Default largest pixel pitch of a scan (µm).
pub const DEFAULT_MAX_STEP_UM: f64 = 10.0;

/// `[safety] soft_limits`: `[min, max]` µm per axis; a missing axis is limited by the stage's
/// travel range only.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct AxisRanges {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub x: Option<[f64; 2]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub y: Option<[f64; 2]>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub z: Option<[f64; 2]>,
}

impl AxisRanges {
    pub fn get(&self, axis: usize) -> Option<[f64; 2]> {
        [self.x, self.y, self.z].get(axis).copied().flatten()
    }
}

/// `[safety]` as written in `bfpscope.toml` (parsed with the rest of the file by
/// `instrument::config::Config`; [`SafetyConfig::limits`] turns it into the rules in force).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SafetyConfig {
    pub soft_limits: AxisRanges,
    /// Largest pixel pitch, µm (default [`DEFAULT_MAX_STEP_UM`]).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_step_um: Option<f64>,
    /// Fastest a scan may move the stage, µm/s (none: no limit).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_speed_um_s: Option<f64>,
}

impl SafetyConfig {
    /// Check the values. `Err((key path, message))`, e.g. `("safety.soft_limits.x", …)`.
    pub fn validate(&self) -> Result<(), (String, String)> {
        for (i, a) in Axis::ALL.iter().enumerate() {
            if let Some([lo, hi]) = self.soft_limits.get(i) {
                if !(lo.is_finite() && hi.is_finite() && lo < hi) {
                    return Err((
                        format!("safety.soft_limits.{a}"),
                        format!(
                            "[{lo}, {hi}]: need [min, max], two finite numbers with min < max (µm)"
                        ),
                    ));
                }
            }
        }
        for (key, v, unit) in [
            ("safety.max_step_um", self.max_step_um, "µm"),
            ("safety.max_speed_um_s", self.max_speed_um_s, "µm/s"),
        ] {
            if let Some(v) = v {
                if !(v.is_finite() && v > 0.0) {
                    return Err((
                        key.into(),
                        format!("{v}: must be a positive number ({unit})"),
                    ));
                }
            }
        }
        Ok(())
    }

    /// The rules in force before narrowing to a stage's travel range (call after `validate`).
    pub fn limits(&self) -> SoftLimits {
        let mut l = SoftLimits::default();
        for (i, r) in l.range.iter_mut().enumerate() {
            if let Some([lo, hi]) = self.soft_limits.get(i) {
                *r = (lo, hi);
            }
        }
        if let Some(s) = self.max_step_um {
            l.max_step_um = s;
        }
        l.max_speed_um_s = self.max_speed_um_s;
        l
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SoftLimits {
    /// (min, max) per axis x, y, z, µm.
    pub range: [(f64, f64); 3],
    /// Largest pixel pitch along any scanned axis, µm.
    pub max_step_um: f64,
    /// Fastest a scan may move the stage between consecutive points, µm/s (none: no limit).
    pub max_speed_um_s: Option<f64>,
}

impl Default for SoftLimits {
    /// No soft limits of their own: the stage's travel range applies; no speed limit.
    fn default() -> Self {
        Self {
            range: [(f64::NEG_INFINITY, f64::INFINITY); 3],
            max_step_um: DEFAULT_MAX_STEP_UM,
            max_speed_um_s: None,
        }
    }
}

/// A refused plan or move. Nothing has been moved when this is returned.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct LimitError(pub String);

fn fmt_um(v: f64) -> String {
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".into()
    } else {
        s.into()
    }
}

/// A computed value with 4 significant digits (`502.5`, `1.005`, `0.0125`).
fn fmt_sig(v: f64) -> String {
    if v == 0.0 || !v.is_finite() {
        return format!("{v}");
    }
    let decimals = (3 - v.abs().log10().floor() as i32).max(0) as usize;
    let s = format!("{v:.decimals$}");
    if s.contains('.') {
        s.trim_end_matches('0').trim_end_matches('.').to_string()
    } else {
        s
    }
}

/// Seconds (`0.006`, `1.500e-5`).
fn fmt_s(v: f64) -> String {
    if v != 0.0 && (v.abs() < 1e-3 || v.abs() >= 1e4) {
        format!("{v:.3e}")
    } else {
        fmt_um(v)
    }
}

/// Soft limits and the stage's travel range cannot be combined on `axis`.
#[derive(Debug, Clone, PartialEq)]
pub struct TravelError {
    pub axis: &'static str,
    pub message: String,
}

impl std::fmt::Display for TravelError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.message)
    }
}

impl SoftLimits {
    /// These limits ∩ the stage's travel range, per axis (step and speed limits kept): the one
    /// intersection, used at connect, before every move and every scan. An axis without soft
    /// limits gets the travel range. Errors (naming the axis and both ranges) when the two do
    /// not overlap or the travel range reported by the controller is not a range.
    pub fn within_travel(&self, travel: [(f64, f64); 3]) -> Result<SoftLimits, TravelError> {
        let mut out = *self;
        for (i, axis) in ["x", "y", "z"].iter().enumerate() {
            let (tlo, thi) = travel[i];
            if !(tlo.is_finite() && thi.is_finite() && tlo < thi) {
                return Err(TravelError {
                    axis,
                    message: format!(
                        "the stage reports a travel range [{tlo}, {thi}] µm for {axis}, which is not a range"
                    ),
                });
            }
            let (lo, hi) = self.range[i];
            let (a, b) = (lo.max(tlo), hi.min(thi));
            if a >= b {
                return Err(TravelError {
                    axis,
                    message: format!(
                        "safety.soft_limits.{axis} = [{lo}, {hi}] µm does not overlap the stage's travel range [{tlo}, {thi}] µm"
                    ),
                });
            }
            out.range[i] = (a, b);
        }
        Ok(out)
    }

    /// Check one absolute position; the message names the axis, the value and the limit.
    pub fn check(&self, p: Pos) -> Result<(), LimitError> {
        for a in Axis::ALL {
            let v = p[a.index()];
            let (lo, hi) = self.range[a.index()];
            if !v.is_finite() {
                return Err(LimitError(format!("{a} = {v} is not a finite position")));
            }
            if v < lo {
                return Err(LimitError(format!(
                    "{a} = {} µm is below the soft limit {a} ≥ {} µm",
                    fmt_um(v),
                    fmt_um(lo)
                )));
            }
            if v > hi {
                return Err(LimitError(format!(
                    "{a} = {} µm is above the soft limit {a} ≤ {} µm",
                    fmt_um(v),
                    fmt_um(hi)
                )));
            }
        }
        Ok(())
    }

    /// Pre-flight of a whole plan: every point, the fixed-axis position and the pixel pitch.
    /// Returns the points (visiting order) when the plan may run.
    pub fn preflight(&self, plan: &Plan, start: Pos) -> Result<Vec<Point>, LimitError> {
        let who = &plan.kind;
        for s in std::iter::once(plan.fast).chain(plan.slow) {
            if s.step() > self.max_step_um {
                return Err(LimitError(format!(
                    "{who} refused before any move: step along {} = {} µm exceeds max_step_um = {} µm \
                     (raise [safety] max_step_um in bfpscope.toml if this is intended)",
                    s.axis,
                    fmt_um(s.step()),
                    fmt_um(self.max_step_um)
                )));
            }
        }
        let pts = plan.points(start);
        let n = pts.len();
        self.check(plan.base(start)).map_err(|e| {
            LimitError(format!("{who} refused before any move: start of scan: {e}"))
        })?;
        for (i, p) in pts.iter().enumerate() {
            self.check(p.target).map_err(|e| {
                LimitError(format!(
                    "{who} refused before any move: point {} of {n}: {e}",
                    i + 1
                ))
            })?;
        }
        Ok(pts)
    }

    /// The speed rule (see the module documentation): each point of `points` (visiting
    /// order) is granted `settle_s + dwell_s`; the distance between consecutive points over
    /// that time must not exceed `max_speed_um_s`. Returns the highest implied speed, µm/s
    /// (0 for a single point).
    pub fn check_speed(
        &self,
        kind: &str,
        points: &[Point],
        settle_s: f64,
        dwell_s: f64,
    ) -> Result<f64, LimitError> {
        let t = settle_s + dwell_s;
        let n = points.len();
        let mut fastest = 0.0f64;
        for (i, w) in points.windows(2).enumerate() {
            let d = dist(w[0].target, w[1].target);
            let v = if d == 0.0 { 0.0 } else { d / t };
            fastest = fastest.max(v);
            let Some(max) = self.max_speed_um_s else {
                continue;
            };
            // within rounding of the limit is at the limit
            if v > max * (1.0 + 1e-9) || v.is_nan() {
                let hint = if w[0].row != w[1].row && d > 0.0 {
                    "; this is a row change: a snake scan (snake: true) avoids the fly-back"
                } else {
                    ""
                };
                return Err(LimitError(format!(
                    "{kind} refused before any move: from point {} to point {} of {n} the stage moves {} µm \
                     in settle {} s + dwell {} s = {} s per point: {} µm/s exceeds max_speed_um_s = {} µm/s \
                     ([safety] in bfpscope.toml; use a longer dwell or settle, or smaller steps){hint}",
                    i + 1,
                    i + 2,
                    fmt_sig(d),
                    fmt_s(settle_s),
                    fmt_s(dwell_s),
                    fmt_s(t),
                    fmt_sig(v),
                    fmt_um(max),
                )));
            }
        }
        Ok(fastest)
    }

    /// Describe the rules in force: `x [-50, 50] µm, y [...], z [...]; max step 10 µm; max
    /// speed 500 µm/s` (or `no speed limit`).
    pub fn describe(&self) -> String {
        let axes = Axis::ALL
            .iter()
            .map(|a| {
                let (lo, hi) = self.range[a.index()];
                format!("{a} [{}, {}] µm", fmt_um(lo), fmt_um(hi))
            })
            .collect::<Vec<_>>()
            .join(", ");
        let speed = match self.max_speed_um_s {
            Some(v) => format!("max speed {} µm/s", fmt_um(v)),
            None => "no speed limit".into(),
        };
        format!("{axes}; max step {} µm; {speed}", fmt_um(self.max_step_um))
    }
}

/// Euclidean distance between two positions, µm.
fn dist(a: Pos, b: Pos) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquire::plan::Sweep;

    /// `ascan axis from to` with `n` points and no dwell (absolute).
    fn ascan(axis: Axis, from: f64, to: f64, n: i64) -> Plan {
        let sweep = Sweep::new("ascan", axis, from, to, n, "n").unwrap();
        Plan::line("ascan", sweep, 0.0, false).unwrap()
    }

    /// The pre-flight of `plan` from the origin is refused, saying `says`.
    fn assert_refused(l: &SoftLimits, plan: &Plan, says: &str) {
        let e = l.preflight(plan, [0.0; 3]).unwrap_err();
        assert!(e.0.contains(says), "{e}");
    }

    #[test]
    fn config_limits_parse_and_refuse_with_axis_value_and_limit() {
        let mut l = SoftLimits::default();
        l.range[0] = (-5.0, 5.0);
        l.range[2] = (-1.0, 1.0);
        l.max_step_um = 0.5;
        let e = l.check([6.0, 0.0, 0.0]).unwrap_err();
        assert_eq!(e.0, "x = 6 µm is above the soft limit x ≤ 5 µm");
        let too_far = ascan(Axis::Z, 0.0, 1.5, 4);
        assert_refused(
            &l,
            &too_far,
            "point 4 of 4: z = 1.5 µm is above the soft limit z ≤ 1 µm",
        );
        let coarse = ascan(Axis::X, 0.0, 4.0, 3);
        assert_refused(
            &l,
            &coarse,
            "step along x = 2 µm exceeds max_step_um = 0.5 µm",
        );
    }

    #[test]
    fn soft_limits_intersect_travel_once_and_refuse_no_overlap() {
        let mut soft = SoftLimits::default();
        soft.range[0] = (-10.0, 50.0);
        soft.range[1] = (20.0, 30.0);
        soft.max_speed_um_s = Some(50.0);
        let travel = [(0.0, 100.0), (0.0, 100.0), (0.0, 20.0)];
        let l = soft.within_travel(travel).unwrap();
        assert_eq!(l.range, [(0.0, 50.0), (20.0, 30.0), (0.0, 20.0)]);
        assert_eq!((l.max_step_um, l.max_speed_um_s), (10.0, Some(50.0)));
        // no overlap is an error, never an inverted range
        let mut soft = SoftLimits::default();
        soft.range[2] = (25.0, 30.0);
        let e = soft.within_travel(travel).unwrap_err();
        assert_eq!(e.axis, "z");
        assert_eq!(
            e.message,
            "safety.soft_limits.z = [25, 30] µm does not overlap the stage's travel range [0, 20] µm"
        );
        let bad = [(0.0, 1.0), (1.0, 1.0), (0.0, 1.0)];
        assert_eq!(
            SoftLimits::default().within_travel(bad).unwrap_err().axis,
            "y"
        );
        let nan = [(0.0, f64::NAN), (0.0, 1.0), (0.0, 1.0)];
        let e = SoftLimits::default().within_travel(nan).unwrap_err();
        assert_eq!(e.axis, "x");
        assert!(
            e.message
                .contains("[0, NaN] µm for x, which is not a range"),
            "{}",
            e.message
        );
    }

    #[test]
    fn speed_rule_is_distance_over_settle_plus_dwell() {
        let l = SoftLimits {
            max_speed_um_s: Some(50.0),
            ..SoftLimits::default()
        };
        let plan = ascan(Axis::Z, 0.0, 0.3, 4);
        let pts = plan.points([0.0; 3]);
        // 0.1 µm per point in 1 ms + 1 ms: 50 µm/s, at the limit
        let v = l.check_speed("ascan", &pts, 0.001, 0.001).unwrap();
        assert!((v - 50.0).abs() < 1e-9, "{v}");
        // in 1 ms + 0.5 ms: 66.67 µm/s
        let e = l.check_speed("ascan", &pts, 0.001, 0.0005).unwrap_err();
        assert!(
            e.0.contains("moves 0.1 µm in settle 0.001 s + dwell 5.000e-4 s = 0.0015 s per point: 66.67 µm/s exceeds max_speed_um_s = 50 µm/s"),
            "{e}"
        );
        // no limit: the fastest speed is still reported; one point has no speed
        assert!(
            (SoftLimits::default()
                .check_speed("a", &pts, 0.0, 0.001)
                .unwrap()
                - 100.0)
                .abs()
                < 1e-9
        );
        assert_eq!(l.check_speed("a", &pts[..1], 0.0, 0.0).unwrap(), 0.0);
        assert_eq!(fmt_sig(502.49378), "502.5");
        assert_eq!(fmt_sig(1.00498756), "1.005");
        assert_eq!(fmt_sig(2500.0), "2500");
        assert!(SoftLimits::default()
            .describe()
            .ends_with("; max step 10 µm; no speed limit"));
        assert!(l.describe().ends_with("max speed 50 µm/s"));
    }
}
