//! Scan plans: pure data describing which points to visit, how long to dwell and whether the
//! plan is relative to the start position. Plans never touch a device; `engine` executes them.

use crate::instrument::Pos;
use serde::{Deserialize, Serialize};

/// Default dwell per point (s) of the scan primitives: 10 ms, the knee of the dwell knob in
/// docs/accuracy.md (the cheapest dwell at which one 64×64 scan of 50 nm pixels reaches the
/// paper's 950 kDa mass resolution for a 110 nm bead at the simulator's paper noise, Sec. 3.2).
/// The paper itself stops at least 0.1 s per position (suppl. S1); quick navigation scans pass
/// `dwell: 0.001` explicitly.
pub const DEFAULT_DWELL_S: f64 = 1e-2;

/// Largest number of points along one axis of a plan.
pub const MAX_POINTS_PER_AXIS: usize = 4096;
/// Largest dwell time per point (s).
pub const MAX_DWELL_S: f64 = 60.0;

/// A stage axis.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Axis {
    X,
    Y,
    Z,
}

impl Axis {
    pub const ALL: [Axis; 3] = [Axis::X, Axis::Y, Axis::Z];
    pub fn index(self) -> usize {
        match self {
            Axis::X => 0,
            Axis::Y => 1,
            Axis::Z => 2,
        }
    }
    pub fn name(self) -> &'static str {
        crate::instrument::AXES[self.index()]
    }
    pub fn parse(s: &str) -> Option<Axis> {
        match s.trim().to_ascii_lowercase().as_str() {
            "x" => Some(Axis::X),
            "y" => Some(Axis::Y),
            "z" => Some(Axis::Z),
            _ => None,
        }
    }
}

impl std::fmt::Display for Axis {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// A plan could not be built from the given arguments. The message names the binding, the
/// argument, its value and the allowed range.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{0}")]
pub struct PlanError(pub String);

/// One swept axis: `n` evenly spaced positions from `from` to `to` (µm, inclusive).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sweep {
    pub axis: Axis,
    pub from: f64,
    pub to: f64,
    pub n: usize,
}

impl Sweep {
    /// Validate: finite ends, `1 ≤ n ≤ 4096`. `who` is the binding name, `n_name` the name of
    /// the point-count argument as the user typed it (`nx`, `n`, ...).
    pub fn new(
        who: &str,
        axis: Axis,
        from: f64,
        to: f64,
        n: i64,
        n_name: &str,
    ) -> Result<Sweep, PlanError> {
        for (name, v) in [("from", from), ("to", to)] {
            if !v.is_finite() {
                return Err(PlanError(format!(
                    "{who}: {axis} {name} = {v} is not a finite position (µm)"
                )));
            }
        }
        if n < 1 || n as usize > MAX_POINTS_PER_AXIS {
            return Err(PlanError(format!(
                "{who}: {n_name} = {n} is out of range: 1 ≤ {n_name} ≤ {MAX_POINTS_PER_AXIS}"
            )));
        }
        if n == 1 && from != to {
            return Err(PlanError(format!(
                "{who}: {n_name} = 1 scans a single point, but the {axis} range [{from}, {to}] µm has two ends: give {n_name} ≥ 2 to scan the range, or the same position twice for one point"
            )));
        }
        if n > 1 && from == to {
            return Err(PlanError(format!(
                "{who}: the {axis} range [{from}, {to}] µm has no extent: its {n} points ({n_name} = {n}) would all be at {from} µm; give two different ends, or {n_name} = 1 for one point"
            )));
        }
        Ok(Sweep {
            axis,
            from,
            to,
            n: n as usize,
        })
    }
    /// The positions (µm), `from` first.
    pub fn values(&self) -> Vec<f64> {
        linspace(self.from, self.to, self.n)
    }
    /// Pixel pitch |to − from| / (n − 1) (0 for a single point), µm.
    pub fn step(&self) -> f64 {
        if self.n < 2 {
            0.0
        } else {
            (self.to - self.from).abs() / (self.n - 1) as f64
        }
    }
}

/// `n` evenly spaced values from `a` to `b` inclusive (`[a]` when `n == 1`).
pub fn linspace(a: f64, b: f64, n: usize) -> Vec<f64> {
    match n {
        0 => vec![],
        1 => vec![a],
        _ => (0..n)
            .map(|i| a + (b - a) * i as f64 / (n - 1) as f64)
            .collect(),
    }
}

