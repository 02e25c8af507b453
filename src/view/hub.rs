//! What the live view shows, kept in one place: the scan in progress (its header and every
//! point measured so far), the session's scans, the figures written, and the instrument's last
//! known state. The engine and the bindings write here; the browser connections read.
//!
//! Writers only lock, store and notify (a few microseconds); a reader copies what is new under
//! the lock and writes to its socket after releasing it, so a slow or closed browser never
//! holds up a scan. Memory is bounded: the points of the current scan only (16 bytes each), a
//! line per scan and per figure.

use crate::acquire::{ScanObserver, ScanStart};
use crate::data::clock::utc_now;
use crate::data::Scan;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::{Condvar, Mutex, MutexGuard};
use std::time::{Duration, Instant};

/// Points sent to a browser in one event at most (a reload in the middle of a large scan is
/// sent in several).
const MAX_POINTS_PER_EVENT: usize = 2048;

/// While a scan runs, readers look for new points this often (points do not wake them).
pub const SCAN_POLL: Duration = Duration::from_millis(50);

/// The scan being measured (or the last one).
struct Live {
    id: u64,
    header: Value,
    started: Instant,
    /// When the scan ended: an ended scan's elapsed time is its own duration, however late a
    /// browser asks.
    ended: Option<Instant>,
    /// Wall time spent paused (Ctrl-C, the question open) before the current pause, and the
    /// start of the current pause: the page's ETA counts only the time spent measuring.
    paused_before: Duration,
    paused_since: Option<Instant>,
    points: Vec<(u32, u32, [f32; 3])>,
    /// `running` (`paused` while Ctrl-C's question is open), then `complete` / `aborted` /
    /// `failed`.
    status: String,
    /// The scan's number in the session folder once saved, and the error of a failed scan.
    end: Value,
}

impl Live {
    /// Seconds from the start to now, or to the end of an ended scan.
    fn elapsed_s(&self) -> f64 {
        self.ended
            .unwrap_or_else(Instant::now)
            .saturating_duration_since(self.started)
            .as_secs_f64()
    }

    /// Seconds spent paused so far (the current pause included).
    fn paused_s(&self) -> f64 {
        let now = self.ended.unwrap_or_else(Instant::now);
        (self.paused_before
            + self
                .paused_since
                .map_or(Duration::ZERO, |t| now.saturating_duration_since(t)))
        .as_secs_f64()
    }
}

/// One scan of the session list.
struct ScanEntry {
    path: Option<PathBuf>,
    row: Value,
}

struct Figure {
    path: PathBuf,
    row: Value,
}

#[derive(Default)]
struct State {
    /// Bumped on every change; readers wait for it to move.
    version: u64,
    live: Option<Live>,
    next_live_id: u64,
    scans: Vec<ScanEntry>,
    figures: Vec<Figure>,
    instrument: Value,
    instrument_version: u64,
    closed: bool,
}

/// Where one browser connection is: what it has been sent so far.
#[derive(Debug, Default, Clone)]
pub struct Cursor {
    version: u64,
    live_id: u64,
    points_sent: usize,
    status_sent: String,
    scans_sent: usize,
    figures_sent: usize,
    instrument_version: u64,
    started: bool,
}

/// The shared state of the view.
#[derive(Default)]
pub struct Hub {
    state: Mutex<State>,
    changed: Condvar,
}

