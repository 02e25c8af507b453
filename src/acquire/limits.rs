//! Soft limits and the pre-flight check: every position a plan (or a single move) would
//! command is checked before the first move; a plan that leaves the limits is refused whole.
//!
//! Config (`bfpscope.toml`):
//!
//! ```toml
//! [safety]
//! soft_limits = { x = [-40.0, 40.0], y = [-40.0, 40.0], z = [-5.0, 5.0] }   # µm
//! max_step_um = 10.0     # largest pixel pitch a scan may use (catches nm/µm mix-ups)
//! ```
//!
//! The limits in force are the config's intersected with the travel range the stage reports.

use super::plan::{Axis, Plan, Point};
use crate::instrument::Pos;
use serde::{Deserialize, Serialize};

/// Default largest pixel pitch of a scan (µm).
pub const DEFAULT_MAX_STEP_UM: f64 = 10.0;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SoftLimits {
    /// (min, max) per axis x, y, z, µm.
    pub range: [(f64, f64); 3],
    /// Largest pixel pitch along any scanned axis, µm.
    pub max_step_um: f64,
}

impl Default for SoftLimits {
    /// No soft limits of their own: the stage's travel range applies.
    fn default() -> Self {
        Self {
            range: [(f64::NEG_INFINITY, f64::INFINITY); 3],
            max_step_um: DEFAULT_MAX_STEP_UM,
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

impl SoftLimits {
    /// Read `[safety]` of a parsed config (`soft_limits = { x = [min, max], ... }`,
    /// `max_step_um`); absent: defaults. The instrument config (`instrument::config`) shares
    /// this section and validates the rest of it.
    pub fn from_toml(config: &toml::Value) -> Result<SoftLimits, String> {
        let mut l = SoftLimits::default();
        let Some(t) = config.get("safety") else {
            // The instrument config's `[limits]` table (x/y/z = [min, max] µm, max_step_um),
            // as written by `instrument::config` and docs/hardware.md.
            if let Some(t) = config.get("limits").and_then(|t| t.as_table()) {
                let num =
                    |x: &toml::Value| x.as_float().or_else(|| x.as_integer().map(|i| i as f64));
                for (i, ax) in ["x", "y", "z"].iter().enumerate() {
                    if let Some(a) = t.get(*ax).and_then(|v| v.as_array()) {
                        match (a.first().and_then(num), a.get(1).and_then(num)) {
                            (Some(lo), Some(hi)) if lo < hi => l.range[i] = (lo, hi),
                            _ => {
                                return Err(format!(
                                    "config: limits.{ax} must be [min, max] µm with min < max"
                                ))
                            }
                        }
                    }
                }
                if let Some(v) = t.get("max_step_um").and_then(num) {
                    l.max_step_um = v;
                }
            }
            return Ok(l);
        };
        let t = t.as_table().ok_or("config: [safety] must be a table")?;
        let num = |x: &toml::Value| x.as_float().or_else(|| x.as_integer().map(|i| i as f64));
        for (k, v) in t {
            match k.as_str() {
                "soft_limits" => {
                    let st = v.as_table().ok_or_else(|| {
                        format!("config: safety.soft_limits must be a table {{ x = [min, max], ... }} (µm), got {v}")
                    })?;
                    for (ak, av) in st {
                        let a = Axis::parse(ak).ok_or_else(|| {
                            format!("config: unknown axis safety.soft_limits.{ak} (allowed: x, y, z)")
                        })?;
                        let arr = av.as_array().filter(|a| a.len() == 2);
                        let pair = arr.and_then(|a| Some((num(&a[0])?, num(&a[1])?)));
                        match pair {
                            Some((lo, hi)) if lo.is_finite() && hi.is_finite() && lo < hi => {
                                l.range[a.index()] = (lo, hi)
                            }
                            _ => {
                                return Err(format!(
                                    "config: safety.soft_limits.{ak} = {av} must be [min, max], two finite numbers with min < max (µm)"
                                ))
                            }
                        }
                    }
                }
                "max_step_um" => match num(v) {
                    Some(s) if s > 0.0 && s.is_finite() => l.max_step_um = s,
                    _ => {
                        return Err(format!(
                            "config: safety.max_step_um = {v} must be a positive number (µm)"
                        ))
                    }
                },
                "max_speed_um_s" => {} // the drivers' business
                _ => {
                    return Err(format!(
                        "config: unknown key safety.{k} (allowed: soft_limits, max_step_um, max_speed_um_s)"
                    ))
                }
            }
        }
        Ok(l)
    }

    /// These limits narrowed to the stage's travel range.
    pub fn within_travel(&self, travel: [(f64, f64); 3]) -> SoftLimits {
        let mut l = *self;
        for (r, t) in l.range.iter_mut().zip(travel) {
            *r = (r.0.max(t.0), r.1.min(t.1));
        }
        l
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

    /// Describe the limits in force: `x [-50, 50] µm, y [...], z [...]`.
    pub fn describe(&self) -> String {
        Axis::ALL
            .iter()
            .map(|a| {
                let (lo, hi) = self.range[a.index()];
                format!("{a} [{}, {}] µm", fmt_um(lo), fmt_um(hi))
            })
            .collect::<Vec<_>>()
            .join(", ")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::acquire::plan::Sweep;

    #[test]
    fn config_limits_parse_and_refuse_with_axis_value_and_limit() {
        let cfg: toml::Value = toml::from_str(
            "[safety]\nsoft_limits = { x = [-5, 5], z = [-1.0, 1.0] }\nmax_step_um = 0.5",
        )
        .unwrap();
        let l = SoftLimits::from_toml(&cfg).unwrap();
        assert_eq!(l.range[0], (-5.0, 5.0));
        assert_eq!(l.max_step_um, 0.5);
        let e = l.check([6.0, 0.0, 0.0]).unwrap_err();
        assert_eq!(e.0, "x = 6 µm is above the soft limit x ≤ 5 µm");
        let plan = Plan::line(
            "ascan",
            Sweep::new("ascan", Axis::Z, 0.0, 1.5, 4, "n").unwrap(),
            0.0,
            false,
        )
        .unwrap();
        let e = l.preflight(&plan, [0.0; 3]).unwrap_err();
        assert!(
            e.0.contains("point 4 of 4: z = 1.5 µm is above the soft limit z ≤ 1 µm"),
            "{e}"
        );
        let coarse = Plan::line(
            "ascan",
            Sweep::new("ascan", Axis::X, 0.0, 4.0, 3, "n").unwrap(),
            0.0,
            false,
        )
        .unwrap();
        let e = l.preflight(&coarse, [0.0; 3]).unwrap_err();
        assert!(
            e.0.contains("step along x = 2 µm exceeds max_step_um = 0.5 µm"),
            "{e}"
        );
    }

    #[test]
    fn bad_config_is_an_error_naming_the_key() {
        let cfg: toml::Value = toml::from_str("[safety]\nsoft_limits = { x = [5, -5] }").unwrap();
        let e = SoftLimits::from_toml(&cfg).unwrap_err();
        assert!(e.contains("safety.soft_limits.x"), "{e}");
        let cfg: toml::Value = toml::from_str("[safety]\nsoft_limits = { w = [0, 1] }").unwrap();
        let e = SoftLimits::from_toml(&cfg).unwrap_err();
        assert!(e.contains("unknown axis safety.soft_limits.w"), "{e}");
    }
}