/// A scan plan. Columns of the resulting images follow `fast`, rows follow `slow` (a line scan
/// has one row). With `rel`, every position (sweeps and `fixed`) is an offset from the stage
/// position when the scan starts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    /// The binding that built the plan (`scan_xy`, `dscan`, ...).
    pub kind: String,
    pub fast: Sweep,
    /// A second axis moved in step with `fast` (SPEC's `a2scan`/`d2scan`: point `i` of both
    /// sweeps together); line plans only. The image's columns follow `fast`.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub with: Option<Sweep>,
    pub slow: Option<Sweep>,
    /// Axes held at a fixed position during the scan (µm; offsets when `rel`).
    pub fixed: Vec<(Axis, f64)>,
    pub rel: bool,
    /// Alternate the direction of the fast axis on every other row (pixels are still stored
    /// in image order).
    pub snake: bool,
    /// Dwell (integration) time per point, s.
    pub dwell_s: f64,
    /// Move back to the start position at the end (always for relative plans).
    pub return_to_start: bool,
}

/// One point of a plan in visiting order: where it goes in the image and where the stage goes.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Point {
    pub row: usize,
    pub col: usize,
    pub target: Pos,
}

/// Validate a dwell time (s).
pub fn check_dwell(who: &str, dwell: f64) -> Result<f64, PlanError> {
    if dwell.is_finite() && (0.0..=MAX_DWELL_S).contains(&dwell) {
        Ok(dwell)
    } else {
        Err(PlanError(format!(
            "{who}: dwell = {dwell} is out of range: 0 ≤ dwell ≤ {MAX_DWELL_S} s"
        )))
    }
}

/// Refuse a plan whose two swept axes (`what`: "scan axes", "motors") are one and the same.
fn two_axes(kind: &str, what: &str, a: Axis, b: Axis) -> Result<(), PlanError> {
    if a == b {
        return Err(PlanError(format!(
            "{kind}: both {what} are {a}: pick two different axes"
        )));
    }
    Ok(())
}

impl Plan {
    /// A line scan along one axis.
    pub fn line(kind: &str, sweep: Sweep, dwell_s: f64, rel: bool) -> Result<Plan, PlanError> {
        Ok(Plan {
            kind: kind.into(),
            fast: sweep,
            with: None,
            slow: None,
            fixed: vec![],
            rel,
            snake: false,
            dwell_s: check_dwell(kind, dwell_s)?,
            return_to_start: rel,
        })
    }

    /// A 2-D raster (or snake) scan: `fast` along the columns, `slow` along the rows.
    pub fn grid(
        kind: &str,
        fast: Sweep,
        slow: Sweep,
        fixed: Vec<(Axis, f64)>,
        dwell_s: f64,
        rel: bool,
        snake: bool,
    ) -> Result<Plan, PlanError> {
        two_axes(kind, "scan axes", fast.axis, slow.axis)?;
        for (a, v) in &fixed {
            if *a == fast.axis || *a == slow.axis {
                return Err(PlanError(format!(
                    "{kind}: {a} is both scanned and held fixed"
                )));
            }
            if !v.is_finite() {
                return Err(PlanError(format!(
                    "{kind}: {a} = {v} is not a finite position (µm)"
                )));
            }
        }
        Ok(Plan {
            kind: kind.into(),
            fast,
            with: None,
            slow: Some(slow),
            fixed,
            rel,
            snake,
            dwell_s: check_dwell(kind, dwell_s)?,
            return_to_start: rel,
        })
    }

    /// A line scan moving two axes together (SPEC `a2scan`, `d2scan`): point `i` is at
    /// `first.values()[i]` on `first.axis` and `second.values()[i]` on `second.axis`.
    pub fn line2(
        kind: &str,
        first: Sweep,
        second: Sweep,
        dwell_s: f64,
        rel: bool,
    ) -> Result<Plan, PlanError> {
        two_axes(kind, "motors", first.axis, second.axis)?;
        if first.n != second.n {
            return Err(PlanError(format!(
                "{kind}: the two sweeps have {} and {} points: they must match",
                first.n, second.n
            )));
        }
        let mut p = Plan::line(kind, first, dwell_s, rel)?;
        p.with = Some(second);
        Ok(p)
    }

    pub fn rows(&self) -> usize {
        self.slow.map_or(1, |s| s.n)
    }
    pub fn cols(&self) -> usize {
        self.fast.n
    }
    pub fn n_points(&self) -> usize {
        self.rows() * self.cols()
    }

