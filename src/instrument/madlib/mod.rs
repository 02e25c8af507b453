//! Mad City Labs Nano-Drive (the paper's Nano-PDQ375 stage) through Madlib, the vendor's C
//! library, loaded at run time (`ffi.rs`, declared from `Madlib.h`).
//!
//! **Connect.** `MCL_GrabAllHandles` takes every Nano-Drive attached, `MCL_GetAllHandles`
//! lists them and `MCL_GetSerialNumber` tells them apart: the one with `stage.serial` is kept
//! (with no serial: the only one attached; two or more are refused, listing their serials).
//! The others are released at once (`MCL_ReleaseHandle`) so another program can take them. The
//! axes used must be in the product's axis bitmap (`MCL_GetProductInfo`); each axis's calibrated
//! range (`MCL_GetCalibration`, µm) is its travel, 0 … range.
//!
//! **Move.** `MCL_SingleWriteN` per axis, only to the axes whose target changes (a scan's z
//! is not rewritten at every point). A Nano-Drive has no on-target flag: the position is
//! read back (`MCL_SingleReadN`; by default back to back, each read being a USB round trip)
//! until every axis stays within `tolerance_um`
//! of its target for two reads in a row, or `on_target_timeout_ms` passes (a stuck stage).
//!
//! **Stop.** Each axis is held at its present reading (`MCL_SingleWriteN` of what
//! `MCL_SingleReadN` just returned). It never writes 0 µm: that is a jump across the whole range.
//! An axis that cannot be read is not written at all.
//!
//! **Release.** The handle is released (`MCL_ReleaseHandle`) when the stage is dropped (exit,
//! reconnect) and after a fault (a negative return code, an on-target timeout): the stage is
//! held first, and every later call is refused with the fault's message until `connect()`.

pub mod config;
pub use config::FAMILY;
pub mod ffi;

use crate::instrument::device::all_then_first_error;
use crate::instrument::{DeviceError, Pos, Stage};
use ffi::Madlib;
use std::os::raw::c_int;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Driver settings (`[stage]` with `backend = "madlib"`).
#[derive(Debug, Clone, PartialEq)]
pub struct MadlibOptions {
    /// The library (`stage.library`); `None`: the usual names and paths.
    pub library: Option<PathBuf>,
    /// The Nano-Drive's serial number (`stage.serial`); `None`: the only one attached.
    pub serial: Option<i32>,
    /// Madlib axis numbers for x, y, z (1 = X, 2 = Y, 3 = Z, 4 = A).
    pub axes: [u32; 3],
    /// On target when every axis reads within this distance of its target, µm.
    pub tolerance_um: f64,
    /// Longest wait for the readings to reach the target after a move.
    pub on_target_timeout: Duration,
    /// Interval between read-backs (zero: back to back, at the link's pace).
    pub poll_interval: Duration,
}

impl Default for MadlibOptions {
    fn default() -> Self {
        Self {
            library: None,
            serial: None,
            axes: [1, 2, 3],
            tolerance_um: 0.05,
            on_target_timeout: Duration::from_millis(5000),
            poll_interval: Duration::ZERO,
        }
    }
}

/// A Madlib return code as a device error: the device, the call with its arguments, the code
/// and its name from `Madlib.h`.
pub fn madlib_error(device: &str, call: &str, code: c_int) -> DeviceError {
    let message = match ffi::code_name(code) {
        Some((name, what)) => format!("{name}: {what}"),
        None => "a code Madlib.h does not define".to_string(),
    };
    DeviceError::Controller {
        device: device.to_string(),
        command: call.to_string(),
        code: code as i64,
        message,
    }
}

/// What connect found, for the scan metadata.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct NanoDriveInfo {
    pub library: String,
    pub handle: i32,
    pub serial: i32,
    pub product_id: i16,
    pub axis_bitmap: u8,
    pub adc_bits: i16,
    pub dac_bits: i16,
    pub firmware_version: i16,
    pub firmware_profile: i16,
    /// Calibrated range of the x, y, z axes, µm (`MCL_GetCalibration`).
    pub calibration_um: [f64; 3],
    pub axes: [u32; 3],
}

