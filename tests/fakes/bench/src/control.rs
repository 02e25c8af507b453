//! The control and inspection API for tests (not vendor API; every symbol starts with
//! `fakebench_`). Strings are returned in the caller's buffer: the functions return the size
//! the whole text needs with its NUL, so a caller passing a too small (or NULL) buffer learns
//! the size to allocate.
//!
//! - `int fakebench_reset(void)`: a fresh bench from the environment (`FAKEBENCH_*`).
//! - `int fakebench_set(const char *key, const char *value)`: change one setting (keys as in
//!   [`crate::config`]) and rebuild the bench with it; 0, or −1 with the reason in
//!   `fakebench_last_error`.
//! - `int fakebench_set_faults(const char *spec)`: the fault switches (see
//!   [`crate::config::Faults::parse`]), applied at once without rebuilding the bench.
//! - `size_t fakebench_log(char *buf, size_t size)`: the call log, one line per call:
//!   `name(arg=value, …) -> result`.
//! - `void fakebench_clear_log(void)`.
//! - `size_t fakebench_state(char *buf, size_t size)`: the bench's state as JSON (stage
//!   position, targets, commands, external inputs, AO voltages, tasks, handles).
//! - `double fakebench_stage_position(int axis)`: the true position (µm) of axis 1–3 now.
//! - `double fakebench_ao_voltage(int channel)`: the voltage at AO terminal 0–1 now.
//! - `size_t fakebench_last_error(char *buf, size_t size)`: why the last `fakebench_set*`
//!   failed.

use crate::{cstr, guard, now, put_cstr, replace_bench, with_bench, Config};
use std::os::raw::{c_char, c_double, c_int};
use std::sync::Mutex;

static LAST_ERROR: Mutex<String> = Mutex::new(String::new());

fn set_error(e: String) -> c_int {
    *LAST_ERROR.lock().unwrap_or_else(|p| p.into_inner()) = e;
    -1
}

#[no_mangle]
pub extern "C" fn fakebench_reset() -> c_int {
    guard(-1, || {
        replace_bench(Config::from_env());
        0
    })
}

/// # Safety
/// `key` and `value` are C strings.
#[no_mangle]
pub unsafe extern "C" fn fakebench_set(key: *const c_char, value: *const c_char) -> c_int {
    guard(-1, || {
        let (k, v) = (cstr(key), cstr(value));
        let mut cfg = with_bench(|b| b.cfg.clone());
        match cfg.set(&k, &v) {
            Ok(()) => {
                replace_bench(cfg);
                0
            }
            Err(e) => set_error(format!("fakebench_set: {e}")),
        }
    })
}

/// # Safety
/// `spec` is a C string.
#[no_mangle]
pub unsafe extern "C" fn fakebench_set_faults(spec: *const c_char) -> c_int {
    guard(-1, || {
        let s = cstr(spec);
        match crate::config::Faults::parse(&s) {
            Ok(f) => with_bench(|b| {
                let t = now();
                crate::daqmx::sync(b, t);
                b.stage.apply_stuck(&f.stage_stuck, t);
                b.cfg.faults = f;
                // new switches: the counters restart, an unplugged device is back
                b.mcl.calls = 0;
                b.mcl.unplugged = false;
                b.daq.reads = 0;
                b.daq.removed = false;
                b.log(format!("fakebench_set_faults(\"{s}\")"));
                0
            }),
            Err(e) => set_error(format!("fakebench_set_faults: {e}")),
        }
    })
}

/// # Safety
/// `buf` is NULL or points to `size` bytes.
#[no_mangle]
pub unsafe extern "C" fn fakebench_log(buf: *mut c_char, size: usize) -> usize {
    guard(0, || {
        let text = with_bench(|b| b.log.join("\n"));
        put_cstr(&text, buf, size)
    })
}

#[no_mangle]
pub extern "C" fn fakebench_clear_log() {
    guard((), || with_bench(|b| b.log.clear()))
}

/// # Safety
/// `buf` is NULL or points to `size` bytes.
#[no_mangle]
pub unsafe extern "C" fn fakebench_last_error(buf: *mut c_char, size: usize) -> usize {
    guard(0, || {
        let e = LAST_ERROR.lock().unwrap_or_else(|p| p.into_inner()).clone();
        put_cstr(&e, buf, size)
    })
}