    /// Absolute position of the stage before the first point: `start` with the fixed axes set.
    pub fn base(&self, start: Pos) -> Pos {
        let mut p = start;
        for (a, v) in &self.fixed {
            p[a.index()] = if self.rel { start[a.index()] + v } else { *v };
        }
        p
    }

    /// Absolute column positions (µm).
    pub fn col_positions(&self, start: Pos) -> Vec<f64> {
        let off = if self.rel {
            start[self.fast.axis.index()]
        } else {
            0.0
        };
        self.fast.values().into_iter().map(|v| v + off).collect()
    }
    /// Absolute row positions (µm); for a line scan, the position of the row axis (see
    /// [`Plan::row_axis`]) at the start.
    pub fn row_positions(&self, start: Pos) -> Vec<f64> {
        match self.slow {
            Some(s) => {
                let off = if self.rel { start[s.axis.index()] } else { 0.0 };
                s.values().into_iter().map(|v| v + off).collect()
            }
            None => vec![self.base(start)[self.row_axis().index()]],
        }
    }
    /// The axis along the image rows (for a line scan: the next axis after the fast one that
    /// is not moved with it).
    pub fn row_axis(&self) -> Axis {
        match self.slow {
            Some(s) => s.axis,
            None => {
                let next = match self.fast.axis {
                    Axis::X => Axis::Y,
                    Axis::Y => Axis::X,
                    Axis::Z => Axis::X,
                };
                match self.with {
                    Some(w) if w.axis == next => Axis::ALL
                        .into_iter()
                        .find(|a| *a != self.fast.axis && *a != w.axis)
                        .unwrap_or(next),
                    _ => next,
                }
            }
        }
    }

    /// Every point in visiting order (snake rows reversed), with absolute targets.
    pub fn points(&self, start: Pos) -> Vec<Point> {
        let base = self.base(start);
        let cols = self.col_positions(start);
        let rows = self.slow.map(|_| self.row_positions(start));
        let with = self.with.map(|w| {
            let off = if self.rel { start[w.axis.index()] } else { 0.0 };
            (
                w.axis,
                w.values().into_iter().map(|v| v + off).collect::<Vec<_>>(),
            )
        });
        let mut out = Vec::with_capacity(self.n_points());
        for r in 0..self.rows() {
            let reverse = self.snake && r % 2 == 1;
            for k in 0..self.cols() {
                let c = if reverse { self.cols() - 1 - k } else { k };
                let mut t = base;
                t[self.fast.axis.index()] = cols[c];
                if let (Some(s), Some(rows)) = (self.slow, rows.as_ref()) {
                    t[s.axis.index()] = rows[r];
                }
                if let Some((a, v)) = &with {
                    t[a.index()] = v[c];
                }
                out.push(Point {
                    row: r,
                    col: c,
                    target: t,
                });
            }
        }
        out
    }

    /// Estimated instrument time (s): one settle + dwell per point, plus the return to start.
    pub fn eta_s(&self, settle_s: f64, samples_time_s: f64) -> f64 {
        let per_point = settle_s + samples_time_s;
        self.n_points() as f64 * per_point + if self.return_to_start { settle_s } else { 0.0 }
    }

    /// One-line description: `scan_xy 64×32 (x × y) snake rel, dwell 1 ms`.
    pub fn describe(&self) -> String {
        let mut s = match self.slow {
            Some(sl) => format!(
                "{} {}×{} ({} × {})",
                self.kind,
                self.cols(),
                self.rows(),
                self.fast.axis,
                sl.axis
            ),
            None => format!(
                "{} {} points along {}{}",
                self.kind,
                self.cols(),
                self.fast.axis,
                self.with
                    .map(|w| format!(" and {}", w.axis))
                    .unwrap_or_default()
            ),
        };
        if self.snake {
            s.push_str(" snake");
        }
        if self.rel {
            s.push_str(" relative");
        }
        s.push_str(&format!(", dwell {}", fmt_seconds(self.dwell_s)));
        s
    }
}

/// Human-readable duration: `850 µs`, `12 ms`, `3.4 s`, `2 min 5 s`, `1 h 3 min`.
pub fn fmt_seconds(s: f64) -> String {
    if !s.is_finite() {
        return format!("{s} s");
    }
    if s < 1e-3 {
        format!("{:.0} µs", s * 1e6)
    } else if s < 1.0 {
        format!("{:.0} ms", s * 1e3)
    } else if s < 60.0 {
        format!("{s:.1} s")
    } else if s < 3600.0 {
        format!("{} min {:.0} s", (s / 60.0).floor(), s % 60.0)
    } else {
        format!("{} h {:.0} min", (s / 3600.0).floor(), (s % 3600.0) / 60.0)
    }
}