/// A Nano-Drive as the three-axis stage.
pub struct MadlibStage {
    lib: Arc<Madlib>,
    /// 0 once released.
    handle: c_int,
    opts: MadlibOptions,
    info: NanoDriveInfo,
    target: Pos,
    /// Set by a fault: the handle was released and this is why.
    fault: Option<DeviceError>,
    move_time_sum: f64,
    moves: u32,
    /// What each Madlib call cost since the last [`Stage::link_costs`] (count, time).
    costs: std::sync::Mutex<crate::instrument::link::LinkCosts>,
    /// Every call's time since connect: (sum s, count), for the move-time model.
    calls: std::sync::Mutex<(f64, u64)>,
    /// The stage's time constant measured on the moves so far: (sum of estimates s, count).
    tau: (f64, u32),
}

/// A move's settling gives a time-constant estimate when its step is at least this many
/// tolerances and its approach was read over a fall of at least this ratio (the log of the
/// ratio, the estimate's divisor, at least ln 10).
const TAU_MIN_RATIO: f64 = 10.0;

/// A reading of the approach is dated to within this fraction of the time between the first
/// and the last reading (half its call's duration), or it is not used for τ: the sensor was
/// read somewhere inside the call, and a host that preempts a call for longer than that would
/// put its reading at the wrong time (two such readings could make τ 25 % wrong).
const TAU_DATING: f64 = 0.05;

/// One reading of the largest step's approach: when its call was made and returned (s since
/// the move's write) and the distance still to go, µm.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Reading {
    t_call: f64,
    t_back: f64,
    to_go: f64,
}

impl Reading {
    fn t(&self) -> f64 {
        0.5 * (self.t_call + self.t_back)
    }
    fn half_width(&self) -> f64 {
        0.5 * (self.t_back - self.t_call).max(0.0)
    }
}

/// The stage's time constant from a move's approach, s: a first-order lag's distance to go
/// falls as exp(−t/τ), so two readings give τ = (t₂ − t₁) / ln(e₁ / e₂), whatever the time the
/// write and the first read took. The two are the first and the last reading dated to within
/// [`TAU_DATING`] of the approach's duration (a call the host stretched is left out), at
/// least [`TAU_MIN_RATIO`] apart in distance to go, so that the dating's error on τ is at
/// most 2 · [`TAU_DATING`]. None when no such pair exists.
fn tau_from_approach(approach: &[Reading]) -> Option<f64> {
    let span = approach.last()?.t() - approach.first()?.t();
    if span <= 0.0 {
        return None;
    }
    let mut dated = approach
        .iter()
        .filter(|r| r.half_width() <= TAU_DATING * span);
    let first = dated.next()?;
    let last = dated.next_back()?;
    let (dt, ratio) = (last.t() - first.t(), first.to_go / last.to_go);
    let dating = first.half_width() + last.half_width();
    (dt > 0.0 && ratio >= TAU_MIN_RATIO && dating <= 2.0 * TAU_DATING * dt).then(|| dt / ratio.ln())
}

impl MadlibStage {
    /// Count one call of `word` that took `since.elapsed()`.
    fn cost(&self, word: &str, since: Instant) {
        let mut c = self.costs.lock().unwrap_or_else(|e| e.into_inner());
        let e = crate::instrument::link::cost_of(&mut c, word);
        let dt = since.elapsed().as_secs_f64();
        e.n += 1;
        e.reply_s += dt;
        let mut a = self.calls.lock().unwrap_or_else(|e| e.into_inner());
        a.0 += dt;
        a.1 += 1;
    }

    /// The mean time of one Madlib call so far (a USB round trip), s; 0 before any.
    pub fn call_s(&self) -> f64 {
        let a = self.calls.lock().unwrap_or_else(|e| e.into_inner());
        if a.1 == 0 {
            0.0
        } else {
            a.0 / a.1 as f64
        }
    }

