//! Golden traces: wrappers around any `Stage` and `Qpd` that record every move
//! and read with the instrument's time, plus the decisions a protocol notes, as readable text
//! lines. Tests compare a protocol's trace with a committed file, so a change in behaviour shows
//! up as a line diff; `bfpscope test --bless` rewrites the files deliberately.
//!
//! Values are printed with limited precision (positions to 0.1 nm, signals to 4 significant
//! digits, time to 0.1 ms) so that harmless floating-point noise does not break a trace.

use super::{Clock, DeviceError, Pos, Qpd, QpdReading, Stage};
use delegate::delegate;
use std::sync::{Arc, Mutex};

/// Shared, append-only event log.
#[derive(Clone, Default)]
pub struct Trace {
    lines: Arc<Mutex<Vec<String>>>,
    clock: Option<Arc<dyn Clock>>,
}

impl std::fmt::Debug for Trace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Trace({} lines)", self.len())
    }
}

impl Trace {
    pub fn new(clock: Arc<dyn Clock>) -> Self {
        Self {
            lines: Arc::default(),
            clock: Some(clock),
        }
    }

    fn stamp(&self) -> String {
        match &self.clock {
            Some(c) => format!("{:>10.4} s", c.now()),
            None => "          ".into(),
        }
    }

    /// Record a line with the current time.
    pub fn record(&self, what: impl AsRef<str>) {
        let line = format!("{}  {}", self.stamp(), what.as_ref());
        self.lines
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .push(line);
    }

    /// A protocol's decision ("focus: best z = 0.0213 µm").
    pub fn note(&self, what: impl AsRef<str>) {
        self.record(format!("note {}", what.as_ref()));
    }

    pub fn len(&self) -> usize {
        self.lines
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn text(&self) -> String {
        let mut s = self
            .lines
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .join("\n");
        s.push('\n');
        s
    }

    pub fn clear(&self) {
        self.lines
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clear();
    }
}

/// Signal with 4 significant digits, exponent form; |v| < 1e-12 (round-off of a zero signal,
/// e.g. Sy on the x-axis by symmetry) prints as 0 so traces do not depend on the last bits.
pub fn sig4(v: f64) -> String {
    if v.abs() < 1e-12 {
        "0".into()
    } else {
        format!("{v:.3e}")
    }
}

fn pos_str(p: &Pos) -> String {
    format!("x={:.4} y={:.4} z={:.4}", p[0], p[1], p[2])
}

/// A stage or QPD that records what it is told to do: each move (and stop) of a stage, each
/// read of a QPD.
pub struct Traced<D: ?Sized> {
    pub inner: Box<D>,
    pub trace: Trace,
}

impl Stage for Traced<dyn Stage> {
    delegate! {
        to self.inner {
            fn move_time_s(&self) -> f64;
            fn move_time_for_s(&self, from: Pos, to: Pos) -> f64;
            fn link_costs(&mut self) -> super::link::LinkCosts;
            fn name(&self) -> String;
            fn position(&mut self) -> Result<Pos, DeviceError>;
            fn target(&mut self) -> Result<Pos, DeviceError>;
            fn set_velocity(&mut self, um_s: f64) -> Result<(), DeviceError>;
            fn velocity(&mut self) -> Result<Option<Pos>, DeviceError>;
            fn enable(&mut self) -> Result<(), DeviceError>;
            fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError>;
        }
    }
    /// The inner stage's raw queries (they move nothing); its other capabilities are not
    /// offered through the trace, whose record is of moves.
    fn capabilities(&mut self, kind: super::CapabilityKind) -> Option<super::Capability<'_>> {
        match kind {
            super::CapabilityKind::RawQuery => self.inner.capabilities(kind),
            _ => None,
        }
    }
    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        let r = self.inner.move_to(target);
        match &r {
            Ok(()) => self.trace.record(format!("move {}", pos_str(&target))),
            Err(e) => self
                .trace
                .record(format!("move {} FAILED: {e}", pos_str(&target))),
        }
        r
    }
    fn move_to_or_abort(
        &mut self,
        target: Pos,
        abort: &std::sync::atomic::AtomicBool,
    ) -> Result<bool, DeviceError> {
        let r = self.inner.move_to_or_abort(target, abort);
        match &r {
            Ok(true) => self.trace.record(format!("move {}", pos_str(&target))),
            Ok(false) => self
                .trace
                .record(format!("move {} INTERRUPTED", pos_str(&target))),
            Err(e) => self
                .trace
                .record(format!("move {} FAILED: {e}", pos_str(&target))),
        }
        r
    }
    fn stop(&mut self) -> Result<(), DeviceError> {
        self.trace.record("stop");
        self.inner.stop()
    }
}