impl Hub {
    pub fn new() -> Hub {
        Hub::default()
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn touch(&self, s: &mut State) {
        s.version += 1;
        self.changed.notify_all();
    }

    /// Stop every reader (the view is closing).
    pub fn close(&self) {
        let mut s = self.lock();
        s.closed = true;
        self.touch(&mut s);
    }

    /// Add a scan already in the session folder (the list at start-up).
    pub fn add_saved_scan(&self, path: &Path, scan: &Scan) {
        let row = scan_row(scan, Some(path));
        let mut s = self.lock();
        s.scans.push(ScanEntry {
            path: Some(path.to_path_buf()),
            row,
        });
        self.touch(&mut s);
    }

    /// A figure was written to `path`.
    pub fn add_figure(&self, path: &Path) {
        let mut s = self.lock();
        let id = s.figures.len() + 1;
        let row = json!({
            "id": id,
            "name": path.file_name().map(|n| n.to_string_lossy().to_string()),
            "path": path.display().to_string(),
            "time": utc_now(),
        });
        s.figures.push(Figure {
            path: path.to_path_buf(),
            row,
        });
        self.touch(&mut s);
    }

    /// The file of figure `id` (1-based, as listed).
    pub fn figure_path(&self, id: usize) -> Option<PathBuf> {
        let s = self.lock();
        id.checked_sub(1)
            .and_then(|i| s.figures.get(i))
            .map(|f| f.path.clone())
    }

    /// The saved file of the scan numbered `number` in the list.
    pub fn scan_path(&self, number: u64) -> Option<PathBuf> {
        let s = self.lock();
        s.scans
            .iter()
            .find(|e| e.row["number"].as_u64() == Some(number))
            .and_then(|e| e.path.clone())
    }

    /// Merge `fields` into the instrument's state (position, backend, last error …); readers
    /// are told only when something changed.
    pub fn set_instrument(&self, fields: Value) {
        let mut s = self.lock();
        if !s.instrument.is_object() {
            s.instrument = json!({});
        }
        let mut changed = false;
        if let (Value::Object(cur), Value::Object(new)) = (&mut s.instrument, fields) {
            for (k, v) in new {
                if cur.get(&k) != Some(&v) {
                    cur.insert(k, v);
                    changed = true;
                }
            }
        }
        if changed {
            s.instrument_version += 1;
            self.touch(&mut s);
        }
    }

    /// The last error the operator saw (a script error, a device fault).
    pub fn set_error(&self, message: &str) {
        self.set_instrument(json!({ "last_error": message, "last_error_time": utc_now() }));
    }

    /// True while a scan is being measured.
    pub fn scanning(&self) -> bool {
        self.lock().live.as_ref().is_some_and(|l| l.ended.is_none())
    }

    /// Bytes held by the view's state (points of the current scan, list rows, figure rows), for
    /// the memory figure of the benchmark.
    pub fn held_bytes(&self) -> usize {
        let s = self.lock();
        let live = s.live.as_ref().map_or(0, |l| {
            l.points.capacity() * std::mem::size_of::<(u32, u32, [f32; 3])>()
                + l.header.to_string().len()
        });
        let rows: usize = s.scans.iter().map(|e| e.row.to_string().len()).sum();
        let figs: usize = s.figures.iter().map(|f| f.row.to_string().len()).sum();
        live + rows + figs + s.instrument.to_string().len()
    }

    /// Everything at once (the `/api/state` endpoint): live header and points, scans,
    /// figures, instrument.
    pub fn snapshot(&self) -> Value {
        let s = self.lock();
        let live = s.live.as_ref().map(|l| {
            let mut h = l.header.clone();
            h["status"] = json!(l.status);
            h["end"] = l.end.clone();
            h["measured"] = json!(l.points.len());
            h["elapsed_s"] = json!(l.elapsed_s());
            h["paused_s"] = json!(l.paused_s());
            h
        });
        json!({
            "live": live,
            "scans": s.scans.iter().map(|e| e.row.clone()).collect::<Vec<_>>(),
            "figures": s.figures.iter().map(|f| f.row.clone()).collect::<Vec<_>>(),
            "instrument": s.instrument,
        })
    }

    /// Wait until something changed for `cur` (or `timeout` passed), then write the events
    /// that bring it up to date into `out` (cleared first; server-sent-event text, `event:` and
    /// `data:` lines), reusing its buffer: a reader allocates next to nothing per call, so a
    /// long session does not fragment the heap. `false` once the view is closing. Nothing
    /// written means the timeout passed with nothing new (the caller sends a keep-alive).
    pub fn next_events(&self, cur: &mut Cursor, timeout: Duration, out: &mut String) -> bool {
        use std::fmt::Write;
        out.clear();
        let mut s = self.lock();
        let deadline = Instant::now() + timeout;
        while cur.started && s.version == cur.version && !s.closed {
            let running = s.live.as_ref().is_some_and(|l| l.ended.is_none());
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                break;
            }
            let wait = if running { left.min(SCAN_POLL) } else { left };
            s = self
                .changed
                .wait_timeout(s, wait)
                .unwrap_or_else(|e| e.into_inner())
                .0;
        }
        if s.closed {
            return false;
        }
        let event = |name: &str, out: &mut String| {
            let _ = write!(out, "event: {name}\ndata: ");
        };
        if !cur.started {
            event("hello", out);
            let _ = write!(out, "{}\n\n", json!({ "time": utc_now() }));
            cur.started = true;
        }
        cur.version = s.version;
        if let Some(l) = &s.live {
            if l.id != cur.live_id {
                event("scan", out);
                let _ = write!(
                    out,
                    "{{\"elapsed_s\":{},\"paused_s\":{},\"header\":{}}}\n\n",
                    l.elapsed_s(),
                    l.paused_s(),
                    l.header
                );
                cur.live_id = l.id;
                cur.points_sent = 0;
                cur.status_sent.clear();
            }
            if cur.points_sent < l.points.len() {
                let end = l.points.len().min(cur.points_sent + MAX_POINTS_PER_EVENT);
                event("points", out);
                points_json(out, l.id, cur.points_sent, &l.points[cur.points_sent..end]);
                out.push_str("\n\n");
                cur.points_sent = end;
                if end < l.points.len() {
                    // more to send: come back at once
                    cur.version = cur.version.wrapping_sub(1);
                }
            }
            if l.status != cur.status_sent && cur.points_sent == l.points.len() {
                event("status", out);
                let _ = write!(
                    out,
                    "{{\"id\":{},\"status\":\"{}\",\"end\":{},\"elapsed_s\":{},\"paused_s\":{}}}\n\n",
                    l.id,
                    l.status,
                    l.end,
                    l.elapsed_s(),
                    l.paused_s()
                );
                cur.status_sent.clear();
                cur.status_sent.push_str(&l.status);
            }
        }
        // list rows are only ever appended: send the new ones
        if cur.scans_sent < s.scans.len() {
            event("scans", out);
            json_rows(out, s.scans[cur.scans_sent..].iter().map(|e| &e.row));
            cur.scans_sent = s.scans.len();
        }
        if cur.figures_sent < s.figures.len() {
            event("figures", out);
            json_rows(out, s.figures[cur.figures_sent..].iter().map(|f| &f.row));
            cur.figures_sent = s.figures.len();
        }
        if s.instrument_version != cur.instrument_version {
            event("instrument", out);
            let _ = write!(out, "{}\n\n", s.instrument);
            cur.instrument_version = s.instrument_version;
        }
        true
    }
}