    /// The stage's first-order time constant measured on the moves so far (the time the
    /// readings took to come within `tolerance_um` of a step d: τ · ln(d / tolerance)), s.
    pub fn tau_s(&self) -> Option<f64> {
        (self.tau.1 > 0).then(|| self.tau.0 / self.tau.1 as f64)
    }

    /// Load Madlib and take the Nano-Drive `opts` names.
    pub fn open(opts: MadlibOptions) -> Result<MadlibStage, DeviceError> {
        let lib = Arc::new(Madlib::load(
            opts.library.as_deref(),
            "Mad City Labs Nano-Drive",
        )?);
        Self::connect(lib, opts)
    }

    /// Take the Nano-Drive `opts` names from an already loaded library: every attached
    /// handle ([`grab_handles`]), the one `opts.serial` names kept and the others released
    /// ([`pick_handle`]), then its product information and calibration read
    /// ([`MadlibStage::read_product`]).
    pub fn connect(lib: Arc<Madlib>, opts: MadlibOptions) -> Result<MadlibStage, DeviceError> {
        let (handle, serial) = pick_handle(&lib, opts.serial)?;
        let name = format!("Mad City Labs Nano-Drive #{serial}");
        // From here on, an error releases `handle` (the stage's Drop).
        let mut stage = MadlibStage {
            lib: lib.clone(),
            handle,
            info: NanoDriveInfo {
                library: lib.path.display().to_string(),
                handle,
                serial,
                product_id: 0,
                axis_bitmap: 0,
                adc_bits: 0,
                dac_bits: 0,
                firmware_version: 0,
                firmware_profile: 0,
                calibration_um: [0.0; 3],
                axes: opts.axes,
            },
            opts,
            target: [0.0; 3],
            fault: None,
            move_time_sum: 0.0,
            moves: 0,
            costs: Default::default(),
            calls: Default::default(),
            tau: (0.0, 0),
        };
        if serial < 0 {
            return Err(madlib_error(
                &name,
                &format!("MCL_GetSerialNumber(handle={handle})"),
                serial,
            ));
        }
        stage.read_product(&name)?;
        // The target starts where the stage is: a relative move starts from there.
        stage.target = stage.read_all()?;
        Ok(stage)
    }

    /// `MCL_GetProductInfo` and, for each configured axis (which the axis bitmap must
    /// list), `MCL_GetCalibration` into [`NanoDriveInfo`].
    fn read_product(&mut self, name: &str) -> Result<(), DeviceError> {
        let (lib, handle) = (self.lib.clone(), self.handle);
        let mut pi = ffi::ProductInformation::default();
        // SAFETY: `int MCL_GetProductInfo(struct ProductInformation *pi, int handle)`.
        let r = unsafe { (lib.get_product_info)(&mut pi, handle) };
        if r != ffi::MCL_SUCCESS {
            return Err(madlib_error(
                name,
                &format!("MCL_GetProductInfo(pi, handle={handle})"),
                r,
            ));
        }
        let bitmap = pi.axis_bitmap;
        self.info.product_id = pi.product_id;
        self.info.axis_bitmap = bitmap;
        self.info.adc_bits = pi.adc_resolution;
        self.info.dac_bits = pi.dac_resolution;
        self.info.firmware_version = pi.firmware_version;
        self.info.firmware_profile = pi.firmware_profile;
        for (k, &a) in self.opts.axes.clone().iter().enumerate() {
            if !(1..=8).contains(&a) || bitmap & (1u8 << (a - 1)) == 0 {
                return Err(DeviceError::Other {
                    device: name.into(),
                    detail: format!(
                        "stage.axes.{} = {a}: this Nano-Drive has axes {} (MCL_GetProductInfo axis bitmap {bitmap:#04x}; 1 = X, 2 = Y, 3 = Z, 4 = A)",
                        crate::instrument::AXES[k],
                        axes_in(bitmap)
                    ),
                });
            }
            // SAFETY: `double MCL_GetCalibration(unsigned int axis, int handle)`.
            let c = unsafe { (lib.get_calibration)(a, handle) };
            let call = format!("MCL_GetCalibration(axis={a}, handle={handle})");
            if let Some(code) = ffi::double_code(c) {
                return Err(madlib_error(name, &call, code));
            }
            if !(c.is_finite() && c > 0.0) {
                return Err(DeviceError::Garbled {
                    device: name.into(),
                    command: call,
                    reply: format!("{c} (a calibrated range in µm must be positive)"),
                });
            }
            self.info.calibration_um[k] = c;
        }
        Ok(())
    }