impl Qpd for Traced<dyn Qpd> {
    delegate! {
        to self.inner {
            fn name(&self) -> String;
            fn sample_rate(&self) -> f64;
            fn metadata(&self) -> Option<serde_json::Value>;
            fn input_range(&self) -> Option<super::range::InputRange>;
            fn overhead_s(&self) -> f64;
            fn link_costs(&mut self) -> super::link::LinkCosts;
        }
    }
    fn read_means(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        self.read(n)
    }
    fn read(&mut self, n: usize) -> Result<QpdReading, DeviceError> {
        let r = self.inner.read(n);
        match &r {
            Ok(v) => self.trace.record(format!(
                "read n={n} sx={} sy={} sz={}",
                sig4(v.sx),
                sig4(v.sy),
                sig4(v.sz)
            )),
            Err(e) => self.trace.record(format!("read n={n} FAILED: {e}")),
        }
        r
    }
}

impl super::Instrument {
    /// Wrap the stage and QPD so every move and read lands in the returned trace.
    pub fn traced(self) -> (Self, Trace) {
        let trace = Trace::new(self.clock.clone());
        let inst = Self {
            stage: Box::new(Traced {
                inner: self.stage,
                trace: trace.clone(),
            }),
            qpd: Box::new(Traced {
                inner: self.qpd,
                trace: trace.clone(),
            }),
            ..self
        };
        (inst, trace)
    }
}

/// Why a golden file was (re)written: lines starting with `# ` at its top, one per blessing,
/// kept from blessing to blessing and ignored by the comparison.
const WHY: &str = "# ";