/// The bench's state as JSON.
pub fn state_json() -> serde_json::Value {
    with_bench(|b| {
        let t = now();
        crate::daqmx::sync(b, t);
        let axes: Vec<serde_json::Value> = b
            .stage
            .axes
            .iter()
            .map(|a| {
                serde_json::json!({
                    "range_um": a.range,
                    "position_um": a.position_at(t),
                    "target_um": a.target_at(t),
                    "usb_command_um": a.usb,
                    "external_um": a.ext,
                    "stuck": a.stuck_at.is_some(),
                })
            })
            .collect();
        let tasks: Vec<serde_json::Value> = b
            .daq
            .tasks
            .values()
            .map(|k| {
                serde_json::json!({
                    "name": k.name,
                    "kind": format!("{:?}", k.kind),
                    "running": k.running,
                    "channels": k.chans.iter().map(|c| c.name.clone()).collect::<Vec<_>>(),
                    "rate": k.timing.map(|t| t.rate),
                    "finite": k.timing.and_then(|t| t.finite),
                    "read_pos": k.read_pos,
                    "implicit_start": k.implicit_start,
                })
            })
            .collect();
        serde_json::json!({
            "time_s": t,
            "stage": {
                "serial": b.stage.serial,
                "held_handle": b.mcl.held,
                "unplugged": b.mcl.unplugged,
                "axes": axes,
            },
            "daq": {
                "device": b.daq.device,
                "removed": b.daq.removed,
                "ao_v": b.daq.ao_v,
                "tasks": tasks,
            },
            "config_errors": b.cfg.errors,
        })
    })
}

/// # Safety
/// `buf` is NULL or points to `size` bytes.
#[no_mangle]
pub unsafe extern "C" fn fakebench_state(buf: *mut c_char, size: usize) -> usize {
    guard(0, || put_cstr(&state_json().to_string(), buf, size))
}

#[no_mangle]
pub extern "C" fn fakebench_stage_position(axis: c_int) -> c_double {
    guard(f64::NAN, || {
        if !(1..=3).contains(&axis) {
            return f64::NAN;
        }
        with_bench(|b| {
            let t = now();
            crate::daqmx::sync(b, t);
            b.stage.axes[axis as usize - 1].position_at(t)
        })
    })
}

#[no_mangle]
pub extern "C" fn fakebench_ao_voltage(channel: c_int) -> c_double {
    guard(f64::NAN, || {
        if !(0..2).contains(&channel) {
            return f64::NAN;
        }
        with_bench(|b| {
            crate::daqmx::sync(b, now());
            b.daq.ao_v[channel as usize]
        })
    })
}

/// Most target changes `fakebench_history` returns (the latest).
const HISTORY_CAP: usize = 200_000;

/// The target changes of axis 1–3 at or after bench time `since_s`, as JSON
/// `[[t_s, target_um, position_um], …]` (the position at the change; between changes the
/// position follows the first-order lag towards the target), the latest
/// [`HISTORY_CAP`] at most; with `"now_s"`. Tests time what the stage did on the bench's
/// clock: when a target left the plan, when the hold brought it back, how far it went.
///
/// # Safety
/// `buf` is NULL or points to `size` bytes.
#[no_mangle]
pub unsafe extern "C" fn fakebench_history(
    axis: c_int,
    since_s: c_double,
    buf: *mut c_char,
    size: usize,
) -> usize {
    guard(0, || {
        let text = if (1..=3).contains(&axis) {
            with_bench(|b| {
                let t = now();
                crate::daqmx::sync(b, t);
                let ev = &b.stage.axes[axis as usize - 1].events;
                let k = ev.partition_point(|e| e.t < since_s);
                let k = k.max(ev.len().saturating_sub(HISTORY_CAP));
                let list: Vec<[f64; 3]> = ev[k..].iter().map(|e| [e.t, e.target, e.pos]).collect();
                serde_json::json!({ "now_s": t, "tau_s": b.cfg.tau_s, "events": list }).to_string()
            })
        } else {
            "{}".to_string()
        };
        put_cstr(&text, buf, size)
    })
}