    /// What connect found (serial, product, calibration), for the scan metadata.
    pub fn info(&self) -> &NanoDriveInfo {
        &self.info
    }

    /// The handle in use; 0 after it was released.
    pub fn handle(&self) -> i32 {
        self.handle
    }

    fn checked(&self) -> Result<(), DeviceError> {
        if let Some(f) = &self.fault {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: format!(
                    "the handle was released after a fault ({f}); connect() again to use the stage"
                ),
            });
        }
        if self.handle == 0 {
            return Err(DeviceError::Other {
                device: self.name(),
                detail: "the handle was released; connect() again to use the stage".into(),
            });
        }
        Ok(())
    }

    /// One axis's reading, µm.
    fn read_axis(&self, k: usize) -> Result<f64, DeviceError> {
        let a = self.opts.axes[k];
        let t = Instant::now();
        // SAFETY: `double MCL_SingleReadN(unsigned int axis, int handle)`.
        let v = unsafe { (self.lib.single_read_n)(a, self.handle) };
        self.cost("MCL_SingleReadN", t);
        let call = || format!("MCL_SingleReadN(axis={a}, handle={})", self.handle);
        if let Some(code) = ffi::double_code(v) {
            return Err(madlib_error(&self.name(), &call(), code));
        }
        if !v.is_finite() {
            return Err(DeviceError::Garbled {
                device: self.name(),
                command: call(),
                reply: format!("{v}"),
            });
        }
        Ok(v)
    }

    fn read_all(&self) -> Result<Pos, DeviceError> {
        Ok([self.read_axis(0)?, self.read_axis(1)?, self.read_axis(2)?])
    }

    fn write_axis(&self, k: usize, um: f64) -> Result<(), DeviceError> {
        let a = self.opts.axes[k];
        let t = Instant::now();
        // SAFETY: `int MCL_SingleWriteN(double position, unsigned int axis, int handle)`.
        let r = unsafe { (self.lib.single_write_n)(um, a, self.handle) };
        self.cost("MCL_SingleWriteN", t);
        if r != ffi::MCL_SUCCESS {
            return Err(madlib_error(
                &self.name(),
                &format!(
                    "MCL_SingleWriteN(position={um:.4}, axis={a}, handle={})",
                    self.handle
                ),
                r,
            ));
        }
        Ok(())
    }

    /// Hold every axis it can read at its reading; returns the first error.
    fn hold(&self) -> Result<(), DeviceError> {
        all_then_first_error(0..3, |k| {
            self.read_axis(k).and_then(|p| self.write_axis(k, p))
        })
    }

    /// After a fault: hold what can be held, release the handle, remember why.
    fn fault(&mut self, e: DeviceError) -> DeviceError {
        if self.handle != 0 {
            let _ = self.hold();
            self.release();
        }
        self.fault = Some(e.clone());
        e
    }

    /// Command axis `k` (0 = x, 1 = y, 2 = z) to `um` over USB (`MCL_SingleWriteN`) and
    /// return at once, without waiting for the readings: a step of a hand-over between the
    /// USB command and the external inputs (`NiStreamStage`), where the position does not
    /// change. Refused outside the calibrated range. A failed write releases the handle
    /// without the usual hold at the readings (the external inputs add to what it would
    /// write).
    pub fn command_now(&mut self, k: usize, um: f64) -> Result<(), DeviceError> {
        self.checked()?;
        self.within_calibration(k, um)?;
        if let Err(e) = self.write_axis(k, um) {
            self.release();
            self.fault = Some(e.clone());
            return Err(e);
        }
        self.target[k] = um;
        Ok(())
    }

    /// Refuses `um` on axis `k` outside the axis's calibrated range 0…`MCL_GetCalibration`.
    fn within_calibration(&self, k: usize, um: f64) -> Result<(), DeviceError> {
        let cal = self.info.calibration_um[k];
        if um.is_finite() && (0.0..=cal).contains(&um) {
            return Ok(());
        }
        Err(DeviceError::Other {
            device: self.name(),
            detail: format!(
                "{} = {um} µm is outside the axis's calibrated range 0–{cal} µm (MCL_GetCalibration)",
                crate::instrument::AXES[k]
            ),
        })
    }

    /// One axis's reading (µm), for [`Self::command_now`]'s callers.
    pub fn read_now(&mut self, k: usize) -> Result<f64, DeviceError> {
        self.checked()?;
        self.read_axis(k)
    }

    /// Release the handle (`MCL_ReleaseHandle`), once.
    pub fn release(&mut self) {
        if self.handle != 0 {
            // SAFETY: `void MCL_ReleaseHandle(int handle)` on the handle we hold.
            unsafe { (self.lib.release_handle)(self.handle) };
            self.handle = 0;
        }
    }

    fn do_move(&mut self, target: Pos, abort: Option<&AtomicBool>) -> Result<bool, DeviceError> {
        self.checked()?;
        for (k, &t) in target.iter().enumerate() {
            self.within_calibration(k, t)?;
        }
        let t0 = Instant::now();
        // only the axes that move are written and watched (a scan's fixed z is neither
        // rewritten nor read back at every point)
        let before = self.target;
        let moved: Vec<usize> = (0..3).filter(|&k| target[k] != self.target[k]).collect();
        let step = moved
            .iter()
            .map(|&k| (target[k] - self.target[k]).abs())
            .fold(0.0, f64::max);
        for &k in &moved {
            if let Err(e) = self.write_axis(k, target[k]) {
                return Err(self.fault(e));
            }
        }
        self.target = target;
        let watch: Vec<usize> = if moved.is_empty() {
            vec![0, 1, 2]
        } else {
            moved
        };
        // the axis with the largest step: its approach (time, distance to go) for the time
        // constant, while it is still well outside the tolerance
        let big = watch
            .iter()
            .copied()
            .max_by(|&a, &b| {
                let d = |k: usize| (target[k] - before[k]).abs();
                d(a).total_cmp(&d(b))
            })
            .unwrap_or(0);
        let mut approach: Vec<Reading> = Vec::new();
        let mut within_before = false;
        let mut last = target;
        loop {
            for &k in &watch {
                let t_call = t0.elapsed().as_secs_f64();
                last[k] = match self.read_axis(k) {
                    Ok(p) => p,
                    Err(e) => return Err(self.fault(e)),
                };
                if k == big {
                    let e = (last[k] - target[k]).abs();
                    if e > 4.0 * self.opts.tolerance_um {
                        approach.push(Reading {
                            t_call,
                            t_back: t0.elapsed().as_secs_f64(),
                            to_go: e,
                        });
                    }
                }
            }
            let within = watch
                .iter()
                .all(|&k| (last[k] - target[k]).abs() <= self.opts.tolerance_um);
            if within && within_before {
                break;
            }
            within_before = within;
            if abort.is_some_and(|a| a.load(Ordering::SeqCst)) {
                return Ok(false);
            }
            if t0.elapsed() > self.opts.on_target_timeout {
                let (k, d) = (0..3)
                    .map(|k| (k, (last[k] - target[k]).abs()))
                    .fold((0, 0.0), |m, x| if x.1 > m.1 { x } else { m });
                let e = DeviceError::Other {
                    device: self.name(),
                    detail: format!(
                        "MCL_SingleReadN(axis={}, handle={}): {} reads {:.4} µm, {:.4} µm from its target {:.4} µm \
                         after {} ms (tolerance {} µm, stage.on_target_timeout_ms): the stage is stuck or \
                         the tolerance is below its noise; the axes were held where they are and the handle released",
                        self.opts.axes[k],
                        self.handle,
                        crate::instrument::AXES[k],
                        last[k],
                        d,
                        target[k],
                        self.opts.on_target_timeout.as_millis(),
                        self.opts.tolerance_um
                    ),
                };
                return Err(self.fault(e));
            }
            if !self.opts.poll_interval.is_zero() {
                std::thread::sleep(self.opts.poll_interval);
            }
        }
        self.move_time_sum += t0.elapsed().as_secs_f64();
        self.moves += 1;
        if step / self.opts.tolerance_um >= TAU_MIN_RATIO {
            if let Some(tau) = tau_from_approach(&approach) {
                self.tau.0 += tau;
                self.tau.1 += 1;
            }
        }
        Ok(true)
    }
}