#[cfg(test)]
mod tests {

    #[test]
    fn two_motor_line_moves_both_axes_together() {
        let x = Sweep::new("a2scan", Axis::X, 0.0, 1.0, 5, "points").unwrap();
        let z = Sweep::new("a2scan", Axis::Z, 2.0, 0.0, 5, "points").unwrap();
        let p = Plan::line2("d2scan", x, z, 0.001, true).unwrap();
        let pts = p.points([10.0, 20.0, 30.0]);
        assert_eq!(pts.len(), 5);
        assert_eq!(pts[0].target, [10.0, 20.0, 32.0]);
        assert_eq!(pts[2].target, [10.5, 20.0, 31.0]);
        assert_eq!(pts[4].target, [11.0, 20.0, 30.0]);
        assert_eq!((pts[4].row, pts[4].col), (0, 4));
        // the image rows are along y, the axis neither motor moves
        assert_eq!(p.row_axis(), Axis::Y);
        assert!(p
            .describe()
            .starts_with("d2scan 5 points along x and z relative"));
        let y = Sweep::new("a2scan", Axis::Y, 0.0, 1.0, 4, "points").unwrap();
        assert!(Plan::line2("a2scan", x, y, 0.001, false)
            .unwrap_err()
            .0
            .contains("5 and 4 points"));
        assert!(Plan::line2("a2scan", x, x, 0.001, false)
            .unwrap_err()
            .0
            .contains("both motors are x"));
    }

    use super::*;

    #[test]
    fn snake_visits_alternate_rows_backwards_but_stores_image_order() {
        let p = Plan::grid(
            "scan_xy",
            Sweep::new("t", Axis::X, 0.0, 2.0, 3, "nx").unwrap(),
            Sweep::new("t", Axis::Y, 0.0, 1.0, 2, "ny").unwrap(),
            vec![(Axis::Z, 0.5)],
            0.0,
            false,
            true,
        )
        .unwrap();
        let pts = p.points([9.0, 9.0, 9.0]);
        let cols: Vec<usize> = pts.iter().map(|p| p.col).collect();
        assert_eq!(cols, vec![0, 1, 2, 2, 1, 0]);
        assert_eq!(pts[3].target, [2.0, 1.0, 0.5]);
        assert_eq!(pts[5].target, [0.0, 1.0, 0.5]);
    }

    #[test]
    fn relative_plan_offsets_from_start() {
        let p = Plan::line(
            "dscan",
            Sweep::new("t", Axis::Y, -1.0, 1.0, 3, "n").unwrap(),
            0.01,
            true,
        )
        .unwrap();
        let pts = p.points([1.0, 2.0, 3.0]);
        assert_eq!(pts[0].target, [1.0, 1.0, 3.0]);
        assert_eq!(pts[2].target, [1.0, 3.0, 3.0]);
        assert!(p.return_to_start);
        assert_eq!(p.row_positions([1.0, 2.0, 3.0]), vec![1.0]);
    }

    #[test]
    fn bad_arguments_name_the_argument_value_and_range() {
        let e = Sweep::new("scan_xy", Axis::X, 0.0, 1.0, 0, "nx").unwrap_err();
        assert_eq!(e.0, "scan_xy: nx = 0 is out of range: 1 ≤ nx ≤ 4096");
        // one point over a range, many points over no range: refused, each in its words
        let e = Sweep::new("scan_xy", Axis::X, 0.0, 1.0, 1, "nx").unwrap_err();
        assert!(
            e.0.starts_with(
                "scan_xy: nx = 1 scans a single point, but the x range [0, 1] µm has two ends"
            ),
            "{}",
            e.0
        );
        let e = Sweep::new("scan_xy", Axis::X, 0.0, 0.0, 8, "nx").unwrap_err();
        assert!(e.0.starts_with("scan_xy: the x range [0, 0] µm has no extent: its 8 points (nx = 8) would all be at 0 µm"), "{}", e.0);
        assert_eq!(
            Sweep::new("scan_xy", Axis::X, 0.5, 0.5, 1, "nx")
                .unwrap()
                .values(),
            vec![0.5]
        );
        let e = check_dwell("ascan", -1.0).unwrap_err();
        assert!(e.0.contains("dwell = -1"), "{e}");
    }
}