/// `[row, row, …]` then the blank line ending an event.
fn json_rows<'a>(out: &mut String, rows: impl Iterator<Item = &'a Value>) {
    use std::fmt::Write;
    out.push('[');
    for (i, r) in rows.enumerate() {
        if i > 0 {
            out.push(',');
        }
        let _ = write!(out, "{r}");
    }
    out.push_str("]\n\n");
}

/// `{"id":…,"from":…,"p":[row,col,sx,sy,sz,…]}` written straight into `out` (no JSON tree per
/// point); a non-finite value is `null`.
fn points_json(out: &mut String, id: u64, from: usize, pts: &[(u32, u32, [f32; 3])]) {
    use std::fmt::Write;
    let _ = write!(out, "{{\"id\":{id},\"from\":{from},\"p\":[");
    for (i, (r, c, v)) in pts.iter().enumerate() {
        if i > 0 {
            out.push(',');
        }
        let _ = write!(out, "{r},{c}");
        for x in v {
            if x.is_finite() {
                let _ = write!(out, ",{x:e}");
            } else {
                out.push_str(",null");
            }
        }
    }
    out.push_str("]}");
}

/// A scan's line in the session list, from its metadata.
fn scan_row(scan: &Scan, path: Option<&Path>) -> Value {
    let m = &scan.meta;
    let number = path
        .and_then(|p| p.file_name())
        .and_then(|n| crate::data::session::scan_number(&n.to_string_lossy()));
    json!({
        "number": number,
        "file": path.and_then(|p| p.file_name()).map(|n| n.to_string_lossy().to_string()),
        "kind": m["plan"]["kind"],
        "time": m["time"]["wall_start"],
        "protocol": m["protocol"]["name"],
        "status": scan.status,
        "notes": m["notes"],
        "points_measured": m["points_measured"],
        "points_total": m["points_total"],
        "error": m["error"]["message"],
        // clipped and dark pixels, in words (empty when none)
        "input": crate::data::clip::input_check(scan, &["sx", "sy", "sz"], None).warnings,
        "rows": scan.sx.data.nrows(),
        "cols": scan.sx.data.ncols(),
    })
}

impl ScanObserver for Hub {
    fn started(&self, st: &ScanStart) {
        let header = json!({
            "kind": st.kind,
            "rows": st.rows,
            "cols": st.cols,
            "x": st.x,
            "y": st.y,
            "x_name": st.x_name,
            "y_name": st.y_name,
            "total": st.points_total,
            "eta_s": st.eta_s,
            "protocol": st.meta["protocol"]["name"],
            "notes": st.meta["notes"],
            "time": utc_now(),
        });
        let mut s = self.lock();
        s.next_live_id += 1;
        let id = s.next_live_id;
        let mut header = header;
        header["id"] = json!(id);
        // reuse the last scan's buffer: no fresh pages to fault in, scan after scan
        let mut points = s.live.take().map(|l| l.points).unwrap_or_default();
        points.clear();
        points.reserve(st.points_total);
        s.live = Some(Live {
            id,
            header,
            started: Instant::now(),
            ended: None,
            paused_before: Duration::ZERO,
            paused_since: None,
            points,
            status: "running".into(),
            end: Value::Null,
        });
        self.touch(&mut s);
    }