/// Every Nano-Drive handle the library grants (`MCL_InitLibrary`, `MCL_GrabAllHandles`,
/// `MCL_GetAllHandles`) with its serial number (`MCL_GetSerialNumber`), after the count
/// `MCL_GrabAllHandles` returned.
fn grab_handles(lib: &Madlib) -> Result<(c_int, Vec<c_int>, Vec<c_int>), DeviceError> {
    let dev = "Mad City Labs Nano-Drive";
    if let Some(init) = lib.init_library {
        // SAFETY: `bool MCL_InitLibrary()` of Madlib.h, no arguments.
        unsafe { init() };
    }
    // SAFETY: `int MCL_GrabAllHandles()`.
    let n = unsafe { (lib.grab_all_handles)() };
    if n < 0 {
        return Err(madlib_error(dev, "MCL_GrabAllHandles()", n));
    }
    if n == 0 {
        return Err(DeviceError::Other {
                device: dev.into(),
                detail: format!(
                    "MCL_GrabAllHandles() returned 0: no Nano-Drive attached (library {}). Check the USB \
                     cable and that the controller is switched on; another program (Micro-Manager, the \
                     vendor's utility, a second bfpscope) may hold it",
                    lib.path.display()
                ),
            });
    }
    let mut handles = vec![0 as c_int; n as usize];
    // SAFETY: `int MCL_GetAllHandles(int *handles, int size)`; the buffer has `size` ints.
    let got = unsafe { (lib.get_all_handles)(handles.as_mut_ptr(), n) };
    if got < 0 {
        return Err(madlib_error(
            dev,
            &format!("MCL_GetAllHandles(handles, size={n})"),
            got,
        ));
    }
    handles.truncate(got.clamp(0, n) as usize);
    // SAFETY: `int MCL_GetSerialNumber(int handle)` on handles the library gave.
    let serials: Vec<c_int> = handles
        .iter()
        .map(|&h| unsafe { (lib.get_serial_number)(h) })
        .collect();
    Ok((n, handles, serials))
}