/// Compare a trace with a golden file: `Ok(())` when equal (ignoring the file's `# ` header
/// lines); when `bless` is `Some(why)` the file is (re)written with its old header lines plus
/// `# why` — a golden file says why each time it was re-blessed (refused if `why` is empty);
/// otherwise an error with a unified-style diff of the first differing lines.
pub fn check_golden(
    actual: &str,
    path: &std::path::Path,
    bless: Option<&str>,
) -> Result<(), String> {
    let old = std::fs::read_to_string(path).ok();
    let header: Vec<&str> = old
        .as_deref()
        .map(|t| t.lines().take_while(|l| l.starts_with(WHY)).collect())
        .unwrap_or_default();
    if let Some(why) = bless {
        let why = why.trim();
        if why.is_empty() || why == "1" {
            return Err(format!(
                "blessing {} needs a reason: BFPSCOPE_BLESS=\"<one line saying why>\"",
                path.display()
            ));
        }
        // an unchanged trace keeps its file: the reason is for the traces it changes
        let skip: usize = header.iter().map(|l| l.len() + 1).sum();
        if old.as_deref().and_then(|t| t.get(skip..)) == Some(actual) {
            return Ok(());
        }
        if let Some(d) = path.parent() {
            std::fs::create_dir_all(d).map_err(|e| format!("{}: {e}", d.display()))?;
        }
        let mut text = String::new();
        for l in header
            .iter()
            .copied()
            .chain(std::iter::once(format!("{WHY}{why}").as_str()))
        {
            text += l;
            text.push('\n');
        }
        text += actual;
        std::fs::write(path, text).map_err(|e| format!("{}: {e}", path.display()))?;
        return Ok(());
    }
    let Some(full) = old.as_deref() else {
        return Err(format!(
            "golden trace {} unreadable; run with BFPSCOPE_BLESS=\"<why>\" to create it",
            path.display()
        ));
    };
    // the trace after the header lines (each ends in a newline when a trace follows)
    let skip: usize = header.iter().map(|l| l.len() + 1).sum();
    let expected = full.get(skip..).unwrap_or("");
    if expected == actual {
        return Ok(());
    }
    let (e, a): (Vec<&str>, Vec<&str>) = (expected.lines().collect(), actual.lines().collect());
    let mut diff = format!(
        "trace differs from {} (run with BFPSCOPE_BLESS=\"<why>\" to accept):\n",
        path.display()
    );
    let mut shown = 0;
    for i in 0..e.len().max(a.len()) {
        let (x, y) = (e.get(i).copied(), a.get(i).copied());
        if x != y {
            diff += &format!(
                "@@ line {}\n- {}\n+ {}\n",
                i + 1,
                x.unwrap_or("<end>"),
                y.unwrap_or("<end>")
            );
            shown += 1;
            if shown >= 10 {
                diff += "...\n";
                break;
            }
        }
    }
    Err(diff)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::instrument::sim::{scene::Bead, Scene, SimConfig, SimCore};
    use crate::optics::params::Optics;

    #[test]
    fn trace_records_moves_reads_and_notes_with_simulated_time() {
        let mut s = Scene::default();
        s.add_bead(Bead {
            pos: [0.0, 0.0, 0.0],
            d_nm: 110.0,
            n: 1.572,
        })
        .unwrap();
        let core = SimCore::new(&Optics::default(), &s, SimConfig::default()).unwrap();
        let (mut inst, trace) = core.instrument(0.01).traced();
        inst.move_settle([0.1, 0.0, 0.0]).unwrap();
        inst.qpd.read(1000).unwrap();
        trace.note("done");
        let e = inst
            .stage
            .move_to([0.0, 0.0, 99.0])
            .unwrap_err()
            .to_string();
        assert!(e.contains("Position out of limits"), "{e}");
        let t = trace.text();
        let lines: Vec<&str> = t.lines().collect();
        assert_eq!(lines.len(), 4, "{t}");
        assert!(
            lines[0].contains("move x=0.1000 y=0.0000 z=0.0000")
                && lines[0].trim_start().starts_with("0.0020 s"),
            "{t}"
        );
        assert!(
            lines[1].contains("read n=1000 sx=") && lines[1].trim_start().starts_with("0.0220 s"),
            "{t}"
        );
        assert!(lines[2].ends_with("note done"));
        assert!(lines[3].contains("FAILED") && lines[3].contains("out of limits"));
        // golden comparison: bless, then equal, then a changed line is reported
        let dir = std::env::temp_dir().join(format!("bfp_golden_{}", std::process::id()));
        let f = dir.join("t.trace");
        let _ = std::fs::remove_dir_all(&dir);
        assert!(check_golden(&t, &f, Some("1"))
            .unwrap_err()
            .contains("needs a reason"));
        check_golden(&t, &f, Some("first trace")).unwrap();
        check_golden(&t, &f, None).unwrap();
        // blessing an unchanged trace leaves its file alone (no reason added)
        check_golden(&t, &f, Some("nothing changed")).unwrap();
        let text = std::fs::read_to_string(&f).unwrap();
        assert!(text.starts_with("# first trace\n") && !text.contains("nothing changed"));
        // a second blessing of a changed trace keeps the first reason and adds its own
        let t2 = t.replace("note done", "note done again");
        check_golden(&t2, &f, Some("re-blessed: why")).unwrap();
        let text = std::fs::read_to_string(&f).unwrap();
        assert!(
            text.starts_with("# first trace\n# re-blessed: why\n"),
            "{text}"
        );
        check_golden(&t2, &f, None).unwrap();
        let changed = t.replace("note done", "note other");
        let e = check_golden(&changed, &f, None).unwrap_err();
        assert!(
            e.contains("- ")
                && e.contains("note done")
                && e.contains("+ ")
                && e.contains("note other"),
            "{e}"
        );
        let _ = std::fs::remove_dir_all(dir);
    }
}