    /// Store the points and move the version, without waking anyone: while a scan runs the
    /// readers look every [`SCAN_POLL`] on their own, so a batch costs the scan one uncontended
    /// lock and a copy, not a wake-up of every reader.
    fn points(&self, pts: &[(usize, usize, [f64; 3])]) {
        let mut s = self.lock();
        if let Some(l) = s.live.as_mut() {
            l.points.extend(pts.iter().map(|(r, c, v)| {
                (
                    *r as u32,
                    *c as u32,
                    [v[0] as f32, v[1] as f32, v[2] as f32],
                )
            }));
            s.version += 1;
        }
    }

    fn ended(&self, scan: &Scan, saved: Option<&Path>) {
        let row = scan_row(scan, saved);
        let mut s = self.lock();
        if let Some(l) = s.live.as_mut() {
            let now = Instant::now();
            if let Some(t) = l.paused_since.take() {
                l.paused_before += now.saturating_duration_since(t);
            }
            l.ended = Some(now);
            l.status = row["status"].as_str().unwrap_or("failed").to_string();
            l.end = json!({ "number": row["number"], "error": row["error"], "file": row["file"], "input": row["input"] });
        }
        if let Some(e) = row["error"].as_str() {
            s.instrument["last_error"] = json!(e);
            s.instrument["last_error_time"] = json!(utc_now());
            s.instrument_version += 1;
        }
        s.scans.push(ScanEntry {
            path: saved.map(Path::to_path_buf),
            row,
        });
        self.touch(&mut s);
    }

    fn paused(&self, paused: bool) {
        let mut s = self.lock();
        let Some(l) = s.live.as_mut() else {
            return;
        };
        if l.ended.is_some() {
            return;
        }
        let now = Instant::now();
        if paused {
            l.paused_since.get_or_insert(now);
            l.status = "paused".into();
        } else {
            if let Some(t) = l.paused_since.take() {
                l.paused_before += now.saturating_duration_since(t);
            }
            l.status = "running".into();
        }
        self.touch(&mut s);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_are_valid_json_with_their_values() {
        let mut s = String::new();
        points_json(
            &mut s,
            3,
            7,
            &[(0, 1, [1.5e-20, -2.0, 0.0]), (2, 3, [f32::NAN, 4.0, 1e6])],
        );
        let v: Value = serde_json::from_str(&s).unwrap();
        assert_eq!(v["id"], 3);
        assert_eq!(v["from"], 7);
        let p = v["p"].as_array().unwrap();
        assert_eq!(p.len(), 10);
        assert_eq!(p[2].as_f64().unwrap() as f32, 1.5e-20);
        assert_eq!(p[3].as_f64().unwrap(), -2.0);
        assert!(p[7].is_null());
        assert_eq!(p[9].as_f64().unwrap(), 1e6);
    }

    #[test]
    fn a_new_reader_gets_everything_then_only_what_is_new() {
        let hub = Hub::new();
        let meta = json!({});
        hub.started(&ScanStart {
            kind: "scan_xy",
            rows: 2,
            cols: 2,
            x: &[0.0, 1.0],
            y: &[0.0, 1.0],
            x_name: "x",
            y_name: "y",
            points_total: 4,
            eta_s: 1.0,
            meta: &meta,
        });
        hub.points(&[(0, 0, [1.0, 2.0, 3.0])]);
        let mut cur = Cursor::default();
        let mut buf = String::new();
        assert!(hub.next_events(&mut cur, Duration::from_millis(10), &mut buf));
        let ev = parse(&buf);
        let names: Vec<&str> = ev.iter().map(|e| e.0.as_str()).collect();
        assert_eq!(names, ["hello", "scan", "points", "status"]);
        assert_eq!(ev[1].1["header"]["cols"], 2);
        assert_eq!(ev[3].1["status"], "running");
        // nothing new: the wait times out with no events
        assert!(hub.next_events(&mut cur, Duration::from_millis(10), &mut buf));
        assert!(buf.is_empty());
        hub.points(&[(0, 1, [4.0, 5.0, 6.0])]);
        assert!(hub.next_events(&mut cur, Duration::from_millis(200), &mut buf));
        let ev = parse(&buf);
        assert_eq!(ev.len(), 1);
        assert_eq!(ev[0].1["from"], 1);
        assert_eq!(ev[0].1["p"], json!([0, 1, 4.0, 5.0, 6.0]));
        hub.close();
        assert!(!hub.next_events(&mut cur, Duration::from_secs(5), &mut buf));
    }

    /// (name, data) of each event in server-sent-event text; every data line is JSON.
    fn parse(text: &str) -> Vec<(String, Value)> {
        text.split("\n\n")
            .filter(|e| !e.is_empty())
            .map(|e| {
                let name = e.lines().next().unwrap().strip_prefix("event: ").unwrap();
                let data = e.lines().nth(1).unwrap().strip_prefix("data: ").unwrap();
                (name.to_string(), serde_json::from_str(data).unwrap())
            })
            .collect()
    }
}