/// The handle of the Nano-Drive `serial` names (the only one attached when unset) with its
/// serial number; every other handle is released, and all of them when none fits.
fn pick_handle(lib: &Madlib, serial: Option<i32>) -> Result<(c_int, c_int), DeviceError> {
    let dev = "Mad City Labs Nano-Drive";
    let (n, handles, serials) = grab_handles(lib)?;
    let release_all_but = |keep: Option<c_int>| {
        for &h in &handles {
            if Some(h) != keep {
                // SAFETY: `void MCL_ReleaseHandle(int handle)`.
                unsafe { (lib.release_handle)(h) };
            }
        }
    };
    let list = serials
        .iter()
        .map(|s| s.to_string())
        .collect::<Vec<_>>()
        .join(", ");
    let pick = match serial {
            Some(want) => serials.iter().position(|&s| s == want).ok_or_else(|| {
                DeviceError::Other {
                    device: dev.into(),
                    detail: format!(
                        "stage.serial = {want}: no Nano-Drive with that serial number is attached (attached: {})",
                        if list.is_empty() { "none".to_string() } else { list.clone() }
                    ),
                }
            }),
            None if handles.len() == 1 => Ok(0),
            None if handles.is_empty() => Err(DeviceError::Other {
                device: dev.into(),
                detail: format!("MCL_GetAllHandles(handles, size={n}) listed no handle"),
            }),
            None => Err(DeviceError::Other {
                device: dev.into(),
                detail: format!(
                    "{} Nano-Drives are attached (serial numbers {list}): name one with `serial = …` in [stage]",
                    handles.len()
                ),
            }),
        };
    let i = match pick {
        Ok(i) => i,
        Err(e) => {
            release_all_but(None);
            return Err(e);
        }
    };
    let handle = handles[i];
    release_all_but(Some(handle));
    Ok((handle, serials[i]))
}

/// The axis numbers set in a product's axis bitmap (`"1, 2, 3"`).
fn axes_in(bitmap: u8) -> String {
    let v: Vec<String> = (1..=8)
        .filter(|a| bitmap & (1u8 << (a - 1)) != 0)
        .map(|a: u32| a.to_string())
        .collect();
    if v.is_empty() {
        "none".into()
    } else {
        v.join(", ")
    }
}

impl Drop for MadlibStage {
    fn drop(&mut self) {
        self.release();
    }
}

impl Stage for MadlibStage {
    fn name(&self) -> String {
        format!("Mad City Labs Nano-Drive #{}", self.info.serial)
    }

    fn position(&mut self) -> Result<Pos, DeviceError> {
        self.checked()?;
        self.read_all().map_err(|e| self.fault(e))
    }

    fn target(&mut self) -> Result<Pos, DeviceError> {
        self.checked()?;
        Ok(self.target)
    }

    fn move_to(&mut self, target: Pos) -> Result<(), DeviceError> {
        self.do_move(target, None).map(|_| ())
    }

    fn move_to_or_abort(&mut self, target: Pos, abort: &AtomicBool) -> Result<bool, DeviceError> {
        self.do_move(target, Some(abort))
    }

    fn travel_range(&mut self) -> Result<[(f64, f64); 3], DeviceError> {
        Ok(self.info.calibration_um.map(|c| (0.0, c)))
    }

    /// Hold every axis at its present reading (never 0 µm). After a fault the handle is
    /// already released and there is nothing to command: Ok.
    fn stop(&mut self) -> Result<(), DeviceError> {
        if self.handle == 0 {
            return Ok(());
        }
        let r = self.hold();
        if let Ok(p) = self.read_all() {
            self.target = p;
        }
        r.map_err(|e| self.fault(e))
    }

    fn link_costs(&mut self) -> crate::instrument::link::LinkCosts {
        std::mem::take(&mut *self.costs.lock().unwrap_or_else(|e| e.into_inner()))
    }

    fn move_time_s(&self) -> f64 {
        if self.moves == 0 {
            0.0
        } else {
            self.move_time_sum / self.moves as f64
        }
    }

    /// The calls of a move at their measured cost and the stage's measured settling: one
    /// `MCL_SingleWriteN` per moving axis, then rounds of one `MCL_SingleReadN` per moving
    /// axis (and the poll interval) until the readings are within `tolerance_um` (after
    /// τ · ln(step / tolerance), at least one round) and one more round to confirm. Before
    /// the time constant is measured: the calls alone.
    fn move_time_for_s(&self, from: Pos, to: Pos) -> f64 {
        let moved = (0..3).filter(|&k| to[k] != from[k]).count();
        if moved == 0 {
            return 0.0;
        }
        let call = self.call_s();
        let step = (0..3).map(|k| (to[k] - from[k]).abs()).fold(0.0, f64::max);
        let settle = match self.tau_s() {
            Some(tau) if step > self.opts.tolerance_um => {
                tau * (step / self.opts.tolerance_um).ln()
            }
            _ => 0.0,
        };
        let round = moved as f64 * call + self.opts.poll_interval.as_secs_f64();
        let rounds = if round > 0.0 {
            (settle / round).ceil().max(1.0) * round
        } else {
            settle
        };
        moved as f64 * call + rounds + round
    }
}

/// A Mad City Labs Nano-Drive through Madlib (the stage), the paper's bench with an NI board. (listed in `instrument::registry`).
/// Mad City Labs Nano-Drive through the vendor's library Madlib: a `[stage]` backend.
pub const MADLIB: crate::instrument::family::Backend = crate::instrument::family::Backend("madlib");

#[cfg(test)]
mod tests {
    use super::*;

    /// An approach read every `every` s with calls of `call` s, the sensor read at the call's
    /// start (as the fake does), τ = 0.5 ms, from 30 µm to go down to 0.2 µm.
    fn approach(every: f64, call: f64) -> Vec<Reading> {
        let tau = 0.5e-3;
        (0..)
            .map(|k| k as f64 * every + 0.1e-3)
            .map(|t| Reading {
                t_call: t,
                t_back: t + call,
                to_go: 30.0 * (-t / tau).exp(),
            })
            .take_while(|r| r.to_go > 0.2)
            .collect()
    }

    #[test]
    fn tau_from_well_dated_readings_is_exact() {
        // readings every 0.1 ms whose calls take 0.05 ms: the midpoint's constant offset
        // cancels in t₂ − t₁
        let tau = tau_from_approach(&approach(0.1e-3, 0.05e-3)).unwrap();
        assert!((tau / 0.5e-3 - 1.0).abs() < 1e-9, "τ {tau}");
    }

    #[test]
    fn a_call_the_host_stretched_is_not_used_to_date_the_approach() {
        // the first reading's call returned 1.2 ms late: dated at its midpoint it would be
        // 0.6 ms late, and τ from it and the last reading 25 % short
        let mut a = approach(0.1e-3, 0.02e-3);
        a[0].t_back += 1.2e-3;
        let naive = (a[a.len() - 1].t() - a[0].t()) / (a[0].to_go / a[a.len() - 1].to_go).ln();
        assert!(naive / 0.5e-3 < 0.8, "the naive estimate {naive}");
        let tau = tau_from_approach(&a).unwrap();
        assert!((tau / 0.5e-3 - 1.0).abs() < 0.1, "τ {tau}");
        // every call stretched that much: no estimate rather than a wrong one
        let slow = approach(0.9e-3, 0.8e-3);
        assert!(slow.len() >= 2);
        assert_eq!(tau_from_approach(&slow), None);
        // too little of the approach read (distance to go falls less than 10×): none either
        assert_eq!(tau_from_approach(&a[a.len() - 3..]), None);
        assert_eq!(tau_from_approach(&[]), None);
    }

    #[test]
    fn errors_name_device_call_code_and_name() {
        let e = madlib_error(
            "Mad City Labs Nano-Drive #2847",
            "MCL_SingleWriteN(position=12.0000, axis=1, handle=3)",
            -3,
        );
        assert_eq!(
            e.to_string(),
            "Mad City Labs Nano-Drive #2847: controller error -3 after `MCL_SingleWriteN(position=12.0000, \
             axis=1, handle=3)`: MCL_DEV_NOT_ATTACHED: the Nano-Drive is not attached (USB unplugged or the \
             controller switched off)"
        );
        assert!(madlib_error("d", "f()", -99).to_string().contains("-99"));
    }

    #[test]
    fn axis_bitmaps_list_their_axes() {
        assert_eq!(axes_in(0b0111), "1, 2, 3");
        assert_eq!(axes_in(0b1000), "4");
        assert_eq!(axes_in(0), "none");
    }
}
